"""A convex free-space method: a polytope free of mapped points carved around a safe seed segment, and the
command toward the point of that polytope that makes the most progress (``scipy.optimize.linprog``, HiGHS).

1. Seed: among directions fanned around the goal direction (nearest first), the first whose segment of
   ``seed_length_m`` keeps ``margin_m`` from every mapped point.
2. Region (an iterative half-space carve, as safe-flight-corridor methods do): take the mapped point nearest
   the seed segment, add the half-space bounded by the plane through it facing the segment, pulled in by
   ``margin_m``; drop the points that plane already excludes; repeat. The region contains the segment.
3. Target: the LP maximises progress along the goal direction minus a small L1 pull toward the home line,
   inside the region and a box of half-size ``region_radius_m`` around the drone.

Escape rule (as the search's): a drone already inside the margin, or outside the course's box, would find no
free seed and hold position there for ever; so a seed may not come closer to a mapped point, nor end further
out of the box, than the drone already is, and inside the margin seeds all round (behind too) are tried.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog

from vitfly.planners.bounds import box_excess_m
from vitfly.planners.mapping import LocalMap
from vitfly.planners.trajectory import Plan, limit_feasibility

ESCAPE_YAW_DEG = tuple(float(a) for a in range(-180, 180, 20))  # seeds all round, for the escape rule


@dataclass(frozen=True)
class ConvexSettings:
    speed_mps: float = 3.0  # design speed (set from PlannerOptions.design_speed_mps)
    accel_max_mps2: float = 4.0  # braking: speed <= sqrt(2 a d) with d the distance to the target
    seed_length_m: float = 4.0
    seed_yaw_deg: tuple[float, ...] = tuple(float(a) for a in range(-60, 61, 10))
    seed_pitch_deg: tuple[float, ...] = (-20.0, -10.0, 0.0, 10.0, 20.0)
    region_radius_m: float = 5.0
    max_planes: int = 40
    margin_m: float = 0.6
    weight_home: float = 0.1
    home_yz_m: tuple[float, float] = (0.0, 3.5)
    z_min_m: float = 0.5
    z_max_m: float = 9.5
    y_abs_max_m: float = 9.0
    plan_s: float = 1.0  # length in time of the straight plan toward the target
    sample_dt_s: float = 0.05


def seed_directions(goal_direction, yaw_deg, pitch_deg) -> np.ndarray:
    """Unit directions (K, 3), fanned around the goal direction (assumed near horizontal), nearest first."""
    goal = np.asarray(goal_direction, dtype=np.float64)
    heading = np.arctan2(goal[1], goal[0])
    yaw, pitch = np.meshgrid(np.radians(yaw_deg), np.radians(pitch_deg), indexing="ij")
    yaw, pitch = yaw.ravel(), pitch.ravel()
    dirs = np.stack([np.cos(pitch) * np.cos(heading + yaw), np.cos(pitch) * np.sin(heading + yaw), np.sin(pitch)], 1)
    return dirs[np.argsort(np.hypot(yaw, pitch), kind="stable")]


def closest_on_segment(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Closest point of segment [a, b] to each of ``points`` (K, 3)."""
    ab = b - a
    s = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return a + s[:, None] * ab


def carve_free_polytope(obstacles_m: np.ndarray, a: np.ndarray, b: np.ndarray, margin_m: float, max_planes: int):
    """Half-spaces (A (K, 3), c (K,)), A q <= c, whose intersection holds segment [a, b] and no obstacle point,
    each face pulled in by ``margin_m``; at most ``max_planes`` of them (points left over are ignored)."""
    normals, offsets = [], []
    remaining = np.asarray(obstacles_m, dtype=np.float64).reshape(-1, 3)
    while len(remaining) and len(normals) < max_planes:
        foot = closest_on_segment(remaining, a, b)
        gap = np.linalg.norm(remaining - foot, axis=1)
        k = int(np.argmin(gap))
        n = (remaining[k] - foot[k]) / max(gap[k], 1e-9)
        # the plane through the nearest point supports the segment side: the segment's points all have
        # n . q <= n . foot (foot is their projection), so pulling it in by min(margin, gap) keeps the segment
        offset = float(n @ remaining[k]) - min(margin_m, gap[k])
        normals.append(n)
        offsets.append(offset)
        remaining = remaining[remaining @ n < n @ remaining[k] - 1e-9]
    return np.array(normals).reshape(-1, 3), np.array(offsets)


