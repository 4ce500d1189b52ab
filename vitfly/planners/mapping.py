"""A local obstacle map fused over recent depth frames: voxel-downsampled points with bounded memory, and a
nearest-obstacle distance query (``scipy.spatial.cKDTree``, rebuilt only when the points changed)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

VOXEL_OFFSET = 1 << 20  # voxel indices within +-2^20 (+-157 km at 0.15 m) pack into 21 bits each


class LocalMap:
    """World-frame obstacle points (m) seen in the last ``memory_s`` seconds, one per ``voxel_m`` cube.

    Points more than ``behind_m`` behind the drone (world x) are forgotten, and at most ``max_points``
    are kept (the most recently seen), so memory stays bounded however long the flight.
    """

    def __init__(self, voxel_m: float = 0.15, memory_s: float = 3.0, behind_m: float = 2.0, max_points: int = 20000):
        self.voxel_m, self.memory_s, self.behind_m, self.max_points = voxel_m, memory_s, behind_m, max_points
        self.points_m = np.zeros((0, 3))
        self.seen_s = np.zeros(0)  # time each point's voxel was last seen
        self._tree: cKDTree | None = None

    def insert(self, points_m: np.ndarray, time_s: float, drone_position_m) -> None:
        """Fuse one frame's points (M, 3) seen at ``time_s``, then forget what is old, far behind or over the cap."""
        points_m = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        pts = np.concatenate([self.points_m, points_m])
        seen = np.concatenate([self.seen_s, np.full(len(points_m), float(time_s))])
        keep = (seen >= time_s - self.memory_s) & (pts[:, 0] >= float(drone_position_m[0]) - self.behind_m)
        pts, seen = pts[keep], seen[keep]
        # one point per voxel, the latest seen (np.unique keeps the first index: newest first); the voxel's three
        # indices packed in one int64 (21 bits each, lexicographic order kept): a 1-D unique, ~10x faster than rows
        cell = np.floor(pts / self.voxel_m).astype(np.int64) + VOXEL_OFFSET
        keys = (cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2]
        order = np.argsort(-seen, kind="stable")
        _, first = np.unique(keys[order], return_index=True)
        chosen = order[first]
        chosen = chosen[np.argsort(-seen[chosen], kind="stable")][: self.max_points]
        self.points_m, self.seen_s = pts[chosen], seen[chosen]
        self._tree = None

    def __len__(self) -> int:
        return len(self.points_m)

    @property
    def tree(self) -> cKDTree | None:
        if self._tree is None and len(self.points_m):
            self._tree = cKDTree(self.points_m)
        return self._tree

    def distance_m(self, query_m: np.ndarray, upper_bound_m: float = np.inf) -> np.ndarray:
        """Distance (m) from each query point (..., 3) to the nearest mapped point; ``inf`` when none lies
        within ``upper_bound_m`` (or the map is empty)."""
        query_m = np.asarray(query_m, dtype=np.float64)
        if self.tree is None:
            return np.full(query_m.shape[:-1], np.inf)
        dist, _ = self.tree.query(query_m.reshape(-1, 3), k=1, distance_upper_bound=upper_bound_m)
        return dist.reshape(query_m.shape[:-1])

    def points_within(self, center_m, radius_m: float) -> np.ndarray:
        """The mapped points (K, 3) within ``radius_m`` of ``center_m``."""
        if self.tree is None:
            return np.zeros((0, 3))
        return self.points_m[self.tree.query_ball_point(np.asarray(center_m, dtype=np.float64), radius_m)]
