"""The privileged expert (paper code): pick the free waypoint nearest straight ahead.

What it sees (the original's inputs): Flightmare published only the ``max_obstacles`` = 10
obstacles nearest the drone (``kNObstacles``), ranked by distance and cut at ``max_range_m`` = 10 m
(``max_detection_range``), behind the drone included, relative to the drone; the original expert
then used only those 0 < dx < ``lookahead_m`` ahead. Flightmare counted a tree as one object, so
here the count is per scene object, not per covering sphere: a sphere, a tree (trunk with the
canopy centred on its top) or a box is one object, and all the covering spheres of a selected
object reach the expert. An object's distance is the distance from the drone to its anchor: a
sphere's centre, a trunk's axis (Flightmare zeroed dz for trees: the horizontal distance while the
drone is below the top), and a box's nearest point (Flightmare had no walls). ``None`` for both
limits gives vitfly's former all-seeing expert.

Given those, the expert looks at a 33 x 33 grid of waypoints in the plane ``lookahead_m`` ahead
of the drone (lateral and vertical offsets -8..8 m in 0.5 m steps). A waypoint is blocked when the
infinite line through the drone and the waypoint passes within ``radius + inflate_m`` of any
obstacle centre that lies 0 < dx < ``lookahead_m`` ahead. The free waypoint nearest the grid centre
(Manhattan distance on grid indices) gives the direction; ties go to the first one in the grid's
row-major order, rows running from +8 m up to -8 m down and columns from +8 m left to -8 m right
(the original drew ties at random). Then the altitude floor and the take-off ramp override single
components, in that order.

Example::

    # a sphere of radius 1 m, 4 m straight ahead: the nearest free waypoints are 3.5 m off-centre
    # (up, left, right, down); the tie goes to "up"
    expert_command(np.array([10.0, 0, 3.5]), np.array([[14.0, 0, 3.5, 1.0]]), 5.0)
    # -> array([4.5808, 0., 2.0041])
    # a whole scene: the expert picks its 10 nearest objects itself
    expert_command(position, ExpertObstacles.from_scene(scene), 5.0)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from vitfly.sim.scenes import Scene


@dataclass(frozen=True)
class ExpertConfig:
    """The expert's constants; defaults are the paper code's values (m, m/s)."""

    lookahead_m: float = 8.0  # plane of waypoints, and the range of obstacles considered
    grid_half_extent_m: float = 8.0  # waypoint offsets span [-8, 8] m laterally and vertically
    grid_step_m: float = 0.5
    inflate_m: float = 0.6  # obstacle radius inflation
    fallback_command: tuple[float, float, float] = (0.5, 0.0, 0.25)  # no free waypoint (m/s)
    min_altitude_m: float = 2.0  # below it: vz = gain * (min_altitude - z)
    altitude_gain: float = 2.0
    ramp_distance_m: float = 2.0  # while x < it: vx = max(ramp_min_speed, x / ramp_distance * speed)
    ramp_min_speed_mps: float = 1.0
    # what Flightmare published: the nearest objects (kNObstacles) within the detection range (m);
    # None: no limit (both None: the all-seeing expert vitfly used before)
    max_obstacles: int | None = 10
    max_range_m: float | None = 10.0


ALL_SEEING = ExpertConfig(max_obstacles=None, max_range_m=None)


@dataclass(frozen=True, eq=False)
class ExpertObstacles:
    """A scene as the expert's sensor sees it: covering spheres grouped by scene object (world frame, m).

    spheres: (K, 4) rows [x, y, z, radius]; object_index: (K,) int, the object each sphere belongs
    to; anchor_lo, anchor_hi: (M, 3), object m's distance to a point is the distance to the
    axis-aligned box [anchor_lo[m], anchor_hi[m]] (a point or a vertical segment when lo and hi
    coincide in some axes). ``singletons`` is true when sphere k is object k, anchored at its centre.
    """

    spheres: np.ndarray
    object_index: np.ndarray
    anchor_lo: np.ndarray
    anchor_hi: np.ndarray
    singletons: bool = False

    @classmethod
    def from_spheres(cls, spheres: np.ndarray) -> ExpertObstacles:
        """Each sphere one object, anchored at its centre (the spheres scenes, and hand-made lists)."""
        sph = np.asarray(spheres, dtype=np.float64).reshape(-1, 4)
        centres = sph[:, :3]
        return cls(sph, np.arange(len(sph)), centres, centres, singletons=True)

    @classmethod
    def from_scene(cls, scene: Scene, spacing_m: float = 0.5) -> ExpertObstacles:
        """The scene's expert cover (:meth:`Scene.expert_obstacles`) with its objects and anchors."""
        spheres, object_index, lo, hi = scene.expert_objects(spacing_m)
        if len(scene.cylinders) == 0 and len(scene.boxes) == 0:
            return cls.from_spheres(spheres)
        return cls(spheres, object_index, lo, hi)

    def __len__(self) -> int:
        return len(self.spheres)


