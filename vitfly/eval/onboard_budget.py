"""The onboard budget: one control tick of the full deployment path, timed part by part, against the control period.

The paper flew ViT+LSTM on the quadrotor's own CPU at 30 Hz, so sensing and inference must fit one period of
1000 / 30 = 33.3 ms. One tick here is what the robot runs between two frames:

1. **sensor**: the exact metric render of the simulator (the camera's stand-in, not timed) through a stereo
   sensor model (``vitfly.sim.sensor_models``: the D435's disparity noise, quantisation, invalid pixels,
   occlusion shadow) and the original's deployment normalisation, to the network's (60, 90) input;
   ``sensor=None`` times the ideal camera's normalisation only (clip(z / range, 0, 1));
2. **network**: the frame as a (1, 1, 1, 60, 90) tensor, one forward pass at batch 1 with the recurrent state
   carried from the previous tick (as in flight), and the paper's deployment of its output into a velocity
   command (``vitfly.eval.learned_policy.deploy_command``, take-off ramp included).

The frames are the exact renders at the poses of an expert flight (``flight_frames``), cycled when there are
fewer poses than ticks. Every tick is timed on two clocks (``vitfly.eval.latency.CLOCKS``): elapsed (wall)
time, the budget's measure, and the process's CPU time, which leaves out the time spent waiting for a core on
a machine shared with other jobs (one torch thread, so CPU time is the work of that thread). The garbage
collector is off while timing (a collection would land in one tick).
"""

from __future__ import annotations

import gc
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from vitfly.errors import VitflyError
from vitfly.eval.latency import CLOCKS
from vitfly.eval.learned_policy import deploy_command
from vitfly.sim.camera import CameraConfig, DepthCamera
from vitfly.sim.policies import ExpertPolicy
from vitfly.sim.quadrotor import quat_wxyz_to_matrix
from vitfly.sim.rollout import RolloutConfig, TaskConfig, run_episodes
from vitfly.sim.scenes import make_scene
from vitfly.sim.sensor_models import StereoDepthSensor

PARTS = ("sensor", "network", "total")
PERCENTILES = (50, 95, 99)


def budget_ms(control_hz: float) -> float:
    """The control period in milliseconds (33.3 ms at 30 Hz)."""
    if not control_hz > 0:
        raise VitflyError(f"--control-hz must be > 0, got {control_hz}")
    return 1000.0 / float(control_hz)


@dataclass
class FlightFrames:
    """Exact metric depth at the poses of one flight: metric_m (N, H, W) float64 (``inf`` = nothing within
    range), quat (N, 4) body-to-world (w, x, y, z), position (N, 3) m world frame, desired_speed m/s, and the
    scene seed (it seeds the sensor model's noise)."""

    metric_m: np.ndarray
    quat: np.ndarray
    position: np.ndarray
    desired_speed: float
    seed: int

    def __len__(self) -> int:
        return len(self.metric_m)


def flight_frames(
    env: str = "course",
    preset: str = "medium",
    seed: int = 0,
    speed_mps: float = 5.0,
    n_frames: int = 300,
    camera: CameraConfig | None = None,
    control_hz: float = 30.0,
) -> FlightFrames:
    """The exact renders (metric depth) at the first ``n_frames`` control ticks of an expert flight."""
    if n_frames < 1:
        raise VitflyError(f"--frames must be >= 1, got {n_frames}")
    camera = camera or CameraConfig()
    # the timeout cuts the flight after n_frames ticks (one extra tick of margin)
    task = TaskConfig(timeout_s=(n_frames + 1) / control_hz, timeout_speed_factor=0.0)
    cfg = RolloutConfig(camera=camera, control_hz=control_hz, task=task)
    scene = make_scene(env, preset, seed)
    log = run_episodes([scene], [float(speed_mps)], ExpertPolicy(), cfg)[0].log
    quat, position = log.quat[:n_frames], log.position[:n_frames]
    cam = DepthCamera(camera)
    rotations = quat_wxyz_to_matrix(quat)
    metric = np.stack([cam.metric_depth(scene, p, r) for p, r in zip(position, rotations, strict=True)])
    return FlightFrames(metric, quat, position, float(speed_mps), int(seed))


