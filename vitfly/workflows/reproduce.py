"""``vitfly reproduce``: the paper's results section in one resumable command.

Stages (each resumes after a kill; a rerun skips what is done with the same settings):

1. ``data``: expert trajectories in spheres (``vitfly.workflows.pipeline.stage_collect``);
2. ``train``: every model with the state input and the no-state ones, each from its recipe
   ``configs/fit/<model>.yaml`` with the preset's overrides (``stage_train``: resumes from
   ``last.ckpt``), into ``OUT/train/<model>-state`` and ``OUT/train/<model>-nostate``; with
   ``train.publish_weights`` each finished state model is published as ``pretrained:<model>``; then the other
   training draws of ``train.draws`` (another seed each) into ``OUT/train/<model>-state-s<seed>``, flown in
   every sweep of their run as ``<run>-s<seed>``;
3. ``evaluate``: ``OUT/eval/spheres`` and ``OUT/eval/trees`` (every state model, expert, straight, at
   ``evaluate.speeds``), ``OUT/eval/window`` (3 m/s) and ``OUT/eval/ablation`` (with and without state,
   spheres and trees); sweeps resume per trial (``stage_evaluate``);
4. ``paths``: repeated trials of one fixed spheres scene (``vitfly.eval.repeats``) into ``OUT/eval/paths``;
5. ``modular``: the modular baselines (``modular:NAME``, ``vitfly.planners``) beside ``modular.models`` and
   ``modular.baselines`` in spheres at ``modular.speeds``, all on the scenes of one sweep seed, into
   ``OUT/eval/modular`` (resumes per trial);
6. ``latency``: the latency table (``vitfly.eval.latency.benchmark_model``) into ``OUT/latency.json``;
7. ``report``: the paper's figures in ``OUT/figures``, ``OUT/ablation.md``, ``OUT/latency.md``,
   ``OUT/results.md`` (each finding of the paper with ours beside it and a verdict,
   ``vitfly.eval.findings``) and ``OUT/results.json``.

Configuration: ``configs/reproduce.yaml``; its ``presets`` section (``tiny``, ``laptop``, ``paper``) is
deep-merged over the top level. Unknown keys anywhere are one clear error.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.training.run_lock import RunBusy
from vitfly.workflows.pipeline import (
    EvalStage,
    TrainStage,
    finished_checkpoint,
    stage_collect,
    stage_evaluate,
    stage_train,
)
from vitfly.workflows.reproduce_config import (
    STAGES,
    ReproduceConfig,
    Run,
    done_checkpoint,
    eval_stage,
    modular_stage,
    paths_plan,
    runs,
    split_callbacks,
    train_callbacks,
    train_frames,
    train_stage,
)
from vitfly.workflows.reproduce_report import stage_report


def stage_data(cfg: ReproduceConfig, progress: bool = True) -> dict:
    return stage_collect(cfg.collect_config, cfg.collect, cfg.data, progress)


def _fit_seconds(train_dir: Path) -> float:
    """Seconds of fitting that ``last.ckpt`` records (Lightning's ``Timer``, kept across resumes); 0 without it."""
    import torch

    last = train_dir / "checkpoints" / "last.ckpt"
    if not last.exists():
        return 0.0
    # mmap: only the callbacks' few bytes are read, not the weights and optimiser state
    timer = torch.load(last, map_location="cpu", weights_only=True, mmap=True).get("callbacks", {}).get("Timer")
    return float(timer["time_elapsed"]["train"]) if timer else 0.0


def _add_cost(train_dir: Path, seconds: float, fit_before_s: float) -> dict:
    """Add a finished training session's wall time to ``cost.json``.

    A killed session never gets here, but the checkpoint it left carries its fitting time (the ``Timer``):
    ``fit_before_s`` (``_fit_seconds`` before this session) beyond the ``fit_s`` that the last finished session
    recorded is such time, counted up to the killed session's last checkpoint (its later work is redone).
    """
    path = train_dir / "cost.json"
    cost = json.loads(path.read_text()) if path.exists() else {"wall_s": 0.0, "sessions": 0, "fit_s": 0.0}
    killed_s = max(0.0, fit_before_s - cost.get("fit_s", fit_before_s))  # an older cost.json: nothing known lost
    cost = {"wall_s": cost["wall_s"] + seconds + killed_s, "sessions": cost["sessions"] + 1,
            "fit_s": _fit_seconds(train_dir), "killed_s": cost.get("killed_s", 0.0) + killed_s}
    write_text(path, json.dumps(cost) + "\n")
    return cost


def stage_train_all(cfg: ReproduceConfig, progress: bool = True) -> dict[str, Path]:
    """Train (or resume, or skip) every run, then the other draws; returns label -> checkpoint. Publishes the
    study's own state models if asked."""
    checkpoints, busy = {}, []
    for run in runs(cfg):
        model, use_state = run.model, run.use_state
        recipe = train_stage(cfg, model, use_state, seed=run.seed)
        stage, train_dir = split_callbacks(recipe)[0], cfg.train_dir(*run)
        ckpt = finished_checkpoint(stage, cfg.data, train_dir)
        if ckpt is not None:  # its callbacks are not built: a rerun of a finished study needs no Lightning
            print(f"[train] done before: {ckpt}")
        else:
            stage, callbacks = train_callbacks(recipe, cfg, "reproduce config")
            fit_before_s = _fit_seconds(train_dir)
            t0 = time.perf_counter()
            try:
                ckpt = stage_train(stage, cfg.data, train_dir, cfg.threads, progress, callbacks=callbacks)
            except RunBusy as e:  # a second `vitfly reproduce` on the study trains the runs the first is not on
                print(f"[train] {train_dir}: skipped here, {e.who} trains it")
                busy.append(train_dir.name)
                continue
            cost = _add_cost(train_dir, time.perf_counter() - t0, fit_before_s)
            killed = f" ({cost['killed_s'] / 60:.1f} of them in killed sessions)" if cost["killed_s"] else ""
            print(f"[train] {run.label}: {cost['wall_s'] / 60:.1f} min of training so far{killed}")
        checkpoints[run.label] = ckpt
        if use_state and run.seed is None and cfg.train.publish_weights and model in cfg.train.publish_models:
            publish(cfg, model, ckpt, stage)
    if busy:
        raise RunsBusy(busy)
    return checkpoints


class RunsBusy(VitflyError):
    """The train stage trained what it could; other processes still train the runs in the folders ``names``."""

    def __init__(self, names: list[str]):
        super().__init__(f"train: {', '.join(names)} still training in another process; run this command again "
                         "when it ends (the runs finished here are kept)")
        self.names = names


def trained_checkpoints(cfg: ReproduceConfig) -> dict[str, Path | str]:
    """label -> checkpoint of every finished training (one line naming the first missing one); with
    ``train.source: pretrained``, label -> ``pretrained:<model>`` (a missing weights file is one line)."""
    if cfg.train.source == "pretrained":
        from vitfly.zoo.pretrained import manifest_entry

        for model in cfg.train.models:
            manifest_entry(model, cfg.train.weights_dir)
        return {model: f"pretrained:{model}" for model in cfg.train.models}
    out = {}
    for run in runs(cfg):
        ckpt = done_checkpoint(cfg.train_dir(*run))
        if ckpt is None:
            raise VitflyError(f"{cfg.train_dir(*run)}: {run.label} is not trained yet; run the train stage first "
                              "(vitfly reproduce --stages train)")
        out[run.label] = ckpt
    return out


def publish(cfg: ReproduceConfig, model: str, ckpt: Path, stage: TrainStage) -> None:
    """``pretrained:<model>`` from ``ckpt`` (skipped if the manifest already holds this checkpoint's state)."""
    import torch

    from vitfly.datamodules.provenance import dataset_fingerprint
    from vitfly.zoo.pretrained import read_manifest, save_pretrained

    saved = torch.load(ckpt, map_location="cpu", weights_only=True)
    entry = read_manifest(cfg.train.weights_dir, missing_ok=True)["models"].get(model) or {}
    if entry.get("source_checkpoint") == str(ckpt.resolve()) and entry.get("steps") == saved.get("global_step"):
        return
    train_dir = cfg.train_dir(model, True)
    cost = json.loads((train_dir / "cost.json").read_text()) if (train_dir / "cost.json").exists() else {}
    fields = {"preset": cfg.preset, **dataset_fingerprint(cfg.data), "train_frames": train_frames(train_dir, cfg.data),
              "train_wall_s": cost.get("wall_s"), "recipe": dataclasses.asdict(stage)}
    path = save_pretrained(ckpt, model, fields, cfg.train.weights_dir)
    print(f"[train] published {model} as pretrained:{model} ({path})")


def evaluation_plan(cfg: ReproduceConfig, checkpoints: dict[str, Path]) -> dict[str, tuple[EvalStage, list]]:
    """Sweep name -> (settings, [(policy, label)]) of the study: every draw flies beside its run (the study's own
    runs first, so an interrupted sweep has them all)."""
    e = cfg.evaluate
    every = runs(cfg)
    state = [(str(checkpoints[r.label]), r.label) for r in every if r.use_state]
    baselines = [(b, None) for b in e.baselines]
    compared = [Run(m, s) for m in cfg.train.nostate_models for s in (True, False)]
    drawn = [r for r in every if r.seed is not None and r._replace(seed=None) in compared]
    ablation = [(str(checkpoints[r.label]), r.label) for r in compared + drawn]
    return {
        "spheres": (eval_stage(cfg, ["spheres"], e.speeds, e.spheres_trials), state + baselines),
        "trees": (eval_stage(cfg, ["trees"], e.speeds, e.trees_trials), state + baselines),
        "window": (eval_stage(cfg, ["window"], e.window_speeds, e.window_trials), state + baselines),
        "ablation": (eval_stage(cfg, ["spheres", "trees"], e.ablation_speeds, e.ablation_trials), ablation),
    }


def stage_evaluate_all(cfg: ReproduceConfig, checkpoints: dict[str, Path], progress: bool = True) -> None:
    from vitfly.eval.evaluation import write_outputs

    for name, (stage, policies) in evaluation_plan(cfg, checkpoints).items():
        if not policies:
            continue
        stage_evaluate(stage, cfg.eval_dir(name), policies, progress, gif_for=None)
        write_outputs(cfg.eval_dir(name), with_plots=True, title=f"reproduce ({cfg.preset}): {name}")


def stage_paths(cfg: ReproduceConfig, checkpoints: dict[str, Path]) -> None:
    from vitfly.eval.repeats import fly_repeats

    plan = paths_plan(cfg)
    for policy, label in [(str(checkpoints[m]), m) for m in cfg.train.models] + [(b, b) for b in cfg.paths.baselines]:
        flown, before = fly_repeats(plan, policy, cfg.eval_dir("paths"), label, cfg.evaluate.threads)
        print(f"[paths] {label}: {flown} repeats flown, {before} done before")


def modular_plan(cfg: ReproduceConfig, checkpoints: dict[str, Path | str]) -> list[tuple[str, str, str | None]]:
    """(policy, label, planners YAML) of the modular comparison, flown on the same scenes: the learned models and
    the baselines first (cheap: an interrupted study has them to pair with), then the planners."""
    m = cfg.modular
    return ([(str(checkpoints[model]), model, None) for model in m.models if model in checkpoints]
            + [(b, b, None) for b in m.baselines] + [(f"modular:{p}", p, m.planner_config) for p in m.planners])


def stage_modular(cfg: ReproduceConfig, checkpoints: dict[str, Path | str], progress: bool = True) -> None:
    """Fly the modular comparison into ``OUT/eval/modular`` (each sweep resumes per trial), then its summary."""
    from vitfly.eval.evaluation import write_outputs
    from vitfly.eval.sweep import run_sweep
    from vitfly.workflows.pipeline import sweep_config

    m, out = cfg.modular, cfg.eval_dir("modular")
    if not m.planners:
        print("[modular] no planners configured (modular.planners): nothing to fly")
        return
    missing = [model for model in m.models if model not in checkpoints]
    if missing:
        print(f"[modular] {', '.join(missing)}: not in train.models, left out of the modular comparison")
    for policy, name, planner_config in modular_plan(cfg, checkpoints):
        speeds = m.speeds_of(name) if policy.startswith("modular:") else [float(v) for v in m.speeds]
        sweep = dataclasses.replace(sweep_config(modular_stage(cfg, speeds), out, policy, name),
                                    planner_config=planner_config)
        outcome = run_sweep(sweep, progress=progress)
        replaced = f", {outcome.replaced} stale trials (another setup) replaced" if outcome.replaced else ""
        print(f"[modular] {sweep.label}: {outcome.flown} trials flown, {outcome.skipped} done before{replaced}")
    write_outputs(out, with_plots=False, title=f"reproduce ({cfg.preset}): modular baselines")


def _latency_key(cfg: ReproduceConfig, devices: list[str]) -> dict:
    return {"models": list(cfg.train.models), "devices": devices, **dataclasses.asdict(cfg.latency)}


def stage_latency(cfg: ReproduceConfig) -> list[dict]:
    """The latency table of the trained architectures (random weights: latency does not depend on them)."""
    import torch

    from vitfly.eval.latency import benchmark_model

    lat = cfg.latency
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else []) if lat.device == "auto" else [lat.device]
    path = cfg.out_dir / "latency.json"
    key = _latency_key(cfg, devices)
    if path.exists():
        stored = json.loads(path.read_text())
        if stored.get("settings") == key:
            print(f"[latency] done before: {path}")
            return stored["results"]
    results = []
    for model in cfg.train.models:
        for device in devices:
            r = benchmark_model(model, lat.backend, device, lat.threads, lat.iters, lat.warmup)
            results.append(r.to_dict())
            print(f"[latency] {model} {device}: median {r.median_ms:.2f} ms")
    write_text(path, json.dumps({"settings": key, "results": results}, indent=2) + "\n")
    return results


