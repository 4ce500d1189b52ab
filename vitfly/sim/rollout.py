"""Lockstep episode engine: N scenes, one batched policy call per control tick.

Each scene gets its own drone; all drones live in one physics back end (``vitfly.sim.physics``); one
step advances them all. At every control tick (``control_hz``, 30 Hz by default, the camera's rate too)
the engine renders the depth images, calls the policy ONCE with an :class:`Observation` of the
whole batch, then runs ``physics_hz / control_hz`` physics steps, each with the cascaded
controller tracking the commands, a contact test, and the goal and bounding-box checks. Finished
episodes stay in the batch (``active`` false, their commands ignored, their drones hover) so a
learned policy always sees the same batch size.

Example::

    from vitfly.sim import make_scene, run_episodes, ExpertPolicy
    scenes = [make_scene("spheres", "medium", seed=s) for s in range(4)]
    results = run_episodes(scenes, speeds=[3.0] * 4, policy=ExpertPolicy())
    results[0].summary.success, results[0].summary.end_reason, results[0].log.position.shape

A policy is any object with ``reset(num_envs)`` and ``__call__(obs) -> (N, 3)`` world-frame
velocity commands in m/s (see :class:`Policy`). A policy that sets ``needs_depth = False`` (the
expert, ``straight``) skips rendering unless ``record_depth`` asks for the frames anyway. A policy
may instead return :class:`LabelledCommands`: the commands to fly plus a label per env (what a
teacher would have commanded, e.g. the expert while a student flies); the engine flies the former
and logs both (``EpisodeLog.command`` and ``EpisodeLog.label``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from vitfly.sim.camera import CameraConfig, DepthCamera
from vitfly.sim.collision import ContactChecker
from vitfly.sim.controller import ControllerGains
from vitfly.sim.physics import make_fleet
from vitfly.sim.quadrotor import Airframe, DroneState
from vitfly.sim.scenes import Scene
from vitfly.sim.sensor_models import FrameDelay, StereoDepthConfig, StereoDepthSensor

END_REASONS = ("goal", "timeout", "out_of_bounds")


@dataclass(frozen=True)
class TaskConfig:
    """The flight task (paper, DodgeDrone rules), world frame, m and s."""

    start: tuple[float, float, float] = (0.0, 0.0, 3.5)
    goal_x_m: float = 60.0
    timeout_s: float = 40.0
    # slow flights get more time: timeout = max(timeout_s, factor * (goal_x - start_x) / speed)
    timeout_speed_factor: float = 2.0
    bounds_min: tuple[float, float, float] = (-5.0, -10.0, 0.0)
    bounds_max: tuple[float, float, float] = (65.0, 10.0, 10.0)
    body_radius_m: float = 0.0  # 0: point drone, as the paper's evaluator; 0.125: the airframe

    def timeout_for(self, desired_speed: float) -> float:
        distance = self.goal_x_m - self.start[0]
        return max(self.timeout_s, self.timeout_speed_factor * distance / max(float(desired_speed), 1e-6))


@dataclass(frozen=True)
class RolloutConfig:
    """Rates and parts of the simulation."""

    physics_hz: float = 240.0
    control_hz: float = 30.0  # policy and camera
    task: TaskConfig = field(default_factory=TaskConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    airframe: Airframe = field(default_factory=Airframe)
    gains: ControllerGains = field(default_factory=ControllerGains)
    record_depth: bool = False  # keep every depth frame in the episode log
    physics: str = "auto"  # back end: "pybullet", "native", or "auto" (pybullet where installed)
    # a stereo sensor model applied to the camera's clean render (vitfly.sim.sensor_models); None: the ideal camera
    sensor: StereoDepthConfig | None = None

    def __post_init__(self) -> None:
        if self.sensor is not None and (self.camera.noise_std_m > 0 or self.camera.dropout_prob > 0):
            raise ValueError("a sensor model replaces the camera's noise_std_m and dropout_prob: set one or the other")

    @property
    def physics_steps_per_tick(self) -> int:
        ratio = self.physics_hz / self.control_hz
        steps = int(round(ratio))
        if steps < 1 or abs(ratio - steps) > 1e-9:
            raise ValueError(f"physics_hz ({self.physics_hz}) must be a multiple of control_hz ({self.control_hz})")
        return steps


@dataclass
class Observation:
    """What the policy sees at one control tick, for all N envs (world frame, SI units).

    depth: (N, H, W) float32 in [0, 1] (zeros where not rendered: inactive envs, or a policy that
    does not need depth); desired_speed: (N,) m/s; quat: (N, 4) (w, x, y, z) body-to-world;
    position: (N, 3) m; velocity: (N, 3) m/s; obstacles: N arrays (K, 4) [x, y, z, radius]
    (privileged: only the expert may use them); active: (N,) bool, false once an env has
    finished; time: (N,) s since each episode's start; tick: control tick index; scenes: the N
    scenes (privileged, for the expert's own obstacle selection), None when not given.
    """

    depth: np.ndarray
    desired_speed: np.ndarray
    quat: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    obstacles: list[np.ndarray]
    active: np.ndarray
    time: np.ndarray
    tick: int
    scenes: list[Scene] | None = None


@dataclass
class LabelledCommands:
    """What a labelling policy returns for all N envs (world frame, m/s): ``command`` (N, 3), flown;
    ``label`` (N, 3), the teacher's command for the same observation (logged, not flown)."""

    command: np.ndarray
    label: np.ndarray


@runtime_checkable
class Policy(Protocol):
    """Maps a batched observation to world-frame velocity commands (N, 3) in m/s (or to
    :class:`LabelledCommands`: commands to fly and a label for each).

    ``reset(num_envs)`` is called once before the first tick of a batch (clear recurrent state).
    Optional attribute ``needs_depth: bool`` (default True): False lets the engine skip rendering.
    """

    def reset(self, num_envs: int) -> None: ...

    def __call__(self, obs: Observation) -> np.ndarray: ...


@dataclass
class EpisodeLog:
    """Per control tick, T ticks (world frame, SI units).

    time (T,) s; position (T, 3) m; velocity (T, 3) m/s; quat (T, 4) (w, x, y, z); command (T, 3)
    m/s, the command flown at that tick; contact (T,) bool, true when the drone touched an
    obstacle at any physics step while that command was applied; depth (T, H, W) float32 in [0, 1]
    when recorded (the frame the policy saw), else None; label (T, 3) m/s, the label the policy
    gave with its command (:class:`LabelledCommands`), else None.
    """

    time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    quat: np.ndarray
    command: np.ndarray
    contact: np.ndarray
    depth: np.ndarray | None = None
    label: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.time)


