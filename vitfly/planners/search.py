"""FastPlanner-like kinodynamic search on the local map: constant-acceleration primitives expanded level by
level from the current state (a beam keeps the cheapest nodes), collisions rejected on the map's distance
field, the winner smoothed with a B-spline and time-stretched to the speed and acceleration limits.

Cost of a primitive (lower is better): effort (|a|^2 tau), minus progress along the goal direction, the
deviation from the design speed, a soft clearance penalty inside ``safe_m``, and a small pull toward the
home line (lateral / vertical centre of the course), as FastPlanner's goal point.

Escape rule: a drone that starts inside the margin (it braked toward an obstacle seen late) or outside the
course's box would find every primitive "in collision" and hold position there for ever; so the limits a
primitive must keep are the margin and the box, or where the drone starts if that is already worse (a
sample may not come closer to a mapped point, nor further out of the box, than the start). Primitives that
move away stay allowed, and the clearance cost steers toward them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vitfly.planners.bounds import box_excess_m
from vitfly.planners.mapping import LocalMap
from vitfly.planners.trajectory import Plan, limit_feasibility, smooth_through_waypoints


@dataclass(frozen=True)
class SearchSettings:
    speed_mps: float = 3.0  # design speed (set from PlannerOptions.design_speed_mps): aimed for, and the limit
    accel_max_mps2: float = 4.0
    primitive_s: float = 0.5  # duration of one constant-acceleration primitive
    levels: int = 3  # primitives per trajectory (horizon = levels * primitive_s)
    accel_steps: int = 5  # acceleration values per axis in [-accel_max, accel_max]
    beam_width: int = 32  # nodes kept per level
    samples_per_primitive: int = 5  # collision checks along each primitive
    margin_m: float = 0.6  # a sample closer than this to a mapped point is a collision
    safe_m: float = 1.5  # clearance below this is penalised
    weight_progress: float = 10.0
    weight_speed: float = 2.0
    weight_effort: float = 0.2
    weight_clearance: float = 30.0
    weight_home: float = 0.5
    home_yz_m: tuple[float, float] = (0.0, 3.5)
    z_min_m: float = 0.5
    z_max_m: float = 9.5
    y_abs_max_m: float = 9.0
    sample_dt_s: float = 0.05  # spacing of the smoothed plan's samples


def acceleration_primitives(accel_max_mps2: float, steps: int) -> np.ndarray:
    """(steps^3, 3) accelerations on a grid over [-a_max, a_max]^3, those inside the a_max ball."""
    axis = np.linspace(-accel_max_mps2, accel_max_mps2, steps)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid[np.linalg.norm(grid, axis=1) <= accel_max_mps2 * (1 + 1e-9)]


def kinodynamic_search(local_map: LocalMap, position_m, velocity_mps, goal_direction, s: SearchSettings) -> Plan | None:
    """The cheapest collision-free sequence of ``s.levels`` primitives from (position, velocity), world frame,
    smoothed and limited; None when every first primitive collides."""
    goal = np.asarray(goal_direction, dtype=np.float64)
    goal = goal / np.linalg.norm(goal)
    accels = acceleration_primitives(s.accel_max_mps2, s.accel_steps)
    tau = s.primitive_s
    t = tau * np.arange(1, s.samples_per_primitive + 1) / s.samples_per_primitive  # (S,)
    p = np.asarray(position_m, dtype=np.float64).reshape(1, 3)
    v = np.asarray(velocity_mps, dtype=np.float64).reshape(1, 3)
    cost = np.zeros(1)
    # the escape rule: where the start already breaks a limit, the start is the limit (see the module doc)
    margin_m = min(s.margin_m, float(local_map.distance_m(p, upper_bound_m=s.margin_m)[0]))
    start_excess_m = box_excess_m(p[0, 1], p[0, 2], s)
    history: list[np.ndarray] = [p]  # end positions per level, rows follow the surviving nodes
    velocities: list[np.ndarray] = [v]
    for _ in range(s.levels):
        # (N, P, S, 3) samples along every child primitive
        samples = p[:, None, None] + v[:, None, None] * t[:, None] + 0.5 * accels[None, :, None] * (t**2)[:, None]
        v_end = v[:, None] + accels[None] * tau  # (N, P, 3)
        clearance = local_map.distance_m(samples, upper_bound_m=s.safe_m).min(axis=2)  # (N, P)
        y, z = samples[..., 1], samples[..., 2]
        ok = (
            (clearance >= margin_m)
            # over the design speed only while slowing down (the drone may start faster than it)
            & ((np.linalg.norm(v_end, axis=2) <= s.speed_mps * 1.05)
               | (np.linalg.norm(v_end, axis=2) < np.linalg.norm(v, axis=1)[:, None]))
            & np.all(box_excess_m(y, z, s) <= start_excess_m + 1e-9, axis=2)
        )
        if not ok.any():
            break
        end = samples[:, :, -1]
        progress = (end - p[:, None]) @ goal
        home = np.abs(end[..., 1] - s.home_yz_m[0]) + np.abs(end[..., 2] - s.home_yz_m[1])
        shortfall = np.maximum(0.0, s.safe_m - np.minimum(clearance, s.safe_m))
        step_cost = (
            s.weight_effort * np.sum(accels**2, axis=1)[None] * tau
            - s.weight_progress * progress
            + s.weight_speed * (np.linalg.norm(v_end, axis=2) - s.speed_mps) ** 2 * tau
            + s.weight_clearance * shortfall**2
            + s.weight_home * home * tau
        )
        total = np.where(ok, cost[:, None] + step_cost, np.inf)
        best = np.argsort(total, axis=None)[: min(s.beam_width, int(ok.sum()))]
        parent, child = np.unravel_index(best, total.shape)
        history = [h[parent] for h in history] + [end[parent, child]]
        velocities = [u[parent] for u in velocities] + [v_end[parent, child]]
        p, v, cost = end[parent, child], v_end[parent, child], total[parent, child]
    if len(history) == 1:
        return None
    # the winner (row 0: the beam is sorted by cost) through its level ends, smoothed and limited
    waypoints = np.stack([h[0] for h in history])
    times = tau * np.arange(len(waypoints))
    plan = smooth_through_waypoints(times, waypoints, velocities[0][0], velocities[-1][0], s.sample_dt_s)
    if local_map.distance_m(plan.position_m, upper_bound_m=s.margin_m).min() < margin_m - 1e-9:
        # the spline cut a corner the primitives went round: fly the primitives' own path instead
        tk = np.arange(0.0, times[-1] + 1e-9, s.sample_dt_s)
        level = np.minimum((tk // tau).astype(int), len(waypoints) - 2)
        dt = (tk - level * tau)[:, None]
        v0 = np.stack([u[0] for u in velocities])
        acc = (v0[1:] - v0[:-1]) / tau
        pos = waypoints[level] + v0[level] * dt + 0.5 * acc[level] * dt**2
        plan = Plan(tk, pos, v0[level] + acc[level] * dt)
    return limit_feasibility(plan, s.speed_mps, s.accel_max_mps2)
