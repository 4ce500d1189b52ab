"""``vitfly dagger``: DAgger with the privileged expert, beside behaviour cloning at equal labelled frames.

Round 0 flies the expert (beta_0 = 1: the expert's own flights, behaviour-cloning data) and trains a student
from scratch (or from ``train.init_checkpoint``). Round i >= 1 flies round i-1's student in fresh training
scenes, mixed with the expert per env and tick with probability beta_i (``vitfly.sim.MixturePolicy``); the
expert labels every visited state. The round's trajectories are appended to the same dataset, each tagged
with its round and beta (schema v1's optional fields; the flown command is kept in
``/velocity_cmd_executed``, the label in ``/velocity_cmd``), and round i-1's student is fine-tuned on the
aggregate into round i's student.

The baseline, behaviour cloning at an equal number of expert-labelled frames: its dataset holds round 0's
flights and, for each round i, extra expert flights until it holds exactly as many frames as DAgger's after
round i (the last flight is cut to the frame); round i-1's baseline student is fine-tuned on it for exactly
as many optimiser steps as DAgger's round i took. Same architecture, same schedule, same validation
trajectories (round 0's), only the data differ. Every round's students fly the held-out evaluation scenes.

Layout of ``OUT``::

    data/dagger.h5, data/bc.h5       the aggregated datasets (appends are atomic per trajectory)
    train/r0, train/dagger-rI, train/bc-rI   runs; checkpoints/last.ckpt: the weights each ended with
    eval/trials.jsonl                every round's students and the baselines on the same scenes
    paths/trials.jsonl               repeats of one evaluation scene by the last round's students
    manifests/<stage>.json           what each stage was run with (its fingerprint) and what it produced
    dagger.md, dagger.csv, dagger.json, success_vs_frames.png, paths_<env>.png   the report

Resuming: every stage is recorded in ``manifests/<stage>.json`` with the fingerprint of everything that
decides its result (its settings and the fingerprints of the stages it builds on). A rerun skips a stage
whose manifest says done with the same fingerprint, resumes one that was interrupted (flights already
committed to the dataset are not flown again; training resumes from its ``last.ckpt``; evaluation per trial),
recomputes a training or evaluation stage whose settings changed, and refuses (one line, before anything
runs) when a round's flights in a dataset were made with other settings than the config now gives them:
they are never silently reused.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.workflows.dagger_config import DaggerConfig, base_collect, eval_stage, paths_plan, student_label
from vitfly.workflows.dagger_stages import (
    Stage,
    check_existing,
    data_path,
    final_checkpoint,
    plan_stages,
    read_stage_manifest,
    rounds_in,
    train_dir,
    train_settings,
    write_stage_manifest,
)

DAGGER_FIELDS = ("velocity_cmd_executed", "dagger_round", "dagger_beta")


# -------------------------------------------------------------------------------------------------
# collection


def _check_disjoint(cfg: DaggerConfig, scene_seed: int, eval_seeds: set[int], what: str) -> None:
    if scene_seed in eval_seeds:
        raise VitflyError(f"{what}: scene seed {scene_seed} is also an evaluation scene (evaluate.seed "
                          f"{cfg.evaluate.seed}); choose another data.seed")


def evaluation_scene_seeds(cfg: DaggerConfig) -> set[int]:
    """Scene seeds of every evaluated scene: the sweep's trials and the paths' scene."""
    from vitfly.eval.sweep import derive_scene_seed

    e = cfg.evaluate
    seeds = {derive_scene_seed(e.seed, env, k) for env in e.env for k in range(e.trials)}
    seeds |= {derive_scene_seed(e.seed, env, cfg.paths.scene_trial) for env in e.env}
    return seeds


def _writer(cfg: DaggerConfig, baseline: bool, collect_cfg):
    from vitfly.datamodules.schema import TrajectoryWriter

    meta = {"made_by": "vitfly dagger", "dataset": "baseline (expert only)" if baseline else "dagger",
            "collect": {k: v for k, v in collect_cfg.content_key().items() if k != "seed"}}
    return TrajectoryWriter(data_path(cfg, baseline), config=meta, depth_max_m=collect_cfg.camera.max_range_m,
                            depth_compression=collect_cfg.depth_compression,
                            camera=dataclasses.asdict(collect_cfg.camera), control_hz=collect_cfg.control_hz,
                            optional_fields=DAGGER_FIELDS)


def episode_record(collect_cfg, result, round_index: int, beta: float):
    """A flown episode as a dataset record: the expert's labels in ``velocity_cmd``, the flown commands in
    ``velocity_cmd_executed``, only the ticks the collection logs (``CollectConfig.logged_ticks``)."""
    from vitfly.datamodules.schema import TrajectoryRecord, encode_depth

    log, summary = result.log, result.summary
    rows = collect_cfg.logged_ticks(log.position[:, 0])
    label = log.command if log.label is None else log.label
    return TrajectoryRecord(
        depth=encode_depth(log.depth[rows]), desired_speed=summary.desired_speed, quat=log.quat[rows],
        position=log.position[rows], velocity=log.velocity[rows], velocity_cmd=label[rows], time=log.time[rows],
        collision=log.contact[rows], env=summary.env, seed=summary.seed, n_collisions=summary.n_collisions,
        success=summary.success, velocity_cmd_executed=log.command[rows], dagger_round=round_index,
        dagger_beta=beta)


def _expert_record(rec, round_index: int):
    """A record flown by the expert alone (``vitfly collect``'s) with the DAgger fields: flown = label, beta 1."""
    return dataclasses.replace(rec, velocity_cmd_executed=np.asarray(rec.velocity_cmd).copy(),
                               dagger_round=round_index, dagger_beta=1.0)


def _load_student(cfg: DaggerConfig, checkpoint: Path | str):
    from vitfly.eval.learned_policy import LearnedPolicy
    from vitfly.zoo.pretrained import load_weights

    return LearnedPolicy(load_weights(checkpoint), device=cfg.evaluate.device)


def stage_collect(cfg: DaggerConfig, stage: Stage, student: Path | str | None, progress: bool = True,
                  on_trajectory: Callable[[int], None] | None = None) -> dict:
    """Fly round ``stage.round``'s trajectories not yet in the DAgger dataset and append each as it ends."""
    from vitfly.sim.collect import ordered_records, start_pool, trajectory_spec
    from vitfly.sim.engine import fly
    from vitfly.sim.policies import ExpertPolicy, MixturePolicy
    from vitfly.sim.scenes import make_scene

    r = stage.round
    beta = cfg.schedule.beta(r)
    n = cfg.trajectories(r)
    collect_cfg = dataclasses.replace(base_collect(cfg), seed=cfg.collect_seed(r), trajectories=n)
    specs = [trajectory_spec(collect_cfg.seed, k, collect_cfg.speeds) for k in range(n)]
    eval_seeds = evaluation_scene_seeds(cfg)
    for seed, _ in specs:
        _check_disjoint(cfg, seed, eval_seeds, f"{stage.name}")
    if len({seed for seed, _ in specs}) != n:
        raise VitflyError(f"{stage.name}: two flights of round {r} share a scene seed; choose another data.seed")
    flown_seeds = _round_seeds(data_path(cfg, False), r)
    todo = [k for k in range(n) if specs[k][0] not in flown_seeds]
    if student is None and beta < 1.0:
        raise VitflyError(f"{stage.name}: beta {beta} needs a student to fly")
    expert_ticks = [0, 0]
    t0 = time.perf_counter()
    pool = start_pool(cfg.data.workers) if (student is None and todo) else None
    try:
        with _writer(cfg, False, collect_cfg) as writer:
            if student is None:  # the expert alone: `vitfly collect`'s flights, in index order
                for rec in ordered_records(collect_cfg, todo, pool):
                    writer.append(_expert_record(rec, r))
                    if on_trajectory is not None:
                        on_trajectory(writer.num_trajectories)
            else:
                net = _load_student(cfg, student)
                rollout = collect_cfg.rollout_config()
                for lo in range(0, len(todo), cfg.data.num_envs):
                    batch = todo[lo: lo + cfg.data.num_envs]
                    scenes = [make_scene(collect_cfg.env, collect_cfg.preset, specs[k][0]) for k in batch]
                    mix = MixturePolicy(ExpertPolicy(), net, beta, seeds=[[cfg.data.seed, r, k] for k in batch])

                    def finished(i: int, result, mix=mix) -> None:
                        writer.append(episode_record(collect_cfg, result, r, beta))
                        expert_ticks[0] += int(mix.expert_ticks[i])
                        expert_ticks[1] += int(mix.ticks[i])
                        if on_trajectory is not None:
                            on_trajectory(writer.num_trajectories)

                    fly(scenes, [specs[k][1] for k in batch], mix, rollout, on_episode_end=finished,
                        engine=collect_cfg.engine)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    frames, round_frames, count = _frames(data_path(cfg, False), r)
    share = f", expert flew {100 * expert_ticks[0] / expert_ticks[1]:.0f} % of ticks" if expert_ticks[1] else ""
    print(f"[{stage.name}] {count} flights at beta {beta:.3f} ({len(todo)} new{share}), {round_frames} frames; "
          f"dataset {frames} labelled frames ({time.perf_counter() - t0:.0f} s)")
    return {"trajectories": count, "round_frames": round_frames, "frames": frames, "beta": beta,
            "expert_tick_share": expert_ticks[0] / expert_ticks[1] if expert_ticks[1] else None}


def _round_seeds(path: Path, round_index: int) -> set[int]:
    from vitfly.datamodules.schema import open_trajectories

    rounds = rounds_in(path)
    if not len(rounds):
        return set()
    with open_trajectories(path, check_values=False) as tf:
        seeds = np.asarray(tf.table["seed"], dtype=np.int64)
    return {int(s) for s in seeds[rounds == round_index]}


def _frames(path: Path, round_index: int) -> tuple[int, int, int]:
    """(frames of rounds <= round_index, frames of that round, its trajectories) in ``path``."""
    from vitfly.datamodules.schema import open_trajectories

    rounds = rounds_in(path)
    if not len(rounds):
        return 0, 0, 0
    with open_trajectories(path, check_values=False) as tf:
        lengths = np.asarray(tf.lengths)
    upto = int(lengths[rounds <= round_index].sum())
    this = rounds == round_index
    return upto, int(lengths[this].sum()), int(this.sum())


def stage_bc_collect(cfg: DaggerConfig, stage: Stage, on_trajectory: Callable[[int], None] | None = None) -> dict:
    """The baseline's dataset after round ``stage.round``: round 0's flights (copied) and extra expert flights
    until it holds exactly as many frames as DAgger's dataset after that round (the last flight is cut)."""
    from vitfly.datamodules.schema import open_trajectories
    from vitfly.sim.collect import ordered_records, start_pool

    r = stage.round
    collect_cfg = dataclasses.replace(base_collect(cfg), seed=cfg.collect_seed(r, baseline=True))
    target, _, _ = _frames(data_path(cfg, False), r)
    eval_seeds = evaluation_scene_seeds(cfg)
    t0 = time.perf_counter()
    with _writer(cfg, True, collect_cfg) as writer:
        if r == 1:  # round 0 is shared: the same flights in the same order, so the same validation split fits
            have = writer.num_trajectories
            with open_trajectories(data_path(cfg, False), check_values=False) as src:
                zero = [m for m in range(len(src)) if src.meta(m)["dagger_round"] == 0]
                for m in zero[have:]:
                    writer.append(src[m])
        current, _, done = _frames(data_path(cfg, True), r)
        if current > target:
            raise VitflyError(f"{data_path(cfg, True)}: holds {current} frames up to round {r}, more than DAgger's "
                              f"{target}; use a new --out")
        pool = start_pool(cfg.data.workers) if current < target else None
        try:
            indices = range(done, done + 1_000_000)  # as many as it takes; stops at the target
            for rec in (ordered_records(collect_cfg, indices, pool) if current < target else ()):
                _check_disjoint(cfg, rec.seed, eval_seeds, stage.name)
                rec = _cut(_expert_record(rec, r), target - current)
                writer.append(rec)
                current += rec.length
                if on_trajectory is not None:
                    on_trajectory(writer.num_trajectories)
                if current >= target:
                    break
        finally:
            if pool is not None:
                pool.shutdown(cancel_futures=True)
    frames, round_frames, count = _frames(data_path(cfg, True), r)
    print(f"[{stage.name}] baseline: {count} extra expert flights, {round_frames} frames; dataset {frames} labelled "
          f"frames (DAgger's: {target}) ({time.perf_counter() - t0:.0f} s)")
    return {"trajectories": count, "round_frames": round_frames, "frames": frames, "target_frames": target}


def _cut(rec, max_rows: int):
    """The record's first ``max_rows`` rows (all if it is shorter); per-trajectory fields describe the flight."""
    if rec.length <= max_rows:
        return rec
    rows = slice(0, max_rows)
    cut = {name: np.asarray(getattr(rec, name))[rows] for name in
           ("depth", "quat", "position", "velocity", "velocity_cmd", "time", "collision", "velocity_cmd_executed")}
    speed = np.asarray(rec.desired_speed)
    return dataclasses.replace(rec, **cut, desired_speed=speed if speed.ndim == 0 else speed[rows])


# -------------------------------------------------------------------------------------------------
# training


def stage_train(cfg: DaggerConfig, stage: Stage, baseline: bool, progress: bool = True,
                steps: int | None = None) -> dict:
    """Round 0: train from scratch (or ``train.init_checkpoint``); round i: fine-tune round i-1's final weights.
    ``steps`` (the baseline): exactly this many optimiser steps instead of ``finetune_epochs`` epochs."""
    import torch

    from vitfly.training import finish_wandb, train_policy

    r = stage.round
    data = data_path(cfg, baseline)
    found = rounds_in(data)
    if len(found) and int(found.max()) > r:
        raise VitflyError(f"{data}: already holds flights of round {int(found.max())}, but round {r}'s training is "
                          "missing (deleted?); it would train on later rounds' data: use a new --out")
    settings = train_settings(cfg, r)
    out = train_dir(cfg, r, baseline)
    ckpt = final_checkpoint(cfg, r, baseline)
    if r == 0:
        init = cfg.train.init_checkpoint
    else:
        init = str(final_checkpoint(cfg, r - 1, baseline and r > 1))
    data_kwargs = dict(settings["data_kwargs"])
    if r > 0:  # every round validates on round 0's held-out flights; the new ones go to training
        data_kwargs["split_file"] = str(train_dir(cfg, 0) / "split.json")
    policy_kwargs = dict(settings["policy_kwargs"])
    if cfg.threads and "cpu_threads" not in policy_kwargs:
        policy_kwargs["cpu_threads"] = cfg.threads
    trainer_kwargs = {"enable_model_summary": False, **settings["trainer_kwargs"]}
    max_epochs = settings["epochs"]
    if steps is not None:
        trainer_kwargs["max_steps"] = int(steps)
        max_epochs = -1
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    t0 = time.perf_counter()
    train_policy(data, settings["model"], out, use_state=settings["use_state"], max_epochs=max_epochs,
                 batch_size=settings["batch_size"], val_fraction=settings["val_fraction"], seed=settings["seed"],
                 policy_kwargs=policy_kwargs, data_kwargs=data_kwargs, trainer_kwargs=trainer_kwargs,
                 progress_bar=progress, init_weights=init)
    finish_wandb()
    if not ckpt.exists():
        raise VitflyError(f"{out}: training ended without writing {ckpt}")
    saved = torch.load(ckpt, map_location="cpu", weights_only=True)
    frames, _, _ = _frames(data, r)
    result = {"checkpoint": str(ckpt), "steps": int(saved["global_step"]), "frames": frames,
              "wall_s": time.perf_counter() - t0}
    what = "baseline" if baseline else ("trained" if r == 0 else "DAgger")
    print(f"[{stage.name}] {what} {settings['model']}: {result['steps']} optimiser steps on {frames} labelled "
          f"frames, {result['wall_s']:.0f} s -> {ckpt}")
    return result


# -------------------------------------------------------------------------------------------------
# evaluation and paths


def students(cfg: DaggerConfig, r: int) -> list[tuple[str, str]]:
    """(checkpoint, label) of round r's students: the shared one in round 0, else DAgger's and the baseline's."""
    out = [(str(final_checkpoint(cfg, r)), student_label(r, False))]
    if r and cfg.baseline:
        out.append((str(final_checkpoint(cfg, r, True)), student_label(r, True)))
    return out


def check_scenes_disjoint(cfg: DaggerConfig) -> int:
    """Every trajectory in the datasets is flown in a scene that no evaluation flies; returns how many were checked."""
    from vitfly.datamodules.schema import open_trajectories

    eval_seeds = evaluation_scene_seeds(cfg)
    checked = 0
    for baseline in (False, True):
        path = data_path(cfg, baseline)
        if not path.exists():
            continue
        with open_trajectories(path, check_values=False) as tf:
            seeds = {int(s) for s in tf.table["seed"]}
        both = sorted(seeds & eval_seeds)
        if both:
            raise VitflyError(f"{path}: scene seed {both[0]} was trained on and is also an evaluation scene")
        checked += len(seeds)
    return checked


def stage_evaluate(cfg: DaggerConfig, stage: Stage, progress: bool = True) -> dict:
    from vitfly.eval.sweep import run_sweep
    from vitfly.workflows.pipeline import sweep_config

    checked = check_scenes_disjoint(cfg)
    policies = students(cfg, stage.round)
    if stage.round == 0:
        policies += [(b, b) for b in cfg.evaluate.baselines]
    flown = 0
    for policy, label in policies:
        outcome = run_sweep(sweep_config(eval_stage(cfg), cfg.out_dir / "eval", policy, label), progress=progress)
        flown += outcome.flown
        replaced = f", {outcome.replaced} stale trials replaced" if outcome.replaced else ""
        print(f"[{stage.name}] {label}: {outcome.flown} trials flown, {outcome.skipped} done before{replaced}")
    return {"labels": [label for _, label in policies], "flown": flown, "training_scenes_checked": checked}


def stage_paths(cfg: DaggerConfig, stage: Stage) -> dict:
    from vitfly.eval.repeats import fly_repeats

    if cfg.paths.repeats < 1:
        return {"labels": []}
    last = cfg.rounds[-1]
    policies = students(cfg, last) + [(b, b) for b in cfg.evaluate.baselines if b == "expert"]
    for policy, label in policies:
        flown, before = fly_repeats(paths_plan(cfg), policy, cfg.out_dir / "paths", label, cfg.evaluate.threads)
        print(f"[{stage.name}] {label}: {flown} repeats flown, {before} done before")
    return {"labels": [label for _, label in policies]}


# -------------------------------------------------------------------------------------------------
# the run


def _stage_done(cfg: DaggerConfig, stage: Stage, manifest: dict | None) -> bool:
    if manifest is None or not manifest.get("done") or manifest.get("fingerprint") != stage.fingerprint:
        return False
    if stage.kind in ("train", "bc-train"):
        return Path(manifest["result"].get("checkpoint", "")).exists()
    if stage.kind == "collect":
        return _frames(data_path(cfg, False), stage.round)[2] == cfg.trajectories(stage.round)
    if stage.kind == "bc-collect":
        frames, _, _ = _frames(data_path(cfg, True), stage.round)
        return frames == manifest["result"].get("frames")
    return stage.kind != "report"


def run_dagger(cfg: DaggerConfig, stop_after: str | None = None, progress: bool = True,
               on_trajectory: Callable[[str, int], None] | None = None) -> dict:
    """Run (or resume) every stage up to ``stop_after`` (default: all); returns the report (or {}).

    ``on_trajectory(stage name, trajectories in the dataset)`` is called after each appended flight.
    """
    stages = plan_stages(cfg)
    names = [s.name for s in stages]
    if stop_after is not None and stop_after not in names:
        raise VitflyError(f"--stop-after: unknown stage {stop_after!r}; this config's stages are {', '.join(names)}")
    check_existing(cfg, stages)
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    write_text(cfg.out_dir / "config.json", json.dumps(dataclasses.asdict(cfg), indent=1) + "\n")
    results: dict[str, dict] = {}
    report: dict = {}
    t_start = time.perf_counter()
    for stage in stages:
        manifest = read_stage_manifest(cfg, stage)
        if _stage_done(cfg, stage, manifest):
            results[stage.name] = manifest["result"]
            print(f"[{stage.name}] done before")
        else:
            if manifest is not None and manifest.get("fingerprint") != stage.fingerprint:
                _discard(cfg, stage)  # other settings: recompute (flights in a dataset were refused above)
            write_stage_manifest(cfg, stage, done=False)
            callback = None if on_trajectory is None else (lambda n, name=stage.name: on_trajectory(name, n))
            t0 = time.perf_counter()
            results[stage.name] = _run_stage(cfg, stage, results, progress, callback)
            results[stage.name]["stage_wall_s"] = time.perf_counter() - t0
            if stage.kind == "report":
                report = results[stage.name]
            write_stage_manifest(cfg, stage, done=True, result=results[stage.name])
        if stage.name == stop_after:
            print(f"[dagger] stopped after {stage.name} (--stop-after); rerun without it to go on")
            break
    print(f"[dagger] {time.perf_counter() - t_start:.0f} s")
    return report


def _discard(cfg: DaggerConfig, stage: Stage) -> None:
    """Remove what a stage made with other settings (training runs: their checkpoints would be resumed)."""
    if stage.kind in ("train", "bc-train"):
        out = train_dir(cfg, stage.round, stage.kind == "bc-train")
        if out.exists():
            print(f"[{stage.name}] settings changed: retraining from the start ({out} removed)")
            shutil.rmtree(out)


def _run_stage(cfg: DaggerConfig, stage: Stage, results: dict, progress: bool, callback) -> dict:
    r = stage.round
    if stage.kind == "collect":
        student = None
        if r > 0:
            student = Path(results[f"r{r - 1}.train"]["checkpoint"])
        elif cfg.schedule.beta(0) < 1.0:
            student = cfg.train.init_checkpoint  # a checkpoint path or pretrained:NAME
        return stage_collect(cfg, stage, student, progress, callback)
    if stage.kind == "train":
        return stage_train(cfg, stage, False, progress)
    if stage.kind == "bc-collect":
        return stage_bc_collect(cfg, stage, callback)
    if stage.kind == "bc-train":
        # a fine-tune is a fresh Trainer: DAgger's round-r steps are its checkpoint's global_step
        return stage_train(cfg, stage, True, progress, steps=results[f"r{r}.train"]["steps"])
    if stage.kind == "evaluate":
        return stage_evaluate(cfg, stage, progress)
    if stage.kind == "paths":
        return stage_paths(cfg, stage)
    from vitfly.workflows.dagger_report import write_report

    return write_report(cfg, results)

