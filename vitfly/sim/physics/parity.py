"""How far apart two back ends' flights are, and how far they may be (the parity tolerance).

``tests/test_physics.py`` flies the same command sequences through pybullet and the native back end
(60 s random flights) and holds them to ``PARITY_TOLERANCE``; ``benchmarks/sim_speed.py`` reports
the same gaps for the flights it times. Measured gaps are ~1e-13 (rounding): the bounds leave four
orders of magnitude for the chaos of long flights, while a change of scheme (explicit instead of
semi-implicit Euler, a damping term) shows up at 1e-3.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from vitfly.sim.quadrotor import DroneState

PARITY_TOLERANCE = {"position_m": 1e-9, "attitude_rad": 1e-9, "velocity_mps": 1e-9, "body_rates_radps": 1e-9}


def state_array(states: Sequence[DroneState]) -> np.ndarray:
    """(N, 13): position, quaternion (w, x, y, z), velocity, body rates of each drone."""
    return np.array([[*s.position, *s.quat, *s.velocity, *s.body_rates] for s in states], dtype=np.float64)


def state_gaps(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Largest differences between two stacks of :func:`state_array` rows (any leading shape).

    Attitude: the angle of the relative rotation, 2 atan2(|vector part|, |scalar part|) of a^-1 b
    (robust near zero, and blind to the sign of q, which is the same attitude).
    """
    qa, qb = a[..., 3:7], b[..., 3:7]
    w = np.sum(qa * qb, axis=-1)
    v = qa[..., :1] * qb[..., 1:] - qb[..., :1] * qa[..., 1:] - np.cross(qa[..., 1:], qb[..., 1:])
    angle = 2.0 * np.arctan2(np.linalg.norm(v, axis=-1), np.abs(w))
    return {
        "position_m": float(np.abs(a[..., 0:3] - b[..., 0:3]).max()),
        "attitude_rad": float(angle.max()),
        "velocity_mps": float(np.abs(a[..., 7:10] - b[..., 7:10]).max()),
        "body_rates_radps": float(np.abs(a[..., 10:13] - b[..., 10:13]).max()),
    }


def within_tolerance(gaps: dict[str, float]) -> bool:
    return all(gaps[k] <= bound for k, bound in PARITY_TOLERANCE.items())