@lru_cache(maxsize=8)
def waypoint_grid(config: ExpertConfig) -> tuple[np.ndarray, np.ndarray]:
    """Waypoint offsets relative to the drone, world frame.

    Returns ``(waypoints, manhattan)``: waypoints (G, G, 3) with ``[i, j] = (lookahead, y_j, z_i)``,
    z descending over rows (+8 first) and y descending over columns (+8 = left first), and the
    Manhattan distance of each grid index to the centre, (G, G) int.
    """
    n_half = int(round(config.grid_half_extent_m / config.grid_step_m))
    offsets = config.grid_step_m * np.arange(n_half, -n_half - 1, -1, dtype=np.float64)
    zz, yy = np.meshgrid(offsets, offsets, indexing="ij")
    wpts = np.stack([np.full_like(yy, config.lookahead_m), yy, zz], axis=-1)
    idx = np.abs(np.arange(offsets.size) - n_half)
    manhattan = idx[:, None] + idx[None, :]
    wpts.setflags(write=False)  # cached: shared between calls
    manhattan.setflags(write=False)
    return wpts, manhattan


def takeoff_ramp(vx_mps, x_m, desired_speed_mps, config: ExpertConfig | None = None) -> np.ndarray:
    """The paper code's take-off ramp on the forward command (expert and learned policies alike).

    While the drone is short of ``ramp_distance_m`` along world x, the x command is replaced by
    ``max(ramp_min_speed_mps, x / ramp_distance_m * desired_speed)``; elsewhere it is left as given.
    Elementwise over arrays of envs: vx_mps (m/s), x_m (world-frame x, m), desired_speed_mps (m/s).
    """
    cfg = config or ExpertConfig()
    x = np.asarray(x_m, dtype=np.float64)
    ramp = np.maximum(cfg.ramp_min_speed_mps, x / cfg.ramp_distance_m * np.asarray(desired_speed_mps, np.float64))
    return np.where(x < cfg.ramp_distance_m, ramp, np.asarray(vx_mps, dtype=np.float64))


@lru_cache(maxsize=8)
def _unit_directions(config: ExpertConfig) -> np.ndarray:
    wpts, _ = waypoint_grid(config)
    dirs = wpts.reshape(-1, 3) / np.linalg.norm(wpts.reshape(-1, 3), axis=1, keepdims=True)
    dirs.setflags(write=False)
    return dirs


def blocked_waypoints(rel_obstacles: np.ndarray, config: ExpertConfig) -> np.ndarray:
    """(G, G) bool: waypoint blocked by any of ``rel_obstacles`` (K, 4) given relative to the drone.

    Only obstacles with 0 < dx < lookahead count. The test is on the infinite line through the
    drone and the waypoint (as the original code does), not the segment.
    """
    wpts, _ = waypoint_grid(config)
    near = _near_obstacles(rel_obstacles, config)
    if near is None:
        return np.zeros(wpts.shape[:2], dtype=bool)
    along, centre2, radius2 = near
    blocked = _blocked_rows(along, centre2, radius2)
    return blocked.reshape(wpts.shape[:2])


def _near_obstacles(rel_obstacles: np.ndarray, config: ExpertConfig):
    """The obstacles that may block a waypoint, as ``(along, centre2, radius2)``, or None if there are none.

    along (G*G, K): projection of each centre on each line; centre2 (K,): squared centre distances;
    radius2 (K,): squared inflated radii. A line is blocked by centre k when
    ``centre2[k] - along[:, k] ** 2 <= radius2[k]``.
    """
    rel = np.asarray(rel_obstacles, dtype=np.float64).reshape(-1, 4)
    radii = rel[:, 3] + config.inflate_m
    # all lines lie in the double pyramid |y|, |z| <= slope |x|; an obstacle farther than its inflated
    # radius from the pyramid's side planes cannot block any of them (a shortcut, same answer)
    slope = config.grid_half_extent_m / config.lookahead_m
    margin = radii * np.sqrt(1.0 + slope * slope)
    dx = rel[:, 0]
    near_cone = (np.abs(rel[:, 1]) - slope * dx < margin) & (np.abs(rel[:, 2]) - slope * dx < margin)
    keep = (dx > 0.0) & (dx < config.lookahead_m) & near_cone
    if not keep.any():
        return None
    centres, radii = rel[keep, :3], radii[keep]
    # (G*G, K) projection of each centre on each line (np.dot: the same BLAS product as ``@``, less overhead)
    along = np.dot(_unit_directions(config), centres.T)
    return along, np.sum(centres * centres, axis=1), radii * radii


