"""Repeated trials of one fixed scene (the paper's path figure), resumable, as ordinary trial records.

The simulator is deterministic, so flying the same scene again gives the same path. The paper's repeats
varied through the real-time stack (ROS, Unity) around the same start; vitfly varies the start instead:
repeat ``r`` starts at ``start + (0, dy_r, dz_r)`` with dy, dz uniform in [-jitter, jitter] m drawn from
``(seed, r)``, the same offsets for every policy. Each repeat is one rollout (one scene, batch of one).

Records go to ``DIR/trials.jsonl`` (``vitfly.eval.records``) with ``trial`` = repeat index, so the usual
readers, summaries and path plots work on them. Their ``setup`` carries a rollout hash that includes the
jitter and its seed, so repeats flown with another jitter never mix with these.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vitfly.eval import records
from vitfly.eval.config import SweepConfig
from vitfly.eval.fingerprint import Setup, digest, policy_fingerprint, scene_fingerprint
from vitfly.eval.policy_source import PolicySource
from vitfly.eval.sweep import TimedPolicy, TrialSpec, derive_scene_seed, record_from_result, rollout_config


@dataclass(frozen=True)
class RepeatPlan:
    """``repeats`` flights of scene ``derive_scene_seed(seed, env, scene_trial)`` at ``speed`` m/s."""

    env: str = "spheres"
    preset: str = "medium"
    speed: float = 5.0
    repeats: int = 10
    jitter_m: float = 0.1  # start offset bound in y and z, m
    seed: int = 1000  # sweep seed of the scene (and of the offsets)
    scene_trial: int = 0  # which of the sweep's scenes
    timeout_s: float | None = None

    @property
    def scene_seed(self) -> int:
        return derive_scene_seed(self.seed, self.env, self.scene_trial)

    def offsets(self) -> np.ndarray:
        """(repeats, 3) start offsets in m: x 0, y and z uniform in [-jitter, jitter]."""
        out = np.zeros((self.repeats, 3))
        for r in range(self.repeats):
            out[r, 1:] = np.random.default_rng([int(self.seed), 17, r]).uniform(-self.jitter_m, self.jitter_m, 2)
        return out


def _sweep_config(plan: RepeatPlan, policy: str, label: str | None, out_dir: Path) -> SweepConfig:
    return SweepConfig(policy=policy, name=label, env=[plan.env], preset=plan.preset, speeds=[plan.speed],
                       trials=plan.repeats, seed=plan.seed, out=str(out_dir), timeout_s=plan.timeout_s,
                       gif=False, plots=False)


def repeat_setup(plan: RepeatPlan, cfg: SweepConfig, source: PolicySource) -> Setup:
    rollout_id = digest({"rollout": rollout_config(cfg), "jitter_m": plan.jitter_m, "offset_seed": plan.seed,
                         "scene_trial": plan.scene_trial})
    return Setup(policy_fingerprint(source), rollout_id, int(plan.seed), plan.preset,
                 scene_fingerprint(plan.env, plan.preset))


def fly_repeats(plan: RepeatPlan, policy: str, out_dir: str | Path, label: str | None = None,
                threads: int = 1) -> tuple[int, int]:
    """Fly the repeats of ``policy`` (checkpoint path, ``pretrained:NAME``, expert, straight) not yet in
    ``out_dir``; returns (flown, done before). Repeats flown under this label with another setup are replaced."""
    import torch

    from vitfly.sim.rollout import run_episodes
    from vitfly.sim.scenes import make_scene

    out_dir = Path(out_dir)
    cfg = _sweep_config(plan, policy, label, out_dir)
    source = PolicySource(policy)
    source.check()
    setup = repeat_setup(plan, cfg, source)
    stale = [r for r in records.read_sweep(out_dir) if r.policy == cfg.label and r.setup_id != setup.id]
    if stale:
        for p in records.iter_trial_files(out_dir):
            records.remove_records(p, lambda r: r.policy == cfg.label and r.setup_id != setup.id)
    done = {r.key for r in records.read_sweep(out_dir)}
    todo = [r for r in range(plan.repeats)
            if records.trial_key(cfg.label, setup.id, plan.env, plan.speed, r) not in done]
    if not todo:
        return 0, plan.repeats
    torch.set_num_threads(threads)
    policy_obj = source.build()
    scene = make_scene(plan.env, plan.preset, plan.scene_seed)
    base = rollout_config(cfg)
    offsets = plan.offsets()
    out_file = out_dir / records.TRIALS_FILE
    out_dir.mkdir(parents=True, exist_ok=True)
    for r in todo:
        start = tuple(float(v) for v in np.asarray(base.task.start) + offsets[r])
        run_cfg = dataclasses.replace(base, task=dataclasses.replace(base.task, start=start))
        timed = TimedPolicy(policy_obj)
        (result,) = run_episodes([scene], [plan.speed], timed, run_cfg)
        calls = max(int(timed.calls[0]), 1)
        spec = TrialSpec(plan.env, plan.preset, plan.speed, r, plan.scene_seed)
        rec = record_from_result(spec, cfg.label, result, cfg, float(timed.env_ms[0] / calls),
                                 float(timed.call_ms[0] / calls), 1, setup)
        rec.extra["start"] = list(start)
        records.append_record(out_file, rec)
    return len(todo), plan.repeats - len(todo)


def mean_path(recs, x_grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and std over trials of y(x) and z(x) on ``x_grid`` (m), and how many trials reach each x.

    Each path is resampled by its forward position (x made non-decreasing, so a brief backwards step
    does not fold the curve); beyond the farthest x a trial reached it counts no more.
    Returns mean (G, 2), std (G, 2) (ddof 0; nan where no trial reaches), count (G,).
    """
    samples = np.full((len(recs), len(x_grid), 2), np.nan)
    for i, rec in enumerate(recs):
        pos = rec.path_arrays()["position"]
        if len(pos) < 2:
            continue
        x = np.maximum.accumulate(pos[:, 0])
        keep = np.concatenate(([True], np.diff(x) > 0))
        x, yz = x[keep], pos[keep, 1:]
        inside = (x_grid >= x[0]) & (x_grid <= x[-1])
        for k in range(2):
            samples[i, inside, k] = np.interp(x_grid[inside], x, yz[:, k])
    count = np.sum(np.isfinite(samples[:, :, 0]), axis=0)
    with np.errstate(invalid="ignore"):
        mean = np.where(count[:, None] > 0, np.nansum(samples, axis=0) / np.maximum(count, 1)[:, None], np.nan)
        var = np.where(count[:, None] > 0,
                       np.nansum((samples - mean[None]) ** 2, axis=0) / np.maximum(count, 1)[:, None], np.nan)
    return mean, np.sqrt(var), count
