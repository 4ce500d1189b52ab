"""The paper's flight metrics as pure functions of one flown path.

A path is sampled at the control ticks of a trial: ``time_s`` (T,) seconds since the trial's
start, ``position`` (T, 3) m and ``velocity`` (T, 3) m/s measured in the world frame (x forward,
y left, z up), ``command`` (T, 3) the world-frame velocity command in m/s, and ``contact`` (T,)
bool, true while the drone is inside an obstacle. Each sample's contact flag holds until the
next sample (sample-and-hold); the last sample holds for one more tick of the same length.

Undefined values (a rate over a zero-length path, time in collision of a trial without a
collision, time to goal of a trial that never got there) are ``math.nan``; aggregates skip them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from vitfly.errors import VitflyError

SMOOTHING_WINDOW = 4  # commands are smoothed over 4 ticks before differencing (paper code)


def _as_time(time_s) -> np.ndarray:
    t = np.asarray(time_s, dtype=np.float64)
    if t.ndim != 1 or len(t) == 0:
        raise VitflyError(f"path field 'time': expected a non-empty 1-D array, got shape {t.shape}")
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        raise VitflyError("path field 'time': expected strictly increasing sample times")
    return t


def _as_vectors(name: str, values, n: int) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (n, 3):
        raise VitflyError(f"path field {name!r}: expected shape ({n}, 3), got {v.shape}")
    return v


def tick_durations_s(time_s) -> np.ndarray:
    """Duration each sample holds for (s): t[i+1] - t[i], and the last interval again for the last sample."""
    t = _as_time(time_s)
    if len(t) == 1:
        return np.zeros(1)
    d = np.diff(t)
    return np.append(d, d[-1])


def collision_entries(contact) -> int:
    """Number of collisions = rising edges of the contact flag (contact at the first sample counts as one)."""
    c = np.asarray(contact, dtype=bool)
    previous = np.concatenate(([False], c[:-1]))
    return int(np.count_nonzero(c & ~previous))


def contact_time_s(time_s, contact) -> float:
    """Total time spent inside obstacles (s)."""
    c = np.asarray(contact, dtype=bool)
    return float(np.sum(tick_durations_s(time_s)[c]))


def time_in_collision_per_obstacle_s(time_s, contact) -> float:
    """Time in contact divided by the number of collision entries (s); nan without a collision."""
    entries = collision_entries(contact)
    return contact_time_s(time_s, contact) / entries if entries else math.nan


def path_length_m(position) -> float:
    """Length of the flown polyline (m)."""
    p = np.asarray(position, dtype=np.float64)
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0


def acceleration_change_sum(time_s, velocity) -> float:
    """sum_i |a_{i+1} - a_i| with a_i = (v_{i+1} - v_i) / (t_{i+1} - t_i) from measured velocity (m/s^2)."""
    t = _as_time(time_s)
    v = _as_vectors("velocity", velocity, len(t))
    if len(t) < 3:
        return 0.0
    a = np.diff(v, axis=0) / np.diff(t)[:, None]
    return float(np.sum(np.linalg.norm(np.diff(a, axis=0), axis=1)))


def energy_cost(time_s, velocity, position, reference_length_m: float | None = None) -> float:
    """Energy cost (1/s^2): summed change of measured acceleration per metre.

    Divides by the path length flown (paper code), or by ``reference_length_m`` when given (the
    AvoidBench variant: the optimal path length, e.g. the straight start-to-goal distance).
    """
    length = path_length_m(position) if reference_length_m is None else float(reference_length_m)
    total = acceleration_change_sum(time_s, velocity)
    return total / length if length > 0 else math.nan


def moving_average(values, window: int = SMOOTHING_WINDOW) -> np.ndarray:
    """Mean over each run of ``window`` consecutive samples along axis 0 (fewer rows: T - window + 1)."""
    x = np.asarray(values, dtype=np.float64)
    if len(x) < window:
        return x[:0]
    csum = np.cumsum(np.concatenate((np.zeros((1, *x.shape[1:])), x)), axis=0)
    return (csum[window:] - csum[:-window]) / window


def commanded_acceleration(time_s, command, position, window: int = SMOOTHING_WINDOW) -> float:
    """Commanded acceleration per metre flown (1/s^2, paper code).

    Commands are smoothed by a ``window``-sample moving average (sample times likewise), then the
    norms |d v_cmd / dt| between consecutive smoothed samples are summed and divided by the path length.
    """
    t = _as_time(time_s)
    cmd = _as_vectors("command", command, len(t))
    length = path_length_m(position)
    smooth_cmd, smooth_t = moving_average(cmd, window), moving_average(t, window)
    if len(smooth_t) < 2 or length <= 0:
        return math.nan if length <= 0 else 0.0
    rates = np.linalg.norm(np.diff(smooth_cmd, axis=0), axis=1) / np.diff(smooth_t)
    return float(np.sum(rates) / length)


def lateral_deviation_m(position) -> tuple[float, float]:
    """(mean, max) of |y - y_start| (m): sideways distance from the straight line along x."""
    p = np.asarray(position, dtype=np.float64)
    dev = np.abs(p[:, 1] - p[0, 1])
    return float(dev.mean()), float(dev.max())


def mean_forward_speed_mps(velocity) -> float:
    """Mean measured forward (world x) speed over the trial (m/s)."""
    return float(np.mean(np.asarray(velocity, dtype=np.float64)[:, 0]))


def time_to_goal_s(time_s, position, goal_x_m: float) -> float:
    """Time from the trial's start to the first sample at or beyond ``goal_x_m`` (s); nan if never."""
    t = _as_time(time_s)
    reached = np.flatnonzero(np.asarray(position, dtype=np.float64)[:, 0] >= goal_x_m)
    return float(t[reached[0]] - t[0]) if len(reached) else math.nan


