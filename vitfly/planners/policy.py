"""The modular baselines as lockstep policies: depth -> map every tick, a replan at a fixed rate whose
compute time is charged in simulated time, the current plan tracked at the control rate.

The latency rule: a replan started at tick time t with the state and map of that tick takes c seconds
(``time.thread_time`` around it: the planning thread's CPU time, which other processes sharing the machine do
not inflate, and which equals the wall time on a dedicated core; or ``fixed_latency_s`` for deterministic
runs); its plan is used from the first tick at or after t + c, and until then the previous plan is tracked.
No replan starts while one is pending, so a planner slower than its period replans less often and falls
behind its observations. A failed replan (nothing safe found) yields a plan that holds position.

Scaled variants (the paper's FastPlanner-scaled): the planner works at its design speed and the command
is multiplied by desired speed / design speed.
"""

from __future__ import annotations

import dataclasses
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vitfly.errors import VitflyError
from vitfly.planners.convex import ConvexSettings, convex_plan
from vitfly.planners.mapping import LocalMap
from vitfly.planners.perception import depth_to_world_points
from vitfly.planners.search import SearchSettings, kinodynamic_search
from vitfly.planners.trajectory import Plan, stop_plan, track
from vitfly.sim.camera import CameraConfig
from vitfly.sim.quadrotor import quat_wxyz_to_matrix

# bump when a change to vitfly/planners alters what a planner flies: it is part of the policy fingerprint
PLANNERS_CODE_VERSION = 2
PLANNER_NAMES = ("fastplanner", "fastplanner_scaled", "convex", "convex_scaled")
METHODS = ("fastplanner", "convex")
DEFAULT_CONFIG = "planners"  # configs/planners.yaml


@dataclass(frozen=True)
class MapSettings:
    voxel_m: float = 0.15
    memory_s: float = 3.0
    behind_m: float = 2.0
    max_points: int = 20000
    depth_stride: int = 2  # every 2nd row and column of the 60 x 90 frame


@dataclass(frozen=True)
class PlannerOptions:
    """One modular planner (m, s, m/s). ``search`` / ``convex``: the method's own settings."""

    method: str = "fastplanner"  # "fastplanner" or "convex"
    scaled: bool = False  # command x desired speed / design speed
    design_speed_mps: float = 3.0
    replan_hz: float = 10.0
    fixed_latency_s: float | None = None  # None: the measured compute time of each replan
    position_gain_per_s: float = 1.0  # tracking: pull back onto the plan
    lookahead_s: float = 0.1  # tracking: command the plan's velocity this far ahead
    goal_direction: tuple[float, float, float] = (1.0, 0.0, 0.0)  # world frame, the course's forward
    map: MapSettings = field(default_factory=MapSettings)
    search: SearchSettings = field(default_factory=SearchSettings)
    convex: ConvexSettings = field(default_factory=ConvexSettings)

    def validate(self, source: str = "planner options") -> PlannerOptions:
        if self.method not in METHODS:
            raise VitflyError(f"{source}: field 'method' is {self.method!r}; expected one of {', '.join(METHODS)}")
        for name in ("design_speed_mps", "replan_hz"):
            if not getattr(self, name) > 0:
                raise VitflyError(f"{source}: field {name!r} must be > 0, got {getattr(self, name)}")
        for section in ("search", "convex"):  # one speed for both methods: the design speed
            if getattr(self, section).speed_mps != 3.0:
                raise VitflyError(f"{source}: field '{section}.speed_mps' is set by 'design_speed_mps'; set that")
        for name in ("voxel_m", "memory_s", "depth_stride", "max_points"):
            if not getattr(self.map, name) > 0:
                raise VitflyError(f"{source}: field 'map.{name}' must be > 0, got {getattr(self.map, name)}")
        if self.fixed_latency_s is not None and self.fixed_latency_s < 0:
            raise VitflyError(f"{source}: field 'fixed_latency_s' must be >= 0 s or null, got {self.fixed_latency_s}")
        return self

    @property
    def settings(self) -> SearchSettings | ConvexSettings:
        """The method's settings at the design speed."""
        chosen = self.search if self.method == "fastplanner" else self.convex
        return dataclasses.replace(chosen, speed_mps=self.design_speed_mps)


def _from_mapping(cls, data, source: str, prefix: str = ""):
    """Dataclass ``cls`` from a YAML mapping (nested sections for nested dataclasses, lists for tuples); an
    unknown field or a value of the wrong kind is one VitflyError line naming it."""
    if not isinstance(data, dict):
        raise VitflyError(f"{source}: {prefix.rstrip('.') or 'planner'} must be a mapping of settings, got {data!r}")
    hints = typing.get_type_hints(cls)
    values = {}
    for key, value in data.items():
        if key not in hints:
            raise VitflyError(f"{source}: unknown field '{prefix}{key}'; known: {', '.join(sorted(hints))}")
        values[key] = _check_value(value, hints[key], source, f"{prefix}{key}")
    return cls(**values)


def _check_value(value, hint, source: str, name: str):
    if dataclasses.is_dataclass(hint):
        return _from_mapping(hint, value, source, f"{name}.")
    args = typing.get_args(hint)
    if type(None) in args:  # X | None
        return None if value is None else _check_value(value, next(a for a in args if a is not type(None)),
                                                       source, name)
    if typing.get_origin(hint) is tuple:
        fixed = Ellipsis not in args
        if not isinstance(value, list) or (fixed and len(value) != len(args)):
            size = f"{len(args)} numbers" if fixed else "numbers"
            raise VitflyError(f"{source}: field {name!r} must be a list of {size}, got {value!r}")
        return tuple(_check_value(v, float, source, name) for v in value)
    if hint is bool and isinstance(value, bool) or hint is str and isinstance(value, str):
        return value
    if hint in (int, float) and isinstance(value, (int, float)) and not isinstance(value, bool):
        if hint is int and not isinstance(value, int):
            raise VitflyError(f"{source}: field {name!r} must be a whole number, got {value!r}")
        return hint(value)
    raise VitflyError(f"{source}: field {name!r} must be {getattr(hint, '__name__', hint)}, got {value!r}")


