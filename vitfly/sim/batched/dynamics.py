"""The airframe and the native back end's physics step, for E drones at once (torch).

The same step as :mod:`vitfly.sim.physics.base` fixes and :mod:`vitfly.sim.physics.native` computes
(scalar kernel, operation for operation where it matters): motors as an exact first-order lag, rotor
thrusts and torques at the attitude at the start of the step, Bullet's semi-implicit Euler
(``v += dt a``, ``p += dt v``; ``w += dt J^-1 (tau - w x J w)``, then the attitude turns by the
exponential map of the new rate, normalised), and the quaternion reported with pybullet's sign.

Everything is differentiable with respect to the rotor commands (and the state): square roots and
quotients that may meet zero are guarded so that their unused branch never feeds NaN into a gradient.

Example::

    af = Airframe()
    state = hover_state(torch.tensor([[0.0, 0.0, 3.5]] * 4, dtype=torch.float64), af)
    state = physics_step(state, torch.full((4, 4), af.hover_omega_radps, dtype=torch.float64), af, 1 / 240)
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from vitfly.sim.quadrotor import GRAVITY_MPS2, Airframe

# Bullet replaces sin(|w| dt / 2) / |w| by its Taylor series below this rate (rad/s), as the native back end
TAYLOR_BELOW_RADPS = 1e-3


class DroneTensors(NamedTuple):
    """E drones' state, world frame unless said otherwise (SI units).

    position (E, 3) m; quat (E, 4) (w, x, y, z) body-to-world; rotation (E, 3, 3) body-to-world
    matrix; velocity (E, 3) m/s; body_rates (E, 3) rad/s in the body frame; rotor (E, 4) rotor
    speeds, rad/s, in the rotor order of :mod:`vitfly.sim.quadrotor`.
    """

    position: torch.Tensor
    quat: torch.Tensor
    rotation: torch.Tensor
    velocity: torch.Tensor
    body_rates: torch.Tensor
    rotor: torch.Tensor


def hover_state(positions: torch.Tensor, airframe: Airframe) -> DroneTensors:
    """Drones at ``positions`` (E, 3) m, level, heading +x, at rest, rotors at hover speed (as ``Fleet.reset``)."""
    n = positions.shape[0]
    like = dict(dtype=positions.dtype, device=positions.device)
    quat = torch.zeros(n, 4, **like)
    quat[:, 0] = 1.0
    return DroneTensors(
        position=positions.clone(), quat=quat, rotation=torch.eye(3, **like).expand(n, 3, 3).clone(),
        velocity=torch.zeros(n, 3, **like), body_rates=torch.zeros(n, 3, **like),
        rotor=torch.full((n, 4), airframe.hover_omega_radps, **like),
    )


def motor_alpha(airframe: Airframe, dt: float) -> float:
    """The exact discretisation of the motor lag over one step of ``dt`` s: ``omega += alpha (cmd - omega)``."""
    return 1.0 - math.exp(-dt / airframe.motor_time_constant_s)


def quat_to_rotation(quat: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (E, 3, 3), body-to-world, from unit quaternions (E, 4) (w, x, y, z)."""
    qw, qx, qy, qz = quat.unbind(-1)
    xx, yy, zz = 2.0 * qx * qx, 2.0 * qy * qy, 2.0 * qz * qz
    xy, xz, yz = 2.0 * qx * qy, 2.0 * qx * qz, 2.0 * qy * qz
    wx, wy, wz = 2.0 * qw * qx, 2.0 * qw * qy, 2.0 * qw * qz
    rows = [
        torch.stack([1.0 - yy - zz, xy - wz, xz + wy], -1),
        torch.stack([xy + wz, 1.0 - xx - zz, yz - wx], -1),
        torch.stack([xz - wy, yz + wx, 1.0 - xx - yy], -1),
    ]
    return torch.stack(rows, -2)