@dataclass
class EpisodeSummary:
    """Outcome of one episode. Contact is tested at the physics rate.

    n_collisions: collision entries (rising edges of contact); time_in_contact_s: total time in
    contact; reached_goal: crossed x = goal; success: reached the goal with zero collisions;
    end_reason: "goal", "timeout" or "out_of_bounds"; duration_s: simulated time at the end.
    """

    env: str
    preset: str
    seed: int
    desired_speed: float
    end_reason: str
    reached_goal: bool
    success: bool
    n_collisions: int
    time_in_contact_s: float
    duration_s: float
    final_position: tuple[float, float, float]

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass
class EpisodeResult:
    scene: Scene
    log: EpisodeLog
    summary: EpisodeSummary


class _EnvTracker:
    """Bookkeeping of one env during a rollout: log buffers, contact state, end condition."""

    def __init__(self, scene: Scene, speed: float, cfg: RolloutConfig):
        self.scene, self.speed = scene, float(speed)
        self.contact = ContactChecker(scene, cfg.task.body_radius_m)
        self.timeout_s = cfg.task.timeout_for(speed)
        self.obstacles = scene.expert_obstacles()
        self.rows: dict[str, list] = {
            k: [] for k in ("time", "position", "velocity", "quat", "command", "contact", "label")
        }
        self.frames: list[np.ndarray] = []
        self.in_contact = False
        self.tick_contact = False
        self.n_collisions = 0
        self.contact_steps = 0
        self.end_reason: str | None = None
        self.end_time = 0.0
        self.final_position = (0.0, 0.0, 0.0)
        self.candidates: list[tuple] = []


