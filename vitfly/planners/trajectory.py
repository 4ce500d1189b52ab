"""A planned trajectory as dense samples, the smoothing and feasibility limits shared by the planners, and the
tracking law that turns a plan into a velocity command."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import make_interp_spline


@dataclass(frozen=True)
class Plan:
    """World-frame trajectory samples: ``time_s`` (K,) from the plan's start, ``position_m`` (K, 3),
    ``velocity_mps`` (K, 3). ``stop``: the planner found nothing safe and asks to hold position."""

    time_s: np.ndarray
    position_m: np.ndarray
    velocity_mps: np.ndarray
    stop: bool = False


def stop_plan(position_m) -> Plan:
    p = np.asarray(position_m, dtype=np.float64).reshape(1, 3)
    return Plan(np.zeros(1), p, np.zeros((1, 3)), stop=True)


def smooth_through_waypoints(
    times_s: np.ndarray, waypoints_m: np.ndarray, start_velocity_mps, end_velocity_mps, sample_dt_s: float
) -> Plan:
    """A cubic B-spline through the waypoints (``scipy.interpolate.make_interp_spline``) with the start and
    end velocities clamped, sampled every ``sample_dt_s``: C2, so the velocity reference has no jumps."""
    spline = make_interp_spline(
        times_s, waypoints_m, k=3, bc_type=([(1, np.asarray(start_velocity_mps))], [(1, np.asarray(end_velocity_mps))])
    )
    t = np.arange(0.0, times_s[-1] + 1e-9, sample_dt_s)
    return Plan(t, spline(t), spline.derivative(1)(t))


def limit_feasibility(plan: Plan, speed_max_mps: float, accel_max_mps2: float) -> Plan:
    """Stretch the plan's time uniformly so that its speed stays <= ``speed_max_mps`` and its acceleration
    (finite differences) <= ``accel_max_mps2`` (same path; a stretch by f divides speeds by f, accelerations
    by f^2)."""
    if len(plan.time_s) < 2:
        return plan
    speed = np.linalg.norm(plan.velocity_mps, axis=1).max()
    accel = np.linalg.norm(np.diff(plan.velocity_mps, axis=0), axis=1) / np.diff(plan.time_s)
    factor = max(1.0, speed / speed_max_mps, float(np.sqrt(accel.max() / accel_max_mps2)) if len(accel) else 1.0)
    if factor == 1.0:
        return plan
    return Plan(plan.time_s * factor, plan.position_m, plan.velocity_mps / factor, plan.stop)


def track(plan: Plan, position_m, position_gain_per_s: float, lookahead_s: float) -> np.ndarray:
    """Velocity command (3,) m/s, world frame: the plan's velocity ``lookahead_s`` past the sample nearest the
    drone, plus a pull back onto the path. Indexed by where the drone is, not by the clock, so a plan that
    started from an older state (planning latency) is joined where the drone now is."""
    if plan.stop:
        return position_gain_per_s * (plan.position_m[0] - np.asarray(position_m, dtype=np.float64))
    p = np.asarray(position_m, dtype=np.float64)
    nearest = int(np.argmin(np.linalg.norm(plan.position_m - p, axis=1)))
    ahead = int(np.searchsorted(plan.time_s, plan.time_s[nearest] + lookahead_s))
    ahead = min(ahead, len(plan.time_s) - 1)
    return plan.velocity_mps[ahead] + position_gain_per_s * (plan.position_m[nearest] - p)
