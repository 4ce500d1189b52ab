"""Do two inference paths of one network fly the same commands? Replayed over recorded flights.

A fast path (ONNX Runtime, int8) computes a slightly different function from the eager float32 network;
what matters in flight is the command. ``record_flights`` flies the simulator (the privileged expert by
default, so the flights are collision-free and cover the scenes) with every depth frame kept;
``replay_commands`` feeds a recorded flight, tick by tick, to a ``LearnedPolicy`` exactly as the rollout
engine would (depth, desired speed, attitude, position; recurrent state carried from the first tick,
several flights batched in lockstep), and ``command_agreement`` compares two policies' world-frame
commands (m/s, after the paper's clip / normalise / scale and take-off ramp) over every tick.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from vitfly.eval.learned_policy import LearnedPolicy

# largest per-component command difference (m/s) to the eager float32 network accepted for each fast back end:
# float32 graphs differ by rounding; int8 products by their quantisation, 0.15 m/s being 2 % of 7 m/s
COMMAND_TOLERANCE_MPS = {"onnxruntime": 1e-3, "onnxruntime-int8": 0.15}


@dataclass
class RecordedFlight:
    """One flight, per control tick (T ticks): what a policy observes. World frame, SI units."""

    env: str
    seed: int
    desired_speed_mps: float
    depth: np.ndarray  # (T, 60, 90) float32 in [0, 1]
    quat: np.ndarray  # (T, 4) (w, x, y, z) body-to-world
    position_m: np.ndarray  # (T, 3)

    def __len__(self) -> int:
        return len(self.depth)


def record_flights(
    env: str = "spheres",
    seeds: Sequence[int] = (0,),
    speeds_mps: Sequence[float] = (5.0,),
    preset: str = "medium",
    policy: str = "expert",
    timeout_s: float | None = None,
) -> list[RecordedFlight]:
    """Fly one episode per (seed, speed) with a built-in policy and keep what it observed at every tick.

    ``timeout_s`` shortens the flights (e.g. a few seconds for a test); None keeps the task's own timeout.
    """
    from vitfly.sim.policies import make_builtin_policy
    from vitfly.sim.rollout import RolloutConfig, TaskConfig, run_episodes
    from vitfly.sim.scenes import make_scene

    pairs = [(seed, speed) for seed in seeds for speed in speeds_mps]
    task = TaskConfig() if timeout_s is None else TaskConfig(timeout_s=timeout_s, timeout_speed_factor=0.0)
    results = run_episodes([make_scene(env, preset, seed) for seed, _ in pairs], [speed for _, speed in pairs],
                           make_builtin_policy(policy), RolloutConfig(task=task, record_depth=True))  # fmt: skip
    return [
        RecordedFlight(env, seed, float(speed), r.log.depth.astype(np.float32), r.log.quat.copy(),
                       r.log.position.copy())  # fmt: skip
        for (seed, speed), r in zip(pairs, results, strict=True)
    ]


@functools.lru_cache(maxsize=4)
def calibration_depth(seed: int = 10, seconds: float = 6.0, every: int = 2) -> np.ndarray:
    """Depth frames (N, 60, 90) for calibrating int8 activation ranges (``vitfly.deploy.quantize``).

    Expert flights of ``seconds`` through one spheres scene at 3 and 7 m/s and one trees scene at 5 m/s
    (scene ``seed``; the agreement checks fly other seeds), every ``every``-th tick: about 270 frames.
    Deterministic; recorded once per process. Read-only.
    """
    flights = record_flights("spheres", (seed,), (3.0, 7.0), timeout_s=seconds)
    flights += record_flights("trees", (seed,), (5.0,), timeout_s=seconds)
    frames = np.concatenate([f.depth[::every] for f in flights])
    frames.flags.writeable = False
    return frames


def replay_commands(policy: LearnedPolicy, flights: Sequence[RecordedFlight]) -> list[np.ndarray]:
    """The policy's command (T, 3) m/s at every tick of every flight, flights batched in lockstep."""
    n, horizon = len(flights), max(len(f) for f in flights)
    policy.reset(n)
    commands = [np.zeros((len(f), 3)) for f in flights]
    depth = np.zeros((n, *flights[0].depth.shape[1:]), dtype=np.float32)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    position = np.zeros((n, 3))
    speed = np.array([f.desired_speed_mps for f in flights])
    for t in range(horizon):
        active = np.array([t < len(f) for f in flights])
        for i in np.flatnonzero(active):
            depth[i], quat[i], position[i] = flights[i].depth[t], flights[i].quat[t], flights[i].position_m[t]
        obs = {"depth": depth, "desired_speed": speed, "quat": quat, "position": position, "active": active}
        out = policy(obs)
        for i in np.flatnonzero(active):
            commands[i][t] = out[i]
    return commands


@dataclass
class Agreement:
    """Differences of a candidate's commands from a reference's over every tick of the flights (m/s, deg)."""

    flights: int
    ticks: int
    max_abs_mps: float  # largest per-component difference
    p99_abs_mps: float  # 99th percentile of the per-tick largest component difference
    mean_abs_mps: float  # mean per-tick largest component difference
    max_angle_deg: float  # largest angle between the two commands (ticks with both commands non-zero)

    def within(self, tolerance_mps: float) -> bool:
        return self.max_abs_mps <= tolerance_mps

    def to_dict(self) -> dict:
        return asdict(self)


def compare_commands(reference: Sequence[np.ndarray], candidate: Sequence[np.ndarray]) -> Agreement:
    """``Agreement`` of two lists of per-flight commands (T, 3) m/s."""
    ref, cand = np.concatenate(reference), np.concatenate(candidate)
    per_tick = np.abs(cand - ref).max(axis=1)
    norms = np.linalg.norm(ref, axis=1) * np.linalg.norm(cand, axis=1)
    ok = norms > 1e-9
    cosine = np.clip(np.sum(ref * cand, axis=1)[ok] / norms[ok], -1.0, 1.0)
    angle = float(np.degrees(np.arccos(cosine)).max()) if ok.any() else 0.0
    return Agreement(len(reference), len(ref), float(per_tick.max()), float(np.percentile(per_tick, 99)),
                     float(per_tick.mean()), angle)  # fmt: skip


def command_agreement(
    reference: LearnedPolicy, candidate: LearnedPolicy, flights: Sequence[RecordedFlight]
) -> Agreement:
    """Replay ``flights`` through both policies and compare their commands tick by tick."""
    return compare_commands(replay_commands(reference, flights), replay_commands(candidate, flights))