def run_episodes(
    scenes: Sequence[Scene],
    speeds: Sequence[float],
    policy: Policy,
    config: RolloutConfig | None = None,
    on_episode_end: Callable[[int, EpisodeResult], None] | None = None,
    camera_seed: int | None = None,
) -> list[EpisodeResult]:
    """Fly one episode per (scene, desired speed m/s) in lockstep; results in input order.

    ``on_episode_end(i, result)`` is called as soon as episode i finishes (e.g. to write it out).
    ``camera_seed`` seeds sensor noise and dropout, and the sensor model's noise per tick (default: each
    scene's seed).
    """
    cfg = config or RolloutConfig()
    n = len(scenes)
    if len(speeds) != n:
        raise ValueError(f"got {n} scenes but {len(speeds)} speeds")
    if n == 0:
        return []
    substeps, dt = cfg.physics_steps_per_tick, 1.0 / cfg.physics_hz
    task = cfg.task
    lo, hi = tuple(map(float, task.bounds_min)), tuple(map(float, task.bounds_max))
    camera = DepthCamera(cfg.camera)
    needs_depth = bool(getattr(policy, "needs_depth", True)) or cfg.record_depth
    rngs = [np.random.default_rng([camera_seed if camera_seed is not None else s.seed, 7]) for s in scenes]
    sensing = None
    if cfg.sensor is not None:  # (model, per-env seed, per-env frame delay)
        seeds = [int(camera_seed if camera_seed is not None else s.seed) for s in scenes]
        delays = [FrameDelay(cfg.sensor.delay_ticks) for _ in scenes]
        sensing = (StereoDepthSensor(cfg.sensor, cfg.camera), seeds, delays)
    envs = [_EnvTracker(s, v, cfg) for s, v in zip(scenes, speeds, strict=True)]
    speed_arr = np.array([e.speed for e in envs])
    results: list[EpisodeResult | None] = [None] * n
    hover = (0.0, 0.0, 0.0)

    with make_fleet(cfg.physics, n, cfg.airframe, cfg.physics_hz) as fleet:
        fleet.reset(np.tile(np.asarray(task.start, dtype=np.float64), (n, 1)))
        policy.reset(n)
        states = fleet.states()
        tick, time_s = 0, 0.0
        while any(e.end_reason is None for e in envs):
            # 1. observe all envs, 2. one batched policy call
            active = np.array([e.end_reason is None for e in envs])
            obs = _observe(states, envs, active, speed_arr, time_s, tick, camera, rngs, needs_depth, cfg,
                           sensing)
            out = policy(obs)
            labels = None
            if isinstance(out, LabelledCommands):
                out, labels = out.command, np.asarray(out.label, dtype=np.float64)
                if labels.shape != (n, 3) or not np.all(np.isfinite(labels[active])):
                    raise ValueError(f"policy returned labels of shape {labels.shape} (expected ({n}, 3), finite)")
            commands = np.asarray(out, dtype=np.float64)
            if commands.shape != (n, 3) or not np.all(np.isfinite(commands[active])):
                raise ValueError(f"policy returned commands of shape {commands.shape} (expected ({n}, 3), finite)")
            for i, e in enumerate(envs):
                if active[i]:
                    e.tick_contact = False
                    # obstacles out of reach before the next tick (twice the distance at the current
                    # or desired speed, plus margin) are left out of the per-step contact tests
                    reach = 2.0 * max(math.hypot(*states[i].velocity), e.speed, 5.0) / cfg.control_hz + 0.5
                    e.candidates = e.contact.nearby(states[i].position, reach)
            # 3. physics steps with the cascaded controller tracking the commands
            cmd_rows = [tuple(c) if a else hover for c, a in zip(commands.tolist(), active, strict=True)]
            for _ in range(substeps):
                states = fleet.track(cmd_rows, states, cfg.gains)  # cascaded controller + one physics step
                time_s += dt
                for i, e in enumerate(envs):
                    if e.end_reason is None:
                        _physics_checks(e, states[i], time_s, dt, task.goal_x_m, lo, hi)
            # 4. log the tick, close finished episodes
            for i, e in enumerate(envs):
                if not active[i]:
                    continue
                e.rows["command"].append(commands[i].copy())
                if labels is not None:
                    e.rows["label"].append(labels[i].copy())
                e.rows["contact"].append(e.tick_contact)
                if e.end_reason is None and time_s >= e.timeout_s - 1e-9:
                    e.end_reason, e.end_time, e.final_position = "timeout", time_s, states[i].position
                if e.end_reason is not None:
                    results[i] = _finish(e, dt)
                    if on_episode_end is not None:
                        on_episode_end(i, results[i])
            tick += 1
    return results  # type: ignore[return-value]