def load_planner_options(name: str, path: str | Path | None = None) -> PlannerOptions:
    """Options of planner ``name`` from a planners YAML (default: the shipped ``configs/planners.yaml``):
    its ``common`` mapping, then the mapping under ``name`` (wins)."""
    from vitfly.packaged import config_path, read_yaml

    file = config_path(path or DEFAULT_CONFIG)
    data = read_yaml(file)
    if not isinstance(data, dict):
        raise VitflyError(f"{file}: expected a mapping of planner names, got {type(data).__name__}")
    names = [k for k in data if k != "common"]
    if name not in names:
        raise VitflyError(f"modular:{name}: no planner {name!r} in {file}; it defines {', '.join(names) or 'none'}")
    common, own = data.get("common") or {}, data[name] or {}
    if not isinstance(common, dict) or not isinstance(own, dict):
        raise VitflyError(f"{file}: 'common' and {name!r} must be mappings of settings")
    merged = {**common, **own}
    for key in ("map", "search", "convex"):  # nested sections merge key by key
        if isinstance(common.get(key), dict) and isinstance(own.get(key), dict):
            merged[key] = {**common[key], **own[key]}
    return _from_mapping(PlannerOptions, merged, f"{file} [{name}]").validate(f"{file} [{name}]")


@dataclass
class _EnvState:
    local_map: LocalMap
    plan: Plan | None = None  # being tracked
    pending: Plan | None = None  # computed, usable from ``pending_ready_s``
    pending_ready_s: float = 0.0
    next_replan_s: float = 0.0
    replan_ms: list[float] = field(default_factory=list)  # this env's replans, measured compute time (ms)


def _promote_if_ready(env: _EnvState, now_s: float) -> None:
    if env.pending is not None and now_s >= env.pending_ready_s - 1e-9:
        env.plan, env.pending = env.pending, None


class ModularPolicy:
    """Perception -> map -> plan -> track for every active env (``vitfly.sim.rollout.Policy``).

    ``replan_ms``: the measured compute time of every replan so far (ms), whatever ``fixed_latency_s``;
    ``trial_extra(i)``: env ``i``'s own since the last reset, for its trial record.
    """

    needs_depth = True

    def __init__(self, options: PlannerOptions | None = None, camera: CameraConfig | None = None):
        self.config = self.options = (options or PlannerOptions()).validate()
        self.camera = camera or CameraConfig()
        self.replan_ms: list[float] = []
        self._envs: list[_EnvState] = []

    def reset(self, num_envs: int) -> None:
        m = self.options.map
        self._envs = [_EnvState(LocalMap(m.voxel_m, m.memory_s, m.behind_m, m.max_points)) for _ in range(num_envs)]

    def trial_extra(self, i: int) -> dict:
        """What env ``i``'s trial record keeps of the planner: every replan's measured compute time (ms, 0.01 ms
        steps), the latency rule in force (``fixed_latency_s``, null: the measured times were charged), the design
        speed and whether the command is scaled to the desired speed."""
        o = self.options
        return {"replan_ms": [round(ms, 2) for ms in self._envs[i].replan_ms], "fixed_latency_s": o.fixed_latency_s,
                "design_speed_mps": o.design_speed_mps, "scaled": o.scaled}

    def plan(self, local_map: LocalMap, position_m, velocity_mps) -> Plan | None:
        """One replan from the given state on the given map (world frame); None when nothing safe was found."""
        o = self.options
        planner = kinodynamic_search if o.method == "fastplanner" else convex_plan
        return planner(local_map, position_m, velocity_mps, o.goal_direction, o.settings)

    def __call__(self, obs) -> np.ndarray:
        o = self.options
        out = np.zeros((len(obs.active), 3))
        rotations = quat_wxyz_to_matrix(obs.quat)
        for i in np.flatnonzero(obs.active):
            env, now = self._envs[i], float(obs.time[i])
            points = depth_to_world_points(obs.depth[i], obs.position[i], rotations[i], self.camera, o.map.depth_stride)
            env.local_map.insert(points, now, obs.position[i])
            _promote_if_ready(env, now)  # a plan that finished frees the planner for this tick
            if env.pending is None and now >= env.next_replan_s - 1e-9:
                start = time.thread_time()  # CPU time: a busy shared machine does not inflate it
                velocity = obs.velocity[i]
                if o.scaled:  # the planner thinks at its design speed: the flown velocity, scaled back
                    velocity = velocity * o.design_speed_mps / float(obs.desired_speed[i])
                plan = self.plan(env.local_map, obs.position[i], velocity)
                compute_s = time.thread_time() - start
                self.replan_ms.append(1e3 * compute_s)
                env.replan_ms.append(1e3 * compute_s)
                env.pending = plan if plan is not None else stop_plan(obs.position[i])
                env.pending_ready_s = now + (compute_s if o.fixed_latency_s is None else o.fixed_latency_s)
                env.next_replan_s = now + 1.0 / o.replan_hz
            _promote_if_ready(env, now)  # with zero latency, this tick's plan
            if env.plan is None:
                continue  # nothing planned yet: hover
            command = track(env.plan, obs.position[i], o.position_gain_per_s, o.lookahead_s)
            if o.scaled:
                command = command * float(obs.desired_speed[i]) / o.design_speed_mps
            out[i] = command
        return out
