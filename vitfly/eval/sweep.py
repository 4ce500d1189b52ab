"""An evaluation sweep: one policy over envs x speeds x trials, resumable, sharded, in lockstep batches.

Trial ``k`` of an env flies the scene with seed ``derive_scene_seed(seed, env, k)`` at every speed,
so every policy sees the same scenes. The full trial list is fixed by the config; ``--shard i/n``
takes every n-th trial of it; the rest are grouped by speed into lockstep batches of ``num_envs``
scenes (one batched policy call per control tick) and the batches are spread over ``workers``
processes. Each finished trial is appended to ``DIR/trials.jsonl`` at once (``vitfly.eval.records``),
from whichever process flew it.

Resuming is keyed by what was flown (``vitfly.eval.fingerprint``): a trial already in
``DIR/trials*.jsonl`` under the same label *and* the same setup (the policy's content, the sweep
seed, the preset, the rollout settings) is skipped. If the label's trials in ``DIR`` were flown
with another setup (a retrained checkpoint under the same name, another ``--seed`` or preset, other
rates), the sweep refuses with one line saying what differs, unless ``overwrite`` is set: then
those stale trials are removed and the sweep flies anew.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import signal
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from vitfly import __version__
from vitfly.errors import VitflyError
from vitfly.eval import records
from vitfly.eval.config import SweepConfig, parse_shard
from vitfly.eval.fingerprint import Setup, SweepIdentity, differences, policy_fingerprint, rollout_fingerprint
from vitfly.eval.metrics import trial_metrics
from vitfly.eval.policy_source import PolicySource


@dataclass(frozen=True)
class TrialSpec:
    env: str
    preset: str
    speed: float  # desired forward speed, m/s
    trial: int
    scene_seed: int


def derive_scene_seed(seed: int, env: str, trial: int) -> int:
    """Scene seed of trial ``trial`` in ``env`` for sweep seed ``seed`` (independent of speed and policy)."""
    state = np.random.SeedSequence([int(seed), zlib.crc32(env.encode()), int(trial)]).generate_state(1)
    return int(state[0] & 0x7FFFFFFF)


def plan_trials(cfg: SweepConfig) -> list[TrialSpec]:
    """Every trial of the sweep, ordered by (env, trial, speed) so shards get all speeds alike."""
    return [
        TrialSpec(env, cfg.preset, float(speed), k, derive_scene_seed(cfg.seed, env, k))
        for env in cfg.env
        for k in range(cfg.trials)
        for speed in cfg.speeds
    ]


def select_shard(specs: Sequence[TrialSpec], index: int, count: int) -> list[TrialSpec]:
    return list(specs[index::count])


def make_batches(specs: Sequence[TrialSpec], num_envs: int) -> list[list[TrialSpec]]:
    """Lockstep batches of up to ``num_envs`` trials; equal speeds together, so a batch ends together."""
    ordered = sorted(specs, key=lambda s: (s.speed, s.env, s.trial))
    return [ordered[i : i + num_envs] for i in range(0, len(ordered), num_envs)]


class TimedPolicy:
    """Wraps a policy and books each call's wall time to the envs active in it (ms per env per tick).

    A batched policy (``batched`` true: the batched engine's tensors in and out) stays one; on a CUDA
    device the call is timed to the end of its kernels, not to their launch.
    """

    def __init__(self, policy):
        self.policy = policy
        self.needs_depth = bool(getattr(policy, "needs_depth", True))
        self.batched = bool(getattr(policy, "batched", False))

    def reset(self, num_envs: int) -> None:
        self.policy.reset(num_envs)
        self.env_ms = np.zeros(num_envs)
        self.call_ms = np.zeros(num_envs)
        self.calls = np.zeros(num_envs, dtype=np.int64)

    def __call__(self, obs):
        t0 = time.perf_counter()
        out = self.policy(obs)
        if self.batched and obs.active.is_cuda:
            import torch

            torch.cuda.synchronize(obs.active.device)
        ms = 1e3 * (time.perf_counter() - t0)
        active = np.flatnonzero(obs.active.cpu().numpy() if self.batched else obs.active)
        if len(active):
            self.env_ms[active] += ms / len(active)
            self.call_ms[active] += ms
            self.calls[active] += 1
        return out


def rollout_config(cfg: SweepConfig, record_depth: bool = False):
    from vitfly.eval.sensor import flight_sensor
    from vitfly.sim.rollout import RolloutConfig, TaskConfig
    from vitfly.sim.sensor_models import sensor_from_dict

    task = TaskConfig() if cfg.timeout_s is None else TaskConfig(timeout_s=cfg.timeout_s, timeout_speed_factor=0.0)
    camera, control_hz = flight_sensor(cfg)
    return RolloutConfig(task=task, record_depth=record_depth, camera=camera, control_hz=control_hz,
                         physics=cfg.engine.physics(cfg.physics), sensor=sensor_from_dict(cfg.sensor))


def policy_source(cfg: SweepConfig) -> PolicySource:
    # a modular planner back-projects depth with the camera it flies with
    camera = rollout_config(cfg).camera if cfg.policy.startswith("modular:") else None
    return PolicySource(cfg.policy, cfg.arch, cfg.backend, cfg.device, cfg.threads, cfg.planner_config, camera)


def sweep_identity(cfg: SweepConfig, source: PolicySource | None = None) -> SweepIdentity:
    """What this sweep flies, hashed (loads a checkpoint's network once; a bad file fails here)."""
    source = source or policy_source(cfg)
    return SweepIdentity(policy_fingerprint(source), rollout_fingerprint(rollout_config(cfg), cfg.engine.key()),
                         int(cfg.seed), cfg.preset)


def record_from_result(spec: TrialSpec, label: str, result, cfg: SweepConfig, processing_ms: float,
                       call_ms: float, batch_size: int, setup: Setup) -> records.TrialRecord:
    """One trial record; metrics are computed from the rounded path as stored."""
    log, summary = result.log, result.summary
    # the end state (the physics step that ended the trial) is where a goal crossing shows: no tick reaches it
    path = records.round_path(log.time, log.position, log.velocity, log.command, log.contact,
                              end_time_s=summary.duration_s, end_position=summary.final_position)
    arr = {k: np.asarray(v) for k, v in path.items() if k != "end"}
    goal_x = rollout_config(cfg).task.goal_x_m
    m = trial_metrics(arr["time"], arr["position"].reshape(-1, 3), arr["velocity"].reshape(-1, 3),
                      arr["command"].reshape(-1, 3), arr["contact"], desired_speed_mps=spec.speed, goal_x_m=goal_x,
                      reached_goal=summary.reached_goal, processing_ms=processing_ms,
                      end_time_s=path["end"]["time"], end_position=path["end"]["position"])
    extra = {
        "sweep_seed": cfg.seed,
        "policy_source": cfg.policy,
        "arch": cfg.arch,
        "backend": cfg.backend if cfg.policy not in ("expert", "straight") else None,
        "physics": cfg.engine.physics(cfg.physics),  # the rigid-body back end that flew it
        "sim": cfg.engine.record(),  # the simulator engine that flew it (and its device and precision)
        "vitfly_version": __version__,
        "batch_size": batch_size,
        "batch_call_ms": call_ms,
        # the simulator's own counts at the physics rate (metrics use the per-tick path, recomputable)
        "physics_collisions": summary.n_collisions,
        "physics_contact_time_s": summary.time_in_contact_s,
        "duration_s": summary.duration_s,
        "scene": result.scene.to_dict(),
    }
    return records.TrialRecord(
        policy=label, env=spec.env, preset=spec.preset, speed=spec.speed, trial=spec.trial,
        scene_seed=spec.scene_seed, success_paper=m.success_paper, success_strict=m.success_strict,
        reached_goal=m.reached_goal, end_reason=summary.end_reason, metrics=m.to_dict(), path=path,
        setup=setup.to_dict(), setup_id=setup.id, extra=extra,
    )


def fly_batch(batch: Sequence[TrialSpec], policy, cfg: SweepConfig, out_file: Path,
              on_trial: Callable[[records.TrialRecord], None] | None = None,
              identity: SweepIdentity | None = None) -> int:
    """Fly one lockstep batch; each trial is appended to ``out_file`` the moment it ends.

    ``identity`` (what ``policy`` is, see ``sweep_identity``) keys the records; computed from ``cfg``
    when not given.
    """
    from vitfly.sim.engine import fly
    from vitfly.sim.scenes import make_scene

    identity = identity or sweep_identity(cfg)
    setups = {env: identity.setup(env) for env in {s.env for s in batch}}
    scenes = [make_scene(s.env, s.preset, s.scene_seed) for s in batch]
    engine = cfg.engine
    trial_extra = getattr(policy, "trial_extra", None)  # e.g. a modular planner's replan times
    if engine.batched:  # the batched twin of the expert and straight flight, a learned policy's torch path
        from vitfly.sim.batched.policies import as_batched_policy

        policy = as_batched_policy(policy, compile=engine.compile)
    timed = TimedPolicy(policy)

    def finished(i: int, result) -> None:
        calls = max(int(timed.calls[i]), 1)
        rec = record_from_result(batch[i], cfg.label, result, cfg, float(timed.env_ms[i] / calls),
                                 float(timed.call_ms[i] / calls), len(batch), setups[batch[i].env])
        if trial_extra is not None:
            rec.extra.update(trial_extra(i))
        records.append_record(out_file, rec)
        if on_trial is not None:
            on_trial(rec)

    fly(scenes, [s.speed for s in batch], timed, rollout_config(cfg), on_episode_end=finished, engine=engine)
    return len(batch)


# worker processes build the policy once and keep it here (one per process)
_WORKER: dict = {}


def _worker_init(source: PolicySource, threads: int) -> None:
    import torch

    if sys.platform.startswith("linux"):  # die with the parent: a killed sweep leaves no orphans flying
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    torch.set_num_threads(threads)
    _WORKER["policy"] = source.build()


def _worker_fly(batch: list[TrialSpec], cfg: SweepConfig, out_file: str, identity: SweepIdentity) -> int:
    return fly_batch(batch, _WORKER["policy"], cfg, Path(out_file), identity=identity)


@dataclass
class SweepOutcome:
    out_dir: Path
    planned: int  # trials of this shard
    skipped: int  # already finished before this run
    flown: int
    wall_s: float
    records: list = field(default_factory=list)  # every record in out_dir after the run
    replaced: int = 0  # trials of this label flown with another setup, removed (overwrite)
    identity: SweepIdentity | None = None  # what was flown


def stale_records(recs: Sequence[records.TrialRecord], label: str,
                  identity: SweepIdentity) -> list[records.TrialRecord]:
    """The records of ``label`` flown with another setup than ``identity`` gives for their env."""
    setups: dict[str, Setup] = {}
    stale = []
    for rec in recs:
        if rec.policy == label:
            setup = setups.get(rec.env) or setups.setdefault(rec.env, identity.setup(rec.env))
            if rec.setup_id != setup.id:
                stale.append(rec)
    return stale


def resolve_conflicts(cfg: SweepConfig, identity: SweepIdentity) -> int:
    """Refuse (one line) or, with ``cfg.overwrite``, remove the label's trials flown with another setup.

    Returns how many trials were removed.
    """
    stale = stale_records(records.read_sweep(cfg.out), cfg.label, identity)
    if not stale:
        return 0
    if not cfg.overwrite:
        first = stale[0]
        diff = "; ".join(differences(first.setup, identity.setup(first.env).to_dict())) or "setup"
        was, now = (first.extra or {}).get("sim", {"engine": "numpy"}), cfg.engine.record()
        if was != now:  # the engine hides in the rollout id: say it plainly
            diff += f" (simulator {_engine_text(was)}, now {_engine_text(now)})"
        raise VitflyError(
            f"{cfg.out}: {len(stale)} trials of {cfg.label!r} there were flown with another {diff}; "
            "evaluate into a new --out, give this run another --name, or pass --overwrite to replace them")
    stale_ids = {(r.env, r.setup_id) for r in stale}
    return sum(records.remove_records(p, lambda r: r.policy == cfg.label and (r.env, r.setup_id) in stale_ids)
               for p in records.iter_trial_files(cfg.out))


def _engine_text(sim: dict) -> str:
    return " ".join([str(sim[k]) for k in ("engine", "device", "dtype") if k in sim] + ["compiled"] * bool(
        sim.get("compile")))


def pending_trials(cfg: SweepConfig, identity: SweepIdentity) -> tuple[list[TrialSpec], int]:
    """(trials of this shard still to fly, trials of this shard already finished with this setup)."""
    index, count = parse_shard(cfg.shard)
    mine = select_shard(plan_trials(cfg), index, count)
    done = {r.key for r in records.read_sweep(cfg.out)}
    setup_ids = {env: identity.setup(env).id for env in cfg.env}
    todo = [s for s in mine if records.trial_key(cfg.label, setup_ids[s.env], s.env, s.speed, s.trial) not in done]
    return todo, len(mine) - len(todo)


def run_sweep(cfg: SweepConfig, progress: bool = True) -> SweepOutcome:
    """Fly every pending trial of ``cfg``; return counts and all records now in ``cfg.out``."""
    source = policy_source(cfg)
    source.check()
    identity = sweep_identity(cfg, source)  # a bad checkpoint fails here, with one line, before anything is written
    replaced = resolve_conflicts(cfg, identity)
    todo, skipped = pending_trials(cfg, identity)
    batches = make_batches(todo, cfg.num_envs)
    policy = None
    if batches and cfg.workers <= 1:
        import torch

        torch.set_num_threads(cfg.threads)
        policy = source.build()
    out_dir = Path(cfg.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    out_file = out_dir / records.TRIALS_FILE
    t0 = time.perf_counter()
    with _progress(progress, len(todo), f"{cfg.label}: {len(todo)} trials ({skipped} done before)") as advance:
        if policy is not None:
            for batch in batches:
                fly_batch(batch, policy, cfg, out_file, on_trial=lambda _rec: advance(1), identity=identity)
        elif batches:
            workers = min(cfg.workers, len(batches))
            # spawn: no forked copies of torch / pybullet state
            with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_worker_init,
                                     initargs=(source, cfg.threads)) as pool:
                futures = {pool.submit(_worker_fly, b, cfg, str(out_file), identity) for b in batches}
                while futures:
                    finished, futures = wait(futures, return_when=FIRST_COMPLETED)
                    for fut in finished:
                        advance(fut.result())
    return SweepOutcome(out_dir, len(todo) + skipped, skipped, len(todo), time.perf_counter() - t0,
                        records.read_sweep(out_dir), replaced, identity)


class _progress:
    """A rich progress bar (or nothing) exposing ``advance(n)``."""

    def __init__(self, enabled: bool, total: int, description: str):
        self.enabled, self.total, self.description = enabled and total > 0, total, description

    def __enter__(self):
        if not self.enabled:
            return lambda n: None
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
        self.bar.start()
        task = self.bar.add_task(self.description, total=self.total)
        return lambda n: self.bar.advance(task, n)

    def __exit__(self, *exc):
        if self.enabled:
            self.bar.stop()
        return False


def trials_per_minute(flown: int, wall_s: float) -> float:
    return 60.0 * flown / wall_s if wall_s > 0 else math.nan


def default_workers() -> int:
    return max(1, (os.cpu_count() or 1) // 2)