def _observe(states, envs, active, speed_arr, time_s, tick, camera, rngs, needs_depth, cfg,
             sensing=None) -> Observation:
    n = len(envs)
    position = np.array([s.position for s in states])
    quat = np.array([s.quat for s in states])
    velocity = np.array([s.velocity for s in states])
    depth = np.zeros((n, cfg.camera.height, cfg.camera.width), dtype=np.float32)
    for i, e in enumerate(envs):
        if not active[i]:
            continue
        if needs_depth:
            rot = np.asarray(states[i].rotation).reshape(3, 3)
            if sensing is None:
                depth[i] = camera.render(e.scene, position[i], rot, rngs[i])
            else:
                sensor, seeds, delays = sensing
                frame = sensor.image(camera.metric_depth(e.scene, position[i], rot), seeds[i], tick)
                depth[i] = delays[i](frame)
        e.rows["time"].append(time_s)
        e.rows["position"].append(position[i])
        e.rows["velocity"].append(velocity[i])
        e.rows["quat"].append(quat[i])
        if cfg.record_depth:
            e.frames.append(depth[i].copy())
    return Observation(
        depth=depth,
        desired_speed=speed_arr.copy(),
        quat=quat,
        position=position,
        velocity=velocity,
        obstacles=[e.obstacles for e in envs],
        active=active,
        time=np.full(n, time_s),
        tick=tick,
        scenes=[e.scene for e in envs],
    )


def _physics_checks(e: _EnvTracker, st: DroneState, time_s: float, dt: float, goal_x: float, lo, hi) -> None:
    """Contact bookkeeping and the goal / bounding-box end conditions after one physics step."""
    touching = bool(e.candidates) and e.contact.in_contact(st.position, e.candidates)
    if touching:
        e.contact_steps += 1
        e.tick_contact = True
        if not e.in_contact:
            e.n_collisions += 1
    e.in_contact = touching
    x, y, z = st.position
    if x >= goal_x:
        e.end_reason = "goal"
    elif not (lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]):
        e.end_reason = "out_of_bounds"
    if e.end_reason is not None:
        e.end_time, e.final_position = time_s, tuple(st.position)


def _finish(e: _EnvTracker, dt: float) -> EpisodeResult:
    rows = e.rows
    log = EpisodeLog(
        time=np.asarray(rows["time"], dtype=np.float64),
        position=np.asarray(rows["position"], dtype=np.float64).reshape(-1, 3),
        velocity=np.asarray(rows["velocity"], dtype=np.float64).reshape(-1, 3),
        quat=np.asarray(rows["quat"], dtype=np.float64).reshape(-1, 4),
        command=np.asarray(rows["command"], dtype=np.float64).reshape(-1, 3),
        contact=np.asarray(rows["contact"], dtype=bool),
        depth=np.stack(e.frames) if e.frames else None,
        label=_labels(rows["label"], len(rows["command"])),
    )
    reached = e.end_reason == "goal"
    summary = EpisodeSummary(
        env=e.scene.env,
        preset=e.scene.preset,
        seed=int(e.scene.seed),
        desired_speed=e.speed,
        end_reason=str(e.end_reason),
        reached_goal=reached,
        success=reached and e.n_collisions == 0,
        n_collisions=e.n_collisions,
        time_in_contact_s=e.contact_steps * dt,
        duration_s=float(e.end_time),
        final_position=tuple(float(v) for v in e.final_position),
    )
    return EpisodeResult(scene=e.scene, log=log, summary=summary)


def _labels(rows: list, ticks: int) -> np.ndarray | None:
    """The episode's labels (T, 3), or None when the policy gave none; a policy must label every tick or none."""
    if not rows:
        return None
    if len(rows) != ticks:
        raise ValueError(f"the policy labelled {len(rows)} of {ticks} ticks; label every tick or none")
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)