def run_reproduce(cfg: ReproduceConfig, stages: list[str] | None = None, progress: bool = True) -> dict:
    """Run ``stages`` (default: all, in order); returns what the report stage wrote (or {})."""
    stages = list(stages or STAGES)
    for s in stages:
        if s not in STAGES:
            raise VitflyError(f"--stages: unknown stage {s!r}; stages are {', '.join(STAGES)}")
    timings: dict[str, float] = {}
    checkpoints = None
    for s in STAGES:
        if s not in stages:
            continue
        t0 = time.perf_counter()
        if s == "data" and cfg.train.source == "pretrained":
            print("[data] train.source pretrained: no training data needed")
        elif s == "data":
            stage_data(cfg, progress)
        elif s == "train" and cfg.train.source == "pretrained":
            checkpoints = trained_checkpoints(cfg)
            print(f"[train] train.source pretrained: flying the shipped weights of {', '.join(checkpoints)}")
        elif s == "train":
            checkpoints = stage_train_all(cfg, progress)
        elif s in ("evaluate", "paths", "modular"):
            checkpoints = checkpoints or trained_checkpoints(cfg)
            if s == "evaluate":
                stage_evaluate_all(cfg, checkpoints, progress)
            elif s == "paths":
                stage_paths(cfg, checkpoints)
            else:
                stage_modular(cfg, checkpoints, progress)
        elif s == "latency":
            stage_latency(cfg)
        timings[s] = time.perf_counter() - t0
        if s != "report":
            print(f"[{s}] {timings[s]:.0f} s")
    result = stage_report(cfg) if "report" in stages else {}
    return result

