"""The course's box the planners keep to (world frame, m): |y| <= y_abs_max_m, z_min_m <= z <= z_max_m.

``box_excess_m`` measures how far a point has left it, for the escape rule both planners apply: a plan may not
go further out of the box than the drone already is (``vitfly.planners.search``, ``vitfly.planners.convex``).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class BoxSettings(Protocol):
    z_min_m: float
    z_max_m: float
    y_abs_max_m: float


def box_excess_m(y_m, z_m, s: BoxSettings) -> np.ndarray:
    """How far (m) points lie outside the course's box (0 inside): the largest of their overshoots, elementwise."""
    y, z = np.asarray(y_m, dtype=np.float64), np.asarray(z_m, dtype=np.float64)
    return np.maximum.reduce([np.zeros_like(y), s.z_min_m - z, z - s.z_max_m, np.abs(y) - s.y_abs_max_m])
