"""The episode loop of the batched engine: E scenes in lockstep, every part as tensor code on one device.

The same loop as :func:`vitfly.sim.rollout.run_episodes` (and the same results, as
:class:`~vitfly.sim.rollout.EpisodeResult`): at each control tick the depth images of the active
scenes are rendered in one call, the policy is called once for the batch, the obstacles each drone can
reach before the next tick are kept for the contact tests, and ``physics_hz / control_hz`` physics
steps run, each with the cascaded controller, the contact test, and the goal and bounding-box checks;
at the tick's end the timeouts. Finished episodes stay in the batch (inactive, hovering). The per-tick
logs stay on the device; an episode's log comes to the host once, when it ends (for ``on_episode_end``).

Example::

    results = run_batched([make_scene("spheres", "medium", s) for s in range(64)], [5.0] * 64,
                          ExpertPolicy(), RolloutConfig(), device="cpu")
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from vitfly.sim.batched.camera import BatchedCamera
from vitfly.sim.batched.contact import in_contact, nearby
from vitfly.sim.batched.controller import velocity_control
from vitfly.sim.batched.dynamics import DroneTensors, hover_state, physics_step
from vitfly.sim.batched.policies import BatchedObservation, as_batched_policy
from vitfly.sim.batched.scenes import SceneBatch, scene_batch
from vitfly.sim.rollout import EpisodeLog, EpisodeResult, EpisodeSummary, RolloutConfig
from vitfly.sim.scenes import Scene

END_CODES = (None, "goal", "timeout", "out_of_bounds")  # index = the engine's end code
NOISE_SOURCES = ("numpy", "torch")


@dataclass(frozen=True)
class BatchedSettings:
    """Where and how the batched engine runs.

    device: "cpu", "cuda", "cuda:1", ...; dtype: torch.float64 (exact against the numpy engine) or
    torch.float32 (faster, rounding at 1e-7 relative); compile: run the hot kernels through
    ``torch.compile`` (a one-off compile of some seconds; pays off on long runs);
    noise_source: where the camera's noise and dropout draws come from, "numpy" (each env's own
    generator, seeded as the numpy engine seeds it: the same draws) or "torch" (one generator on the
    device seeded with the camera seed: fast on a GPU, but an env's draws depend on its batch).
    """

    device: str = "cpu"
    dtype: torch.dtype = torch.float64
    compile: bool = False
    noise_source: str = "numpy"

    def validate(self, source: str = "batched engine") -> BatchedSettings:
        if self.noise_source not in NOISE_SOURCES:
            expected = ", ".join(NOISE_SOURCES)
            raise ValueError(f"{source}: noise_source {self.noise_source!r}; expected one of {expected}")
        if self.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"{source}: dtype {self.dtype}; expected torch.float32 or torch.float64")
        torch.empty(0, device=self.device)  # an unknown or absent device fails here, with torch's message
        return self


def _compiler(settings: BatchedSettings, dynamic: bool) -> Callable | None:
    if not settings.compile:
        return None
    return lambda fn: torch.compile(fn, dynamic=dynamic)


class Tracking(NamedTuple):
    """Per-env bookkeeping of contact and end conditions during a rollout, (E,) each unless said.

    end_code: 0 running, else the index of its reason in ``END_CODES``; end_time (s); final_position
    (E, 3) m; touching: in contact after the last physics step; contact_steps, n_collisions (rising
    edges); tick_contact: touched during the current control tick.
    """

    end_code: torch.Tensor
    end_time: torch.Tensor
    final_position: torch.Tensor
    touching: torch.Tensor
    contact_steps: torch.Tensor
    n_collisions: torch.Tensor
    tick_contact: torch.Tensor


def _substep(state: DroneTensors, track: Tracking, command, candidates, time_s, goal_x, lo, hi, batch, airframe,
             gains, dt, body_radius_m) -> tuple[DroneTensors, Tracking]:
    """One physics step for all drones (the cascaded controller tracking ``command`` (E, 3) m/s), then the
    contact, goal and bounding-box checks of the envs still running; ``time_s`` (0-d) is the time after it."""
    running = track.end_code == 0
    state = physics_step(state, velocity_control(command, state, airframe, gains), airframe, dt)
    touching = in_contact(state.position, batch, candidates, body_radius_m) & running
    p = state.position
    goal = running & (p[:, 0] >= goal_x)
    out = running & ~goal & ~((p >= lo) & (p <= hi)).all(1)
    ended = goal | out
    return state, Tracking(
        end_code=torch.where(goal, 1, torch.where(out, 3, track.end_code)),
        end_time=torch.where(ended, time_s, track.end_time),
        final_position=torch.where(ended[:, None], p, track.final_position),
        touching=torch.where(running, touching, track.touching),
        contact_steps=track.contact_steps + touching,
        n_collisions=track.n_collisions + (touching & ~track.touching),
        tick_contact=track.tick_contact | touching,
    )


def _contact_candidates(state: DroneTensors, speed, active, batch, body_radius_m: float,
                        control_hz: float) -> torch.Tensor:
    """(E, K) bool: the obstacles each running drone can reach before the next tick (twice the distance at
    the current or desired speed, plus margin); the others are left out of the per-step contact tests, as
    in the numpy engine."""
    v = state.velocity
    now = torch.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])
    reach = 2.0 * torch.maximum(torch.maximum(now, speed), torch.full_like(now, 5.0)) / control_hz + 0.5
    return nearby(state.position, batch, reach, body_radius_m) & active[:, None]


class _Log:
    """Per-tick logs of all envs on the device, grown by doubling; env i's rows are 0 .. its last tick."""

    def __init__(self, rows: int, n: int, like: dict, labels: bool):
        self.like, self.labels = like, labels
        self.tensors = {
            "position": torch.zeros(rows, n, 3, **like), "velocity": torch.zeros(rows, n, 3, **like),
            "quat": torch.zeros(rows, n, 4, **like), "command": torch.zeros(rows, n, 3, **like),
            "label": torch.zeros(rows, n, 3, **like),
            "contact": torch.zeros(rows, n, dtype=torch.bool, device=like["device"]),
        }
        self.time: list[float] = []
        self.frames: list[torch.Tensor] = []

    def row(self, tick: int) -> dict[str, torch.Tensor]:
        if tick >= next(iter(self.tensors.values())).shape[0]:
            self.tensors = {k: torch.cat([v, torch.zeros_like(v)]) for k, v in self.tensors.items()}
        return {k: v[tick] for k, v in self.tensors.items()}


def run_batched(
    scenes: Sequence[Scene],
    speeds: Sequence[float],
    policy,
    config: RolloutConfig | None = None,
    on_episode_end: Callable[[int, EpisodeResult], None] | None = None,
    camera_seed: int | None = None,
    settings: BatchedSettings | None = None,
    batch: SceneBatch | None = None,
) -> list[EpisodeResult]:
    """Fly one episode per (scene, desired speed m/s) in lockstep on the batched engine; results in input order.

    The arguments of :func:`vitfly.sim.rollout.run_episodes` (``config.physics`` is not used: this engine
    is its own back end, the native one's step in torch), plus ``settings`` (device, dtype, compile,
    noise source) and optionally a prebuilt ``batch`` of the same scenes.
    """
    cfg = config or RolloutConfig()
    st = (settings or BatchedSettings()).validate()
    n = len(scenes)
    if len(speeds) != n:
        raise ValueError(f"got {n} scenes but {len(speeds)} speeds")
    if n == 0:
        return []
    substeps, dt = cfg.physics_steps_per_tick, 1.0 / cfg.physics_hz
    task, af, gains = cfg.task, cfg.airframe, cfg.gains
    like = dict(dtype=st.dtype, device=torch.device(st.device))
    batch = batch if batch is not None else scene_batch(scenes, st.device, st.dtype)
    camera = BatchedCamera(cfg.camera, st.device, st.dtype, compile=_compiler(st, dynamic=True))
    policy = as_batched_policy(policy, compile=st.compile)
    needs_depth = bool(getattr(policy, "needs_depth", True)) or cfg.record_depth
    # compiled step by step (seconds): one graph of a tick's eight physics steps compiled for 80 s, and again
    # for each new batch size; static shapes first (dynamic=True made the step a third slower)
    substep = torch.compile(_substep) if st.compile else _substep
    contact_candidates = torch.compile(_contact_candidates) if st.compile else _contact_candidates
    noisy = cfg.camera.noise_std_m > 0.0 or cfg.camera.dropout_prob > 0.0
    rngs = [np.random.default_rng([camera_seed if camera_seed is not None else s.seed, 7]) for s in scenes]
    generator = None
    if noisy and st.noise_source == "torch":
        generator = torch.Generator(device=like["device"]).manual_seed(camera_seed or 0)

    speed = torch.as_tensor([float(v) for v in speeds], **like)
    timeout = torch.as_tensor([task.timeout_for(v) for v in speeds], **like)
    lo, hi = torch.as_tensor(task.bounds_min, **like), torch.as_tensor(task.bounds_max, **like)
    log = _Log(int(math.ceil(float(timeout.max()) * cfg.control_hz)) + 2, n, like, labels=False)
    state = hover_state(torch.as_tensor(task.start, **like).expand(n, 3), af)
    long, flag = dict(dtype=torch.long, device=like["device"]), dict(dtype=torch.bool, device=like["device"])
    track = Tracking(end_code=torch.zeros(n, **long), end_time=torch.zeros(n, **like),
                     final_position=torch.zeros(n, 3, **like), touching=torch.zeros(n, **flag),
                     contact_steps=torch.zeros(n, **long), n_collisions=torch.zeros(n, **long),
                     tick_contact=torch.zeros(n, **flag))
    results: list[EpisodeResult | None] = [None] * n
    policy.reset(n)
    active = torch.ones(n, dtype=torch.bool, device=like["device"])
    active_host = np.ones(n, dtype=bool)  # the same, kept from each tick's end flags (no extra wait)
    tick, time_s = 0, 0.0
    while True:
        # 1. observe the active envs (log the tick's start state), 2. one batched policy call
        row = log.row(tick)
        row["position"][:], row["velocity"][:], row["quat"][:] = state.position, state.velocity, state.quat
        log.time.append(time_s)
        depth = torch.zeros(n, cfg.camera.height, cfg.camera.width, **like)
        if needs_depth:
            noise, dropout = _draws(cfg, st, rngs, generator, active, like) if noisy else (None, None)
            image = camera.render(batch, state.position, state.rotation, active, noise=noise, dropout=dropout)
            depth = torch.where(active[:, None, None], image, depth)
        if cfg.record_depth:
            log.frames.append(depth.to(torch.float32))
        obs = BatchedObservation(depth, speed, state.quat, state.position, state.velocity, active, time_s, tick, batch,
                                 active_host.copy())
        commands, labels = _commands(policy(obs), n, like)
        if labels is not None:
            log.labels = True
            row["label"][:] = labels
        bad = (~torch.isfinite(commands).all(1) & active).any()
        candidates = contact_candidates(state, speed, active, batch, task.body_radius_m, cfg.control_hz)
        command = torch.where(active[:, None], commands, torch.zeros_like(commands))  # finished envs hover
        track = track._replace(tick_contact=torch.zeros_like(active))
        # 3. physics steps with the cascaded controller; contact, goal and bounds of the running envs
        for _ in range(substeps):
            time_s += dt
            # torch.full fills on the device; torch.tensor would copy from the host and, on a GPU, wait for it
            state, track = substep(state, track, command, candidates, torch.full((), time_s, **like), task.goal_x_m,
                                   lo, hi, batch, af, gains, dt, task.body_radius_m)
        # 4. log the tick, the timeouts, close the episodes that ended
        row["command"][:], row["contact"][:] = commands, track.tick_contact
        timed_out = active & (track.end_code == 0) & (time_s >= timeout - 1e-9)
        track = track._replace(end_code=torch.where(timed_out, 2, track.end_code),
                               end_time=torch.where(timed_out, time_s, track.end_time),
                               final_position=torch.where(timed_out[:, None], state.position, track.final_position))
        flags = torch.cat([bad[None], active & (track.end_code != 0)]).cpu()  # the tick's one synchronisation
        if flags[0]:
            raise ValueError(f"policy returned non-finite commands at tick {tick}")
        for i in np.flatnonzero(flags[1:].numpy()).tolist():
            active_host[i] = False
            results[i] = _finish(i, tick + 1, scenes[i], float(speeds[i]), log, dt, track)
            if on_episode_end is not None:
                on_episode_end(i, results[i])
        active = track.end_code == 0
        tick += 1
        if all(r is not None for r in results):
            return results  # type: ignore[return-value]


def _commands(out, n: int, like: dict) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(commands, labels or None) from what a batched policy returned, checked for shape (finiteness later)."""
    labels = None
    if isinstance(out, tuple):
        out, labels = out
        labels = torch.as_tensor(labels, **like)
        if labels.shape != (n, 3):
            raise ValueError(f"policy returned labels of shape {tuple(labels.shape)} (expected ({n}, 3))")
    commands = torch.as_tensor(out, **like)
    if commands.shape != (n, 3):
        raise ValueError(f"policy returned commands of shape {tuple(commands.shape)} (expected ({n}, 3))")
    return commands, labels


def _draws(cfg: RolloutConfig, st: BatchedSettings, rngs, generator, active, like):
    """Noise (m) and dropout draws (E, H, W) for the active envs, as the numpy engine draws them."""
    cam = cfg.camera
    shape = (len(rngs), cam.height, cam.width)
    if st.noise_source == "torch":
        noise = cam.noise_std_m * torch.randn(shape, generator=generator, **like) if cam.noise_std_m > 0 else None
        dropout = torch.rand(shape, generator=generator, **like) if cam.dropout_prob > 0 else None
        return noise, dropout
    noise = np.zeros(shape) if cam.noise_std_m > 0 else None
    dropout = np.ones(shape) if cam.dropout_prob > 0 else None
    for i in np.flatnonzero(active.cpu().numpy()):
        if noise is not None:  # the numpy camera's order: noise first, then dropout
            noise[i] = rngs[i].normal(0.0, cam.noise_std_m, shape[1:])
        if dropout is not None:
            dropout[i] = rngs[i].random(shape[1:])
    return (None if noise is None else torch.as_tensor(noise, **like),
            None if dropout is None else torch.as_tensor(dropout, **like))


def _finish(i: int, ticks: int, scene: Scene, speed: float, log: _Log, dt: float, track: Tracking) -> EpisodeResult:
    """Episode i's result: its log rows 0 .. ticks - 1 and its summary, brought to the host."""

    def host(name):
        return log.tensors[name][:ticks, i].cpu().numpy()

    episode = EpisodeLog(
        time=np.asarray(log.time[:ticks], dtype=np.float64),
        position=host("position").astype(np.float64),
        velocity=host("velocity").astype(np.float64),
        quat=host("quat").astype(np.float64),
        command=host("command").astype(np.float64),
        contact=host("contact").astype(bool),
        depth=torch.stack([f[i] for f in log.frames[:ticks]]).cpu().numpy() if log.frames else None,
        label=host("label").astype(np.float64) if log.labels else None,
    )
    reason = END_CODES[int(track.end_code[i])]
    reached = reason == "goal"
    collisions = int(track.n_collisions[i])
    summary = EpisodeSummary(
        env=scene.env, preset=scene.preset, seed=int(scene.seed), desired_speed=speed, end_reason=str(reason),
        reached_goal=reached, success=reached and collisions == 0, n_collisions=collisions,
        time_in_contact_s=int(track.contact_steps[i]) * dt, duration_s=float(track.end_time[i]),
        final_position=tuple(float(v) for v in track.final_position[i].tolist()),
    )
    return EpisodeResult(scene=scene, log=episode, summary=summary)
