"""The main job: collect expert data if missing, train a policy, fly it against ``expert`` and ``straight``.

Stages, each resumable (a rerun skips what is finished):

1. collect: ``vitfly.sim.collect.collect`` fills the dataset up to ``collect.trajectories``;
2. train: ``vitfly.training.train_policy`` into ``OUT/train`` (resumes from ``last.ckpt``); a
   finished stage leaves ``OUT/train/done.json`` naming the checkpoint;
3. evaluate: the trained policy, then each baseline, over the same scenes into ``OUT/eval``
   (``trials.jsonl`` resumes per trial; trials are keyed by what was flown, so a retrained model, a
   changed expert or changed evaluation settings replace the stale trials of that policy);
4. report: ``OUT/eval/summary.csv``/``.md``, the plots, a depth GIF, the comparison table on the
   console, and ``OUT/pipeline.json`` (success rates by both definitions, whether the policy beat
   ``straight`` by the paper's, timings).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.eval.config import SweepConfig, dataclass_from_dict
from vitfly.packaged import config_path, read_yaml


@dataclass
class TrainStage:
    """Arguments of ``vitfly.training.train_policy``."""

    model: str = "convnet"
    use_state: bool = True
    max_epochs: int = 6
    batch_size: int = 8
    val_fraction: float = 0.2
    seed: int = 0
    policy_kwargs: dict = field(default_factory=dict)  # PolicyModule: lr, warmup_epochs, tbptt_steps, ...
    data_kwargs: dict = field(default_factory=dict)  # TrajectoryDataModule: cache_mb, num_workers, ...
    trainer_kwargs: dict = field(default_factory=dict)  # lightning.Trainer
    select: str = "best"  # the epoch flown: best (lowest validation loss) or last (the original code's)


@dataclass
class EvalStage:
    """The closed-loop comparison (see ``SweepConfig`` for the fields)."""

    env: list[str] = field(default_factory=lambda: ["spheres"])
    preset: str = "medium"
    speeds: list[float] = field(default_factory=lambda: [3.0, 5.0])
    trials: int = 20
    seed: int = 1000  # not the collection seed: the policy flies scenes it has not seen
    num_envs: int = 20
    workers: int = 1
    threads: int = 1
    backend: str = "eager"
    timeout_s: float | None = None
    device: str = "cpu"  # torch device of learned policies
    physics: str = "auto"  # rigid-body back end: pybullet, native or auto
    sim: str = "numpy"  # simulator engine: numpy or batched (vitfly.sim.engine)
    sim_device: str = "cpu"  # the batched engine's device
    sim_dtype: str = "float64"  # the batched engine's precision
    sim_compile: bool = False  # the batched engine's kernels through torch.compile


@dataclass
class PipelineConfig:
    out: str = "runs/quickstart"
    data: str = "data/quickstart_spheres.h5"
    collect_config: str | None = "configs/collect/spheres.yaml"  # base collect YAML
    collect: dict = field(default_factory=dict)  # its overrides: trajectories, speeds, seed, workers, ...
    train: TrainStage = field(default_factory=TrainStage)
    evaluate: EvalStage = field(default_factory=EvalStage)
    baselines: list[str] = field(default_factory=lambda: ["expert", "straight"])
    threads: int = 0  # torch threads for training; 0 = all cores
    wandb_project: str | None = None
    physics: str | None = None  # set: the physics back end of both collect and evaluate (pybullet, native, auto)

    @property
    def train_dir(self) -> Path:
        return Path(self.out) / "train"

    @property
    def eval_dir(self) -> Path:
        return Path(self.out) / "eval"


def load_pipeline_config(path: str | os.PathLike | None, overrides: dict | None = None) -> PipelineConfig:
    """Defaults < YAML (a path or a shipped config's name; sections ``train`` and ``evaluate`` nested) < overrides
    (top-level keys)."""
    path = config_path(path) if path else None
    data = dict(read_yaml(path)) if path else {}
    source = str(path) if path else "pipeline config"
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    train = dataclass_from_dict(TrainStage, data.pop("train", None) or {}, f"{source}: train")
    evaluate = dataclass_from_dict(EvalStage, data.pop("evaluate", None) or {}, f"{source}: evaluate")
    cfg = dataclasses.replace(dataclass_from_dict(PipelineConfig, data, source), train=train, evaluate=evaluate)
    if cfg.physics is not None:  # one back end for both stages
        cfg = dataclasses.replace(cfg, collect={**cfg.collect, "physics": cfg.physics},
                                  evaluate=dataclasses.replace(cfg.evaluate, physics=cfg.physics))
    for name in cfg.baselines:
        if name not in ("expert", "straight"):
            raise VitflyError(f"{source}: field 'baselines' has {name!r}; expected expert and/or straight")
    from vitfly.zoo import list_models

    if cfg.train.model not in list_models():
        raise VitflyError(f"{source}: train.model {cfg.train.model!r} unknown; known: {', '.join(list_models())}")
    sweep_config(cfg.evaluate, cfg.eval_dir, "expert").validate(f"{source}: evaluate")
    return cfg


def sweep_config(e: EvalStage, out_dir: str | Path, policy: str, name: str | None = None,
                 gif: bool = False) -> SweepConfig:
    """The sweep of one policy with the evaluation stage's settings, into ``out_dir``.

    ``overwrite`` is on: the stage owns ``out_dir``, and trials of a label flown with another setup
    there (the model before a retrain, other evaluation settings) are stale.
    """
    return SweepConfig(policy=policy, name=name, env=list(e.env), preset=e.preset, speeds=list(e.speeds),
                       trials=e.trials, seed=e.seed, out=str(out_dir), num_envs=e.num_envs, workers=e.workers,
                       threads=e.threads, backend=e.backend, timeout_s=e.timeout_s, gif=gif, plots=False,
                       overwrite=True, device=e.device, physics=e.physics, sim=e.sim, sim_device=e.sim_device,
                       sim_dtype=e.sim_dtype, sim_compile=e.sim_compile)


def stage_collect(collect_config: str | None, overrides: dict, data: str | Path, progress: bool = True) -> dict:
    """Fill ``data`` with expert trajectories up to the configured count (nothing to do if complete)."""
    from vitfly.datamodules.schema import open_trajectories
    from vitfly.sim.collect import collect, load_collect_config, stored_collect_key

    collect_cfg = load_collect_config(collect_config, overrides)
    if Path(data).exists():
        # complete with these settings: only read it (a reader elsewhere in this process blocks writers)
        try:
            with open_trajectories(data, check_values=False) as f:
                n, frames, stored = len(f), f.num_rows, stored_collect_key(f.config.get("collect"))
        except VitflyError:  # e.g. empty: killed before its first trajectory; collect resumes it or says why not
            n = frames = 0
            stored = None
        if n >= collect_cfg.trajectories and stored == json.loads(json.dumps(collect_cfg.content_key())):
            print(f"[collect] {data}: complete, {n} trajectories (0 new), {frames} frames")
            return {"trajectories": n, "new": 0, "frames": frames}
    Path(data).parent.mkdir(parents=True, exist_ok=True)
    summary = collect(collect_cfg, data, progress=progress)
    ok = sum(s for s, _ in summary.success_by_speed.values())
    print(f"[collect] {summary.path}: {summary.trajectories} trajectories ({summary.new_trajectories} new), "
          f"{summary.frames} frames, expert success {ok}/{summary.trajectories}")
    return {"trajectories": summary.trajectories, "new": summary.new_trajectories, "frames": summary.frames}


def stage_train(t: TrainStage, data: str | Path, train_dir: Path, threads: int = 0, progress: bool = True,
                callbacks: list | None = None) -> Path:
    """Train (or resume, or skip if done with the same settings); return the best checkpoint.

    ``callbacks`` join the Trainer's (they are not part of the settings a finished run is compared by).
    """
    done = finished_checkpoint(t, data, train_dir)
    if done is not None:
        print(f"[train] done before: {done}")
        return done
    # not started, or finished with other settings (e.g. fewer epochs): train_policy goes on from last.ckpt
    import torch

    from vitfly.training import train_policy

    torch.set_num_threads(threads or os.cpu_count() or 1)
    ckpt = train_policy(data, t.model, train_dir, use_state=t.use_state, max_epochs=t.max_epochs,
                        batch_size=t.batch_size, val_fraction=t.val_fraction, seed=t.seed,
                        policy_kwargs=t.policy_kwargs, data_kwargs=t.data_kwargs,
                        trainer_kwargs={"enable_model_summary": False, **t.trainer_kwargs}, progress_bar=progress,
                        callbacks=callbacks, select=t.select)
    write_text(Path(train_dir) / "done.json", json.dumps({"checkpoint": str(ckpt), "train": train_settings(t, data)})
               + "\n")
    print(f"[train] {t.model} (use_state={t.use_state}): {ckpt}")
    return ckpt


def finished_checkpoint(t: TrainStage, data: str | Path, train_dir: Path) -> Path | None:
    """The best checkpoint of the run in ``train_dir`` if it finished with ``t``'s settings on ``data``, else None
    (a run folder of other data is refused)."""
    marker = Path(train_dir) / "done.json"
    check_trained_data(Path(train_dir), data)
    if marker.exists():
        done = json.loads(marker.read_text())
        if same_settings(done.get("train"), train_settings(t, data)) and Path(done["checkpoint"]).exists():
            return Path(done["checkpoint"])
    return None


def train_settings(t: TrainStage, data: str | Path) -> dict:
    """What a finished run's ``done.json`` records as its settings (a run with other settings is resumed)."""
    return dataclasses.asdict(t) | {"data": str(data)}


# Trainer arguments that change what a run logs, never the weights it trains (the validation loaders draw from
# a generator of their own: vitfly.datamodules.datamodule), as long as no epoch is chosen by its validation loss
VALIDATION_ONLY = ("check_val_every_n_epoch",)
# Data arguments that change how many trajectories a validation call takes, never its metrics (masked means over
# the valid steps: tests/test_static_shapes.py) nor the weights, so in either select mode
VALIDATION_BATCHING = ("val_batch_size", "cpu_val_batch_size")


def same_settings(recorded: dict | None, wanted: dict) -> bool:
    """A finished run's recorded settings are ``wanted``; a field added to TrainStage since it was recorded counts
    as its default, so that a new field never retrains the runs finished before it. How a run batched its
    validation (``VALIDATION_BATCHING``) does not count, and with ``select: last`` neither does how often it
    validated (``VALIDATION_ONLY``): the weights are the same either way."""
    if recorded is None:
        return False
    defaults = dataclasses.asdict(TrainStage())
    recorded = {**{k: defaults[k] for k in wanted.keys() - recorded.keys() if k in defaults}, **recorded}
    return _weights_settings(recorded) == _weights_settings(wanted)


def _weights_settings(settings: dict) -> dict:
    """``settings`` less what cannot change the flown weights."""
    data = {k: v for k, v in (settings.get("data_kwargs") or {}).items() if k not in VALIDATION_BATCHING}
    settings = {**settings, "data_kwargs": data}
    if settings.get("select") != "last":
        return settings
    trainer = {k: v for k, v in (settings.get("trainer_kwargs") or {}).items() if k not in VALIDATION_ONLY}
    return {**settings, "trainer_kwargs": trainer}


@functools.lru_cache(maxsize=8)
def _fingerprint(path: str, size: int, mtime_ns: int) -> dict:
    """The dataset's fingerprint, read once per file version: a study checks one file for every run."""
    from vitfly.datamodules.provenance import dataset_fingerprint

    return dataset_fingerprint(path)


def check_trained_data(train_dir: Path, data: str | Path) -> None:
    """Record in ``train_dir/data.json`` which dataset (its hash) a training uses, or check the record.

    A run folder, finished or not, belongs to the data it was trained on: the same path holding other bytes
    (collected again, on another physics back end, with more trajectories) is one line naming both hashes,
    never a silent resume or a "done before". A folder trained before vitfly kept this record is taken as
    trained on ``data`` and says so.
    """
    record = train_dir / "data.json"
    stat = os.stat(data)
    now = _fingerprint(os.path.realpath(data), stat.st_size, stat.st_mtime_ns)
    if record.exists():
        then = json.loads(record.read_text())
        if then.get("dataset_hash") != now["dataset_hash"]:
            raise VitflyError(
                f"{train_dir}: trained on dataset_hash {then.get('dataset_hash')} ({then.get('data')}), but {data} "
                f"now has {now['dataset_hash']}; move the folder aside to train afresh on this data, or point "
                "the run at the data it was trained on")
        return
    if (train_dir / "done.json").exists() or (train_dir / "checkpoints" / "last.ckpt").exists():
        print(f"[train] {train_dir}: no record of its data (trained before vitfly kept one); taken as trained on "
              f"{data} ({now['dataset_hash']})")
    train_dir.mkdir(parents=True, exist_ok=True)
    write_text(record, json.dumps({"data": str(data), **now}) + "\n")


def stage_evaluate(e: EvalStage, out_dir: Path, policies: list[tuple[str, str | None]], progress: bool = True,
                   gif_for: int | None = 0) -> None:
    """Fly each (policy, label) over the same scenes into ``out_dir``; a depth GIF of ``policies[gif_for]``.

    A policy whose trials in ``out_dir`` were flown with another setup (a retrained checkpoint: its
    weights hash differs) has them replaced and is flown again.
    """
    from vitfly.eval.evaluation import depth_gif
    from vitfly.eval.sweep import run_sweep

    identities = []
    for policy, name in policies:
        sweep = sweep_config(e, out_dir, policy, name)
        outcome = run_sweep(sweep, progress=progress)
        identities.append(outcome.identity)
        replaced = f", {outcome.replaced} stale trials (another setup) replaced" if outcome.replaced else ""
        print(f"[evaluate] {sweep.label}: {outcome.flown} trials flown, {outcome.skipped} done before{replaced}")
    if gif_for is not None:
        depth_gif(sweep_config(e, out_dir, *policies[gif_for], gif=True), identity=identities[gif_for])


def success_by_policy(rows: list[dict], column: str = "success_paper_rate") -> dict[str, float]:
    """Success rate over all of a policy's trials (every env and speed), by the paper's definition (no
    collision) or, with ``column="success_strict_rate"``, the strict one (goal reached and no collision)."""
    totals: dict[str, list[float]] = {}
    for r in rows:
        t = totals.setdefault(r["policy"], [0.0, 0.0])
        t[0] += r[column] * r["trials"]
        t[1] += r["trials"]
    return {p: s / n for p, (s, n) in totals.items() if n}


def run_pipeline(cfg: PipelineConfig, progress: bool = True) -> dict:
    """All stages; returns (and writes to ``OUT/pipeline.json``) the outcome."""
    from vitfly.eval.evaluation import write_outputs
    from vitfly.eval.report import print_table

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    collected = stage_collect(cfg.collect_config, cfg.collect, cfg.data, progress)
    timings["collect_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    checkpoint = stage_train(cfg.train, cfg.data, cfg.train_dir, cfg.threads, progress)
    timings["train_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    learned = (str(checkpoint), cfg.train.model)
    stage_evaluate(cfg.evaluate, cfg.eval_dir, [learned, *((b, None) for b in cfg.baselines)], progress)
    timings["evaluate_s"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    rows, files = write_outputs(cfg.eval_dir, with_plots=True, title="vitfly quick start")
    files.update({p.stem: p for p in sorted(cfg.eval_dir.glob("depth_*.gif"))})
    timings["report_s"] = time.perf_counter() - t3
    timings["total_s"] = time.perf_counter() - t0
    success = success_by_policy(rows)
    strict = success_by_policy(rows, "success_strict_rate")
    model = cfg.train.model
    beat = "straight" in success and success.get(model, 0.0) > success["straight"]
    beat_strict = "straight" in strict and strict.get(model, 0.0) > strict["straight"]
    print_table(rows, title=f"{model} vs {', '.join(cfg.baselines)} ({cfg.eval_dir})")
    line = ", ".join(f"{p} {100 * s:.0f} %" for p, s in sorted(success.items()))
    line_strict = ", ".join(f"{p} {100 * s:.0f} %" for p, s in sorted(strict.items()))
    verdict = "beats" if beat else "does NOT beat"
    print(f"success over all trials (paper: no collision): {line}; {model} {verdict} straight. "
          f"Strict (goal reached, no collision): {line_strict}. Took {timings['total_s']:.0f} s.")
    outcome = {
        "checkpoint": str(checkpoint),
        "dataset": cfg.data,
        "collected": collected,
        "success_paper": success,  # no collision (the paper's definition)
        "success_strict": strict,  # goal reached and no collision
        "beats_straight": bool(beat),  # by the paper's definition
        "beats_straight_strict": bool(beat_strict),
        "timings_s": timings,
        "files": {k: str(v) for k, v in files.items()},
        "config": dataclasses.asdict(cfg),
    }
    write_text(Path(cfg.out) / "pipeline.json", json.dumps(outcome, indent=2) + "\n")
    if cfg.wandb_project:
        from vitfly.eval.wandb_log import log_evaluation

        images = {k: Path(v) for k, v in files.items() if Path(v).suffix in (".png", ".gif")}
        log_evaluation(cfg.wandb_project, rows, images, cfg.out, run_name="pipeline", config=outcome["config"])
    print("wrote " + ", ".join(str(p) for p in [*files.values(), Path(cfg.out) / "pipeline.json"]))
    return outcome
