"""Quadrotor airframe, its state as the simulator reports it, and attitude conversions.

The airframe is the paper's (Flightmare "kingfisher"). Its rigid-body motion is integrated by a
physics back end (``vitfly.sim.physics``: pybullet, or vitfly's native integrator), which also
models the motors and rotor forces the same way in both.

Rotor order and layout (body frame: x forward, y left, z up):
0 front-right (+x, -y), 1 back-left (-x, +y), 2 back-right (-x, -y), 3 front-left (+x, +y).
Rotors 0 and 1 produce a reaction torque of +kappa * thrust about body z, rotors 2 and 3 -kappa * thrust.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

GRAVITY_MPS2 = 9.81


@dataclass(frozen=True)
class Airframe:
    """Physical constants of the quadrotor (SI units)."""

    mass_kg: float = 0.752
    inertia_kgm2: tuple[float, float, float] = (0.0025, 0.0021, 0.0043)  # diagonal, body frame
    arm_x_m: float = 0.075  # rotors at (+-arm_x, +-arm_y)
    arm_y_m: float = 0.10
    thrust_coeff: float = 1.5625e-6  # thrust = thrust_coeff * omega^2 (N, omega in rad/s)
    torque_coeff: float = 0.022  # reaction torque / thrust (m)
    motor_time_constant_s: float = 0.033
    omega_max_radps: float = 2800.0
    omega_min_radps: float = 0.0
    diameter_m: float = 0.25

    @property
    def rotor_positions(self) -> np.ndarray:
        """(4, 3) rotor positions in the body frame (m), in rotor order."""
        ax, ay = self.arm_x_m, self.arm_y_m
        return np.array([[ax, -ay, 0.0], [-ax, ay, 0.0], [-ax, -ay, 0.0], [ax, ay, 0.0]])

    @property
    def rotor_spin(self) -> np.ndarray:
        """(4,) sign of each rotor's reaction torque about body z."""
        return np.array([1.0, 1.0, -1.0, -1.0])

    @property
    def allocation(self) -> np.ndarray:
        """(4, 4) matrix A with [collective thrust, tau_x, tau_y, tau_z] = A @ rotor_thrusts (N, N m)."""
        pos = self.rotor_positions
        return np.stack([np.ones(4), pos[:, 1], -pos[:, 0], self.torque_coeff * self.rotor_spin])

    @property
    def max_rotor_thrust_n(self) -> float:
        return self.thrust_coeff * self.omega_max_radps**2

    @property
    def hover_omega_radps(self) -> float:
        return math.sqrt(self.mass_kg * GRAVITY_MPS2 / (4 * self.thrust_coeff))


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3), body-to-world, from unit quaternions (N, 4) (w, x, y, z)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=1,
    )


class DroneState(NamedTuple):
    """One drone's state. Sequences of floats (tuples, or lists from the native back end), world frame
    unless said otherwise.

    position (3,) m; quat (4,) (w, x, y, z) body-to-world; rotation (9,) body-to-world matrix,
    row-major; velocity (3,) m/s; body_rates (3,) rad/s in the body frame.
    """

    position: Sequence[float]
    quat: Sequence[float]
    rotation: Sequence[float]
    velocity: Sequence[float]
    body_rates: Sequence[float]
