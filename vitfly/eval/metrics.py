"""The paper's flight metrics as pure functions of one flown path, defined as the original analysis code.

A path is sampled at the control ticks of a trial: ``time_s`` (T,) seconds since the trial's
start, ``position`` (T, 3) m and ``velocity`` (T, 3) m/s measured in the world frame (x forward,
y left, z up), ``command`` (T, 3) the world-frame velocity command in m/s, and ``contact`` (T,)
bool, true while the drone is inside an obstacle. Each sample's contact flag holds until the
next sample (sample-and-hold); the last sample holds for one more tick of the same length. A trial
may also carry its end state (``end_time_s``, ``end_position``): the physics step at which it ended,
e.g. the first one at or beyond the goal, which no control tick reaches.

Where the original project's analysis scripts define a metric (``analysis/gen_metrics.py``,
``Analysis/gen_collision_plots.py``, ``envtest/ros/evaluation_node.py``), the default here is that
definition; vitfly's own variants are kept beside it under their own names:

- success: the paper's is a trial without a collision (``success_paper``); ``success_strict``
  also needs the goal reached;
- time in collision: contact time / collisions for a trial with a collision and 0 for one without,
  so that its mean runs over all trials (``time_in_collision_s``, as the paper plots it);
  ``time_in_collision_colliding_s`` is undefined without a collision (a mean over colliding trials);
- commanded acceleration: commands smoothed per axis by ``np.convolve(c, ones(4) / 4, "same")``;
- time to goal: from crossing x = start + 0.5 m (the original evaluator's start mark) to crossing
  the goal, each crossing interpolated linearly between the samples either side.

Undefined values (a rate over a zero-length path, time to goal of a trial that never got there)
are ``math.nan``; aggregates skip them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from vitfly.errors import VitflyError

SMOOTHING_WINDOW = 4  # commands are smoothed over 4 ticks before differencing (paper code)
MOVING_X_M = 0.1  # the original counts distance (and commands) only once x > start + 0.1 m
START_MARK_X_M = 0.5  # the original evaluator starts its clock when x first exceeds start + 0.5 m
DT_GUARD_S2 = 1e-9  # the original divides by dt^2 + 1e-9 (s^2) rather than by dt^2


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


def time_in_collision_s(time_s, contact) -> float:
    """Time in contact per collision (s), 0 for a trial without a collision (the paper's plot).

    ``Analysis/gen_collision_plots.py`` appends 0 for such trials and averages over all of them.
    """
    entries = collision_entries(contact)
    return contact_time_s(time_s, contact) / entries if entries else 0.0


def time_in_collision_colliding_s(time_s, contact) -> float:
    """Time in contact per collision (s); nan without a collision (vitfly's variant: averaged over
    colliding trials only)."""
    entries = collision_entries(contact)
    return contact_time_s(time_s, contact) / entries if entries else math.nan


def path_length_m(position) -> float:
    """Length of the flown polyline (m)."""
    p = np.asarray(position, dtype=np.float64)
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0


def moving_mask(position) -> np.ndarray:
    """Samples the original analysis keeps: x > x_start + 0.1 m (it keeps pos_x > 0.1 with its start at 0)."""
    p = np.asarray(position, dtype=np.float64)
    return p[:, 0] > p[0, 0] + MOVING_X_M


def distance_travelled_m(position) -> float:
    """Length of the polyline through the samples past x_start + 0.1 m (m): the original's divisor."""
    p = np.asarray(position, dtype=np.float64)
    return path_length_m(p[moving_mask(p)])


def _rates(values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Finite-difference rates between consecutive samples, dv * dt / (dt^2 + 1e-9), as the original."""
    dt = np.diff(t)[:, None]
    return np.diff(values, axis=0) * dt / (dt * dt + DT_GUARD_S2)


def acceleration_change_sum(time_s, velocity) -> float:
    """sum_i |a_{i+1} - a_i| with a_i = (v_{i+1} - v_i) / (t_{i+1} - t_i) from measured velocity (m/s^2)."""
    t = _as_time(time_s)
    v = _as_vectors("velocity", velocity, len(t))
    if len(t) < 3:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(_rates(v, t), axis=0), axis=1)))


def energy_cost(time_s, velocity, position, reference_length_m: float | None = None) -> float:
    """Energy cost (1/s^2): summed change of measured acceleration per metre (``gen_metrics.jerkCost``).

    The change is summed over every sample; it is divided by the distance travelled past
    x_start + 0.1 m (paper code), or by ``reference_length_m`` when given (the AvoidBench variant:
    the optimal path length, e.g. the straight start-to-goal distance).
    """
    length = distance_travelled_m(position) if reference_length_m is None else float(reference_length_m)
    total = acceleration_change_sum(time_s, velocity)
    return total / length if length > 0 else math.nan


def smooth_commands(command, window: int = SMOOTHING_WINDOW) -> np.ndarray:
    """Per-axis ``np.convolve(c, ones(window) / window, mode="same")``, as the original (T, 3).

    "same" keeps T samples, zero-padded at both ends: sample i averages c[i-2 .. i+1] for a window
    of 4, with zeros outside the path, so the first and last samples are pulled towards 0.
    """
    c = np.asarray(command, dtype=np.float64)
    kernel = np.ones(window) / window
    return np.stack([np.convolve(c[:, k], kernel, mode="same") for k in range(c.shape[1])], axis=1)


def commanded_acceleration(time_s, command, position, window: int = SMOOTHING_WINDOW) -> float:
    """Commanded acceleration per metre travelled (1/s^2, ``gen_metrics.commandedAccel``).

    Of the samples past x_start + 0.1 m: commands smoothed per axis (``smooth_commands``), then
    sum_i |(c_{i+1} - c_i) / dt_i| over consecutive samples, divided by the distance travelled over
    the same samples. nan with fewer than ``window`` such samples (the original's "same" convolution
    would be longer than the path) or no distance.
    """
    t = _as_time(time_s)
    cmd = _as_vectors("command", command, len(t))
    pos = _as_vectors("position", position, len(t))
    keep = moving_mask(pos)
    t, cmd, pos = t[keep], cmd[keep], pos[keep]
    length = path_length_m(pos)
    if len(t) < window or length <= 0:
        return math.nan
    rates = _rates(smooth_commands(cmd, window), t)
    return float(np.sum(np.linalg.norm(rates, axis=1)) / length)


def lateral_deviation_m(position) -> tuple[float, float]:
    """(mean, max) of |y - y_start| (m): sideways distance from the straight line along x."""
    p = np.asarray(position, dtype=np.float64)
    dev = np.abs(p[:, 1] - p[0, 1])
    return float(dev.mean()), float(dev.max())


def mean_forward_speed_mps(velocity) -> float:
    """Mean measured forward (world x) speed over the trial (m/s)."""
    return float(np.mean(np.asarray(velocity, dtype=np.float64)[:, 0]))


def crossing_time_s(time_s, x_m, level_m: float) -> float:
    """Time at which x first reaches ``level_m`` (s), linear between the samples either side; nan if never."""
    t, x = np.asarray(time_s, dtype=np.float64), np.asarray(x_m, dtype=np.float64)
    hits = np.flatnonzero(x >= level_m)
    if len(hits) == 0:
        return math.nan
    i = int(hits[0])
    if i == 0:
        return float(t[0])
    frac = (level_m - x[i - 1]) / (x[i] - x[i - 1])  # x[i-1] < level <= x[i]: no division by 0
    return float(t[i - 1] + frac * (t[i] - t[i - 1]))


def time_to_goal_s(time_s, position, goal_x_m: float, end_time_s: float | None = None,
                   end_position=None) -> float:
    """Time from crossing x = x_start + 0.5 m to crossing ``goal_x_m`` (s); nan if the goal was not crossed.

    The original evaluator (``evaluation_node.py``) starts its clock when x first exceeds 0.5 m (its
    start is at x = 0) and stops it when x first reaches the goal. Both crossings are interpolated
    linearly here. A trial ends at the physics step that reaches the goal, between control ticks:
    pass that end state (``end_time_s``, ``end_position``) so that the crossing can be found.
    """
    t = _as_time(time_s)
    x = np.asarray(position, dtype=np.float64)[:, 0]
    if end_time_s is not None and end_position is not None and float(end_time_s) > t[-1]:
        t, x = np.append(t, float(end_time_s)), np.append(x, float(np.asarray(end_position)[0]))
    goal = crossing_time_s(t, x, goal_x_m)
    start = crossing_time_s(t, x, x[0] + START_MARK_X_M)
    return goal - start if math.isfinite(goal) else math.nan


@dataclass(frozen=True)
class TrialMetrics:
    """Every per-trial metric; units in the names. nan = undefined for this trial."""

    collisions: int
    success_paper: bool  # no collision (the paper's success)
    success_strict: bool  # reached the goal and no collision (vitfly's stricter variant)
    reached_goal: bool
    contact_time_s: float
    time_in_collision_s: float  # contact time / collisions; 0 without a collision (the paper's plot)
    time_in_collision_colliding_s: float  # the same, nan without a collision (mean over colliding trials)
    energy_cost: float  # per metre travelled (paper code)
    energy_cost_optimal: float  # per metre of the straight start-to-goal line (AvoidBench)
    cmd_acc: float  # smoothed commands, per metre travelled (paper code)
    path_length_m: float
    lateral_dev_mean_m: float
    lateral_dev_max_m: float
    forward_speed_mps: float
    speed_ratio: float  # mean forward speed / desired speed
    time_to_goal_s: float  # x_start + 0.5 m -> goal, interpolated crossings
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
    end_time_s: float | None = None,
    end_position=None,
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
        success_paper=n_coll == 0,
        success_strict=bool(reached_goal) and n_coll == 0,
        reached_goal=bool(reached_goal),
        contact_time_s=contact_time_s(t, hit),
        time_in_collision_s=time_in_collision_s(t, hit),
        time_in_collision_colliding_s=time_in_collision_colliding_s(t, hit),
        energy_cost=energy_cost(t, vel, pos),
        energy_cost_optimal=energy_cost(t, vel, pos, reference_length_m=optimal) if optimal > 0 else math.nan,
        cmd_acc=commanded_acceleration(t, cmd, pos),
        path_length_m=path_length_m(pos),
        lateral_dev_mean_m=lat_mean,
        lateral_dev_max_m=lat_max,
        forward_speed_mps=fwd,
        speed_ratio=fwd / desired_speed_mps if desired_speed_mps > 0 else math.nan,
        time_to_goal_s=time_to_goal_s(t, pos, goal_x_m, end_time_s, end_position),
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