@dataclass(frozen=True)
class TrialMetrics:
    """Every per-trial metric; units in the names. nan = undefined for this trial."""

    collisions: int
    success: bool
    reached_goal: bool
    contact_time_s: float
    time_in_collision_s: float  # per obstacle: contact time / collisions
    energy_cost: float  # per metre flown (paper code)
    energy_cost_optimal: float  # per metre of the straight start-to-goal line (AvoidBench)
    cmd_acc: float
    path_length_m: float
    lateral_dev_mean_m: float
    lateral_dev_max_m: float
    forward_speed_mps: float
    speed_ratio: float  # mean forward speed / desired speed
    time_to_goal_s: float
    processing_ms: float  # policy time per control tick

    def to_dict(self) -> dict:
        return asdict(self)


def trial_metrics(
    time_s,
    position,
    velocity,
    command,
    contact,
    *,
    desired_speed_mps: float,
    goal_x_m: float,
    reached_goal: bool,
    processing_ms: float = math.nan,
) -> TrialMetrics:
    """All metrics of one trial from its flown path (see the module docstring for the arrays)."""
    t = _as_time(time_s)
    pos = _as_vectors("position", position, len(t))
    vel = _as_vectors("velocity", velocity, len(t))
    cmd = _as_vectors("command", command, len(t))
    hit = np.asarray(contact, dtype=bool)
    if hit.shape != t.shape:
        raise VitflyError(f"path field 'contact': expected shape {t.shape}, got {hit.shape}")
    n_coll = collision_entries(hit)
    lat_mean, lat_max = lateral_deviation_m(pos)
    fwd = mean_forward_speed_mps(vel)
    optimal = goal_x_m - pos[0, 0]
    return TrialMetrics(
        collisions=n_coll,
        success=bool(reached_goal) and n_coll == 0,
        reached_goal=bool(reached_goal),
        contact_time_s=contact_time_s(t, hit),
        time_in_collision_s=time_in_collision_per_obstacle_s(t, hit),
        energy_cost=energy_cost(t, vel, pos),
        energy_cost_optimal=energy_cost(t, vel, pos, reference_length_m=optimal) if optimal > 0 else math.nan,
        cmd_acc=commanded_acceleration(t, cmd, pos),
        path_length_m=path_length_m(pos),
        lateral_dev_mean_m=lat_mean,
        lateral_dev_max_m=lat_max,
        forward_speed_mps=fwd,
        speed_ratio=fwd / desired_speed_mps if desired_speed_mps > 0 else math.nan,
        time_to_goal_s=time_to_goal_s(t, pos, goal_x_m),
        processing_ms=float(processing_ms),
    )


@dataclass(frozen=True)
class Spread:
    """Mean, sample standard deviation and count of the defined (finite) values."""

    mean: float
    std: float
    n: int


def spread(values) -> Spread:
    """Mean and spread over trials, skipping undefined (nan/None) values; std is 0 for one value."""
    x = np.asarray([math.nan if v is None else float(v) for v in values], dtype=np.float64)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return Spread(math.nan, math.nan, 0)
    return Spread(float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else 0.0, int(len(x)))
