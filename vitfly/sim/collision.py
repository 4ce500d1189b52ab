"""Geometric contact between the drone and a scene's obstacles.

Obstacles never push the drone (they are not pybullet bodies): contact is a test on the drone's
centre. By default the drone is a point, as in the paper's evaluator (contact when the centre is
inside an obstacle); a body radius (e.g. 0.125 m) makes it a sphere.

``signed_distances`` is the exact, vectorised reference. The rollout engine calls
:meth:`ContactChecker.nearby` once per control tick to keep the few obstacles the drone can reach
before the next tick, and :meth:`ContactChecker.in_contact` every physics step on those only.
"""

from __future__ import annotations

import math

import numpy as np

from vitfly.sim.scenes import Scene


def signed_distances(point, scene: Scene) -> np.ndarray:
    """Signed distance (m) from ``point`` (3,) (world frame) to each obstacle, negative inside.

    Order: spheres, then cylinders, then boxes (as stored in the scene).
    """
    p = np.asarray(point, dtype=np.float64).reshape(3)
    parts = []
    sph = scene.spheres
    if len(sph):
        rel = sph[:, :3] - p
        parts.append(np.sqrt(np.einsum("ij,ij->i", rel, rel)) - sph[:, 3])
    cyl = scene.cylinders
    if len(cyl):
        radial = np.hypot(cyl[:, 0] - p[0], cyl[:, 1] - p[1]) - cyl[:, 4]
        axial = np.maximum(cyl[:, 2] - p[2], p[2] - cyl[:, 3])
        parts.append(_combine(radial, axial))
    box = scene.boxes
    if len(box):
        excess = np.maximum(box[:, :3] - p, p - box[:, 3:])  # (K, 3) per-axis
        outside = np.linalg.norm(np.maximum(excess, 0.0), axis=1)
        parts.append(np.where(outside > 0, outside, excess.max(axis=1)))
    return np.concatenate(parts) if parts else np.zeros(0)


def _combine(radial: np.ndarray, axial: np.ndarray) -> np.ndarray:
    """Signed distance of a finite cylinder from its radial and axial excesses."""
    outside = np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0))
    return np.where((radial > 0) | (axial > 0), outside, np.maximum(radial, axial))


class ContactChecker:
    """Contact tests for one scene and one body radius (m)."""

    def __init__(self, scene: Scene, body_radius_m: float = 0.0):
        self.scene = scene
        self.body_radius_m = float(body_radius_m)
        self._n_sph = len(scene.spheres)
        self._n_cyl = len(scene.cylinders)

    def nearby(self, position, horizon_m: float) -> list[tuple]:
        """Obstacles the drone centre could touch after moving at most ``horizon_m`` (m).

        Returns plain tuples ("sphere", x, y, z, r), ("cylinder", x, y, z0, z1, r) or
        ("box", x0, y0, z0, x1, y1, z1) for :meth:`in_contact`.
        """
        if self.scene.num_obstacles == 0:
            return []
        d = signed_distances(position, self.scene)
        out = []
        for i in np.flatnonzero(d < self.body_radius_m + horizon_m).tolist():
            if i < self._n_sph:
                out.append(("sphere", *self.scene.spheres[i].tolist()))
            elif i < self._n_sph + self._n_cyl:
                out.append(("cylinder", *self.scene.cylinders[i - self._n_sph].tolist()))
            else:
                out.append(("box", *self.scene.boxes[i - self._n_sph - self._n_cyl].tolist()))
        return out

    def in_contact(self, position, candidates: list[tuple]) -> bool:
        """True when the drone at ``position`` (world, m) touches any of ``candidates``.

        A point drone (radius 0) touches an obstacle when its centre is strictly inside it.
        """
        px, py, pz = position
        br = self.body_radius_m
        for ob in candidates:
            kind = ob[0]
            if kind == "sphere":
                _, x, y, z, r = ob
                dist = math.sqrt((px - x) ** 2 + (py - y) ** 2 + (pz - z) ** 2) - r
            elif kind == "cylinder":
                _, x, y, z0, z1, r = ob
                radial = math.hypot(px - x, py - y) - r
                axial = max(z0 - pz, pz - z1)
                if radial > 0 or axial > 0:
                    dist = math.hypot(max(radial, 0.0), max(axial, 0.0))
                else:
                    dist = max(radial, axial)
            else:
                _, x0, y0, z0, x1, y1, z1 = ob
                ex, ey, ez = max(x0 - px, px - x1), max(y0 - py, py - y1), max(z0 - pz, pz - z1)
                if ex > 0 or ey > 0 or ez > 0:
                    dist = math.sqrt(max(ex, 0.0) ** 2 + max(ey, 0.0) ** 2 + max(ez, 0.0) ** 2)
                else:
                    dist = max(ex, ey, ez)
            if dist < br:
                return True
        return False