def convex_plan(local_map: LocalMap, position_m, velocity_mps, goal_direction, s: ConvexSettings) -> Plan | None:
    """A straight plan toward the LP's target inside the carved region; None when no seed direction is free."""
    p0 = np.asarray(position_m, dtype=np.float64)
    goal = np.asarray(goal_direction, dtype=np.float64)
    goal = goal / np.linalg.norm(goal)
    along = np.linspace(0.0, 1.0, 17)[:, None]
    # the escape rule: where the start already breaks a limit, the start is the limit (see the module doc)
    margin_m = min(s.margin_m, float(local_map.distance_m(p0, upper_bound_m=s.margin_m)))
    start_excess_m = float(box_excess_m(p0[1], p0[2], s))
    directions = seed_directions(goal, s.seed_yaw_deg, s.seed_pitch_deg)
    if margin_m < s.margin_m:  # inside the margin, the way out may lie behind: the whole circle after the fan
        directions = np.concatenate([directions, seed_directions(goal, ESCAPE_YAW_DEG, s.seed_pitch_deg)])
    seed_end = None
    for d in directions:
        end = p0 + s.seed_length_m * d
        segment = p0 + along[1:] * (end - p0)
        if (local_map.distance_m(segment, upper_bound_m=s.margin_m).min() >= margin_m
                and box_excess_m(end[1], end[2], s) <= start_excess_m + 1e-9):
            seed_end = end
            break
    if seed_end is None:
        return None
    reach = s.region_radius_m
    nearby = local_map.points_within(p0, reach * np.sqrt(3.0))
    a_obs, c_obs = carve_free_polytope(nearby, p0, seed_end, margin_m, s.max_planes)
    # variables (qx, qy, qz, ty, tz): ty >= |qy - y_home|, tz >= |qz - z_home| (the L1 pull, linear)
    y_home, z_home = s.home_yz_m
    objective = np.concatenate([-goal, [s.weight_home, s.weight_home]])
    rows = [np.hstack([a_obs, np.zeros((len(a_obs), 2))])]
    rhs = [c_obs]
    rows.append(np.array([[0, 1, 0, -1, 0], [0, -1, 0, -1, 0], [0, 0, 1, 0, -1], [0, 0, -1, 0, -1]], float))
    rhs.append(np.array([y_home, -y_home, z_home, -z_home]))
    # the course's box, widened to hold the drone where it is already outside (the escape rule)
    y_max = max(s.y_abs_max_m, abs(float(p0[1])))
    lo = np.maximum(p0 - reach, [-np.inf, -y_max, min(s.z_min_m, float(p0[2]))])
    hi = np.minimum(p0 + reach, [np.inf, y_max, max(s.z_max_m, float(p0[2]))])
    bounds = [(float(lo[i]), float(hi[i])) for i in range(3)] + [(0, None), (0, None)]
    result = linprog(objective, A_ub=np.vstack(rows), b_ub=np.concatenate(rhs), bounds=bounds, method="highs")
    target = result.x[:3] if result.status == 0 else seed_end  # LP trouble: the seed segment is free anyway
    if np.linalg.norm(target - p0) < 0.05:
        # the region's best point is where the drone is (inside the margin, the nearest face passes through it):
        # fly the seed, which is free, and plan again from further out
        target = seed_end
    offset = target - p0
    distance = float(np.linalg.norm(offset))
    speed = min(s.speed_mps, float(np.sqrt(2.0 * s.accel_max_mps2 * distance)))
    velocity = offset / distance * speed
    t = np.arange(0.0, s.plan_s + 1e-9, s.sample_dt_s)
    plan = Plan(t, p0 + t[:, None] * velocity, np.tile(velocity, (len(t), 1)))
    return limit_feasibility(plan, s.speed_mps, np.inf)