def _blocked_rows(along: np.ndarray, centre2: np.ndarray, radius2: np.ndarray) -> np.ndarray:
    """Which lines (rows of ``along``) pass within the inflated radius of any centre; overwrites ``along``."""
    along *= along
    dist2 = np.subtract(centre2, along, out=along)  # squared distance centre-line
    return (dist2 <= radius2).any(axis=1)


@lru_cache(maxsize=8)
def _search_order(config: ExpertConfig) -> tuple[np.ndarray, np.ndarray]:
    """Flat waypoint indices by (Manhattan distance, row-major index), split into the first few and the rest.

    The first free waypoint in this order is the one ``argmin`` over the grid picks (the nearest to
    the centre, ties to the first in row-major order); it is usually among the first few.
    """
    _, manhattan = waypoint_grid(config)
    order = np.lexsort((np.arange(manhattan.size), manhattan.ravel()))
    head, tail = order[:64].copy(), order[64:].copy()
    head.setflags(write=False)
    tail.setflags(write=False)
    return head, tail


def _first_free(rel_obstacles: np.ndarray, config: ExpertConfig) -> int | None:
    """Flat index of the free waypoint nearest the grid centre (see the module docstring), None if all are blocked.

    Same answer as ``argmin`` over :func:`blocked_waypoints`, with the same arithmetic, but tests
    the waypoints near the centre first and stops at the first free one.
    """
    near = _near_obstacles(rel_obstacles, config)
    head, tail = _search_order(config)
    if near is None:
        return int(head[0])
    along, centre2, radius2 = near
    for rows in (head, tail):
        free = np.flatnonzero(~_blocked_rows(along[rows], centre2, radius2))
        if len(free):
            return int(rows[free[0]])
    return None


def visible_obstacles(position: np.ndarray, obstacles: ExpertObstacles, config: ExpertConfig) -> np.ndarray:
    """(K', 4) world-frame spheres of the objects Flightmare would have published to the expert.

    The ``config.max_obstacles`` objects nearest ``position`` (m, world frame) among those within
    ``config.max_range_m`` (distance <= range); ties in distance keep the scene order.
    """
    n_max, rng = config.max_obstacles, config.max_range_m
    if (n_max is None and rng is None) or len(obstacles) == 0:
        return obstacles.spheres
    pos = np.asarray(position, dtype=np.float64).reshape(3)
    if obstacles.singletons:
        delta = obstacles.anchor_lo - pos
    else:  # nearest point of each anchor box
        delta = np.clip(pos, obstacles.anchor_lo, obstacles.anchor_hi) - pos
    dist2 = np.einsum("ij,ij->i", delta, delta)
    chosen = np.flatnonzero(dist2 <= rng * rng) if rng is not None else np.arange(len(dist2))
    if n_max is not None and len(chosen) > n_max:
        chosen = chosen[np.argsort(dist2[chosen], kind="stable")[:n_max]]
    if len(chosen) == len(dist2):  # every object (e.g. the window's few walls): no copy
        return obstacles.spheres
    if obstacles.singletons:
        return obstacles.spheres[chosen]
    selected = np.zeros(len(dist2), dtype=bool)
    selected[chosen] = True
    return obstacles.spheres[selected[obstacles.object_index]]


def expert_command(
    position: np.ndarray,
    obstacles: np.ndarray | ExpertObstacles,
    desired_speed: float,
    config: ExpertConfig | None = None,
) -> np.ndarray:
    """World-frame velocity command (3,) in m/s.

    position: (3,) drone position, world frame (m). obstacles: the whole scene as the expert's
    sensor sees it, an :class:`ExpertObstacles` or (K, 4) rows [x, y, z, radius] (each row one
    object), world frame (m); the expert keeps what ``config`` says Flightmare published (see the
    module docstring). desired_speed: forward speed to fly at (m/s).
    """
    cfg = config or ExpertConfig()
    pos = np.asarray(position, dtype=np.float64).reshape(3)
    if not isinstance(obstacles, ExpertObstacles):
        obstacles = ExpertObstacles.from_spheres(obstacles)
    obs = visible_obstacles(pos, obstacles, cfg)
    rel = obs - np.concatenate([pos, [0.0]])
    flat = _first_free(rel, cfg)  # = argmin of the Manhattan distance over the free waypoints
    if flat is None:
        command = np.array(cfg.fallback_command, dtype=np.float64)
    else:
        wpts, _ = waypoint_grid(cfg)
        wpt = wpts.reshape(-1, 3)[flat]
        command = wpt / np.linalg.norm(wpt) * float(desired_speed)
    if pos[2] < cfg.min_altitude_m:
        command[2] = cfg.altitude_gain * (cfg.min_altitude_m - pos[2])
    command[0] = takeoff_ramp(command[0], pos[0], float(desired_speed), cfg)
    return command