def ideal_normalise(metric_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """The ideal camera's network input: clip(z / range, 0, 1), nothing within range -> 1 (float32)."""
    return np.minimum(np.nan_to_num(metric_m / max_range_m, posinf=1.0), 1.0).clip(0.0).astype(np.float32)


def time_deployment(
    net: nn.Module,
    frames: FlightFrames,
    sensor: StereoDepthSensor | None,
    ticks: int = 1000,
    warmup: int = 100,
    max_range_m: float = 10.0,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """Milliseconds of each part of ``ticks`` timed deployment ticks after ``warmup`` untimed ones.

    Returns ``{part: {clock: (ticks,) ms}}`` for part in ``PARTS`` and clock in ``CLOCKS`` (total = sensor +
    network of the same tick). Runs on the CPU with the caller's torch thread count. ``progress(done, total)``
    is called every 100 ticks (warm-up included) and at the end.
    """
    if ticks < 1 or warmup < 0:
        raise VitflyError(f"--ticks must be >= 1 and --warmup >= 0, got {ticks} and {warmup}")
    net = net.eval().cpu()
    speed = np.array([frames.desired_speed])
    speed_t = torch.full((1, 1, 1), frames.desired_speed)
    quat_t = torch.as_tensor(frames.quat, dtype=torch.float32).reshape(-1, 1, 1, 4)
    init = getattr(net, "initial_hidden", None)
    hidden = init(1) if getattr(net, "is_recurrent", False) and init is not None else None
    total = warmup + ticks
    times = {part: {clock: np.empty(ticks) for clock in CLOCKS} for part in ("sensor", "network")}
    wall, cpu = CLOCKS["wall"], CLOCKS["cpu"]
    gc.collect()
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for tick in range(total):
            i = tick % len(frames)
            w0, c0 = wall(), cpu()
            if sensor is None:
                image = ideal_normalise(frames.metric_m[i], max_range_m)
            else:
                image = sensor.image(frames.metric_m[i], frames.seed, tick)
            w1, c1 = wall(), cpu()
            with torch.inference_mode():
                out, hidden = net(torch.from_numpy(image).reshape(1, 1, 1, *image.shape), speed_t, quat_t[i], hidden)
            command = deploy_command(out.reshape(1, 3).double().numpy(), speed, frames.position[i : i + 1, 0])
            w2, c2 = wall(), cpu()
            if not np.all(np.isfinite(command)):
                raise VitflyError(f"tick {tick}: the network's command is not finite ({command.tolist()})")
            k = tick - warmup
            if k >= 0:
                times["sensor"]["wall"][k], times["sensor"]["cpu"][k] = w1 - w0, c1 - c0
                times["network"]["wall"][k], times["network"]["cpu"][k] = w2 - w1, c2 - c1
            if progress is not None and ((tick + 1) % 100 == 0 or tick + 1 == total):
                progress(tick + 1, total)
    finally:
        if gc_was_enabled:
            gc.enable()
    out_ms = {part: {clock: t * 1000.0 for clock, t in by_clock.items()} for part, by_clock in times.items()}
    out_ms["total"] = {clock: out_ms["sensor"][clock] + out_ms["network"][clock] for clock in CLOCKS}
    return out_ms


def summarise(times_ms: np.ndarray, period_ms: float) -> dict[str, float]:
    """mean, p50, p95, p99 and max (ms) of per-tick times, the mean's and the p99's share of the period, and the
    share of ticks over the period."""
    t = np.asarray(times_ms, dtype=np.float64)
    if t.size == 0 or not np.all(np.isfinite(t)):
        raise VitflyError("summarise: expected a non-empty array of finite tick times (ms)")
    out = {"mean_ms": float(t.mean())}
    out.update({f"p{q}_ms": float(np.percentile(t, q)) for q in PERCENTILES})
    out["max_ms"] = float(t.max())
    out["mean_share"] = out["mean_ms"] / period_ms
    out["p99_share"] = out["p99_ms"] / period_ms
    out["over_budget_share"] = float((t > period_ms).mean())
    return out


def fits(summary_total: dict[str, float]) -> bool:
    """The onboard target: the 99th percentile of the whole tick within the period."""
    return math.isfinite(summary_total["p99_share"]) and summary_total["p99_share"] <= 1.0