def bullet_sign(quat: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """``quat`` (E, 4) with the sign pybullet reports (see :func:`vitfly.sim.physics.native.bullet_sign`).

    w > 0 when the trace of ``rotation`` is positive, else the component of the largest diagonal entry
    positive. Applied to every drone: for w > 0.5 (the only case the native back end skips) it keeps q.
    """
    r00, r11, r22 = rotation[:, 0, 0], rotation[:, 1, 1], rotation[:, 2, 2]
    qw, qx, qy, qz = quat.unbind(-1)
    key = torch.where(
        r00 + r11 + r22 > 0.0, qw,
        torch.where(r00 < r11, torch.where(r11 < r22, qz, qy), torch.where(r00 < r22, qz, qx)),
    )
    return torch.where((key >= 0.0)[:, None], quat, -quat)


def physics_step(state: DroneTensors, rotor_cmd: torch.Tensor, airframe: Airframe, dt: float) -> DroneTensors:
    """One physics step of ``dt`` s from rotor speed commands (E, 4) rad/s; returns the new state."""
    af = airframe
    alpha = motor_alpha(af, dt)
    # motors: clip the commands, exact first-order lag; rotor thrusts k omega^2 (N)
    cmd = rotor_cmd.clamp(af.omega_min_radps, af.omega_max_radps)
    omega = state.rotor + alpha * (cmd - state.rotor)
    f0, f1, f2, f3 = (af.thrust_coeff * omega * omega).unbind(-1)
    # translation: v += dt a (thrust along body z = column 2 of R, then gravity), then p += dt v
    a_dt = (f0 + f1 + f2 + f3) * (1.0 / af.mass_kg) * dt
    velocity = state.velocity + state.rotation[:, :, 2] * a_dt[:, None]
    velocity = velocity - velocity.new_tensor([0.0, 0.0, GRAVITY_MPS2 * dt])
    position = state.position + dt * velocity
    # rotation: w += dt J^-1 (tau - w x J w), body frame
    jx, jy, jz = af.inertia_kgm2
    wx, wy, wz = state.body_rates.unbind(-1)
    tau_x = af.arm_y_m * (-f0 + f1 - f2 + f3)
    tau_y = af.arm_x_m * (-f0 + f1 + f2 - f3)
    tau_z = af.torque_coeff * (f0 + f1 - f2 - f3)
    wx, wy, wz = (
        wx + dt / jx * (tau_x - (jz - jy) * wy * wz),
        wy + dt / jy * (tau_y - (jx - jz) * wz * wx),
        wz + dt / jz * (tau_z - (jy - jx) * wx * wy),
    )
    # attitude increment (cos(|w| dt/2), w sin(|w| dt/2) / |w|); Bullet's Taylor series for tiny rates,
    # where cos is 1 - (|w| dt/2)^2 / 2 to rounding (and no square root of zero reaches the gradient)
    half_dt = 0.5 * dt
    rate_sq = wx * wx + wy * wy + wz * wz
    small = rate_sq < TAYLOR_BELOW_RADPS**2
    rate = torch.sqrt(torch.where(small, torch.ones_like(rate_sq), rate_sq))
    s = torch.where(small, half_dt - dt * dt * dt * 0.020833333333 * rate_sq, torch.sin(half_dt * rate) / rate)
    c = torch.where(small, 1.0 - 0.5 * half_dt * half_dt * rate_sq, torch.cos(half_dt * rate))
    bx, by, bz = wx * s, wy * s, wz * s
    qw, qx, qy, qz = state.quat.unbind(-1)
    quat = torch.stack([
        qw * c - qx * bx - qy * by - qz * bz,
        qw * bx + qx * c + qy * bz - qz * by,
        qw * by + qy * c + qz * bx - qx * bz,
        qw * bz + qz * c + qx * by - qy * bx,
    ], -1)  # fmt: skip
    quat = quat / torch.sqrt((quat * quat).sum(-1, keepdim=True))
    rotation = quat_to_rotation(quat)
    quat = bullet_sign(quat, rotation)
    return DroneTensors(position, quat, rotation, velocity, torch.stack([wx, wy, wz], -1), omega)
