"""The cascaded velocity controller of :mod:`vitfly.sim.controller`, for E drones at once (torch).

velocity command (world, m/s) -> desired acceleration (tilt and climb limits) -> desired attitude and
collective thrust -> desired body rates -> body torques -> rotor speed commands (rad/s); the same
laws in the same order as :func:`vitfly.sim.controller.make_velocity_controller`. Differentiable with
respect to the commands: the norms that may be zero are guarded (their unused branch stays finite).

Example::

    omega_cmd = velocity_control(torch.tensor([[5.0, 0.0, 0.0]]), state, Airframe(), ControllerGains())
"""

from __future__ import annotations

import math

import torch

from vitfly.sim.batched.dynamics import DroneTensors
from vitfly.sim.controller import ControllerGains
from vitfly.sim.quadrotor import GRAVITY_MPS2, Airframe


def safe_norm(*components: torch.Tensor) -> torch.Tensor:
    """Euclidean norm of the components, with a zero gradient (not NaN) where the norm is 0."""
    sq = sum(c * c for c in components)
    positive = sq > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, sq, torch.ones_like(sq))), torch.zeros_like(sq))


def velocity_control(
    velocity_cmd: torch.Tensor, state: DroneTensors, airframe: Airframe, gains: ControllerGains
) -> torch.Tensor:
    """Rotor speed commands (E, 4) rad/s for world-frame velocity commands (E, 3) m/s."""
    g, af = GRAVITY_MPS2, airframe
    # desired acceleration: P on velocity, climb / sink limits, horizontal part scaled to the tilt limit
    kx, ky, kz = gains.velocity_p
    err = velocity_cmd - state.velocity
    ax, ay = kx * err[:, 0], ky * err[:, 1]
    az = (kz * err[:, 2]).clamp(-gains.max_accel_down_mps2, gains.max_accel_up_mps2)
    max_h = (g + az) * math.tan(gains.max_tilt_rad)
    norm_h = safe_norm(ax, ay)
    over = norm_h > max_h
    scale = torch.where(over, max_h / torch.where(over, norm_h, torch.ones_like(norm_h)), torch.ones_like(norm_h))
    ax, ay = ax * scale, ay * scale
    # thrust and attitude: desired z along the force, y = z x heading, x = y x z; thrust along body z
    rot = state.rotation
    fx, fy, fz = af.mass_kg * ax, af.mass_kg * ay, af.mass_kg * (az + g)
    n = torch.sqrt(fx * fx + fy * fy + fz * fz)  # > 0: the sink limit is below g
    zx, zy, zz = fx / n, fy / n, fz / n
    c_yaw, s_yaw = math.cos(gains.yaw_rad), math.sin(gains.yaw_rad)
    yx, yy, yz = -zz * s_yaw, zz * c_yaw, zx * s_yaw - zy * c_yaw
    ny = torch.sqrt(yx * yx + yy * yy + yz * yz)
    yx, yy, yz = yx / ny, yy / ny, yz / ny
    xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
    thrust = (fx * rot[:, 0, 2] + fy * rot[:, 1, 2] + fz * rot[:, 2, 2]).clamp(min=0.0)
    # attitude error e_R = vee(R_d^T R - R^T R_d) / 2 -> desired body rates
    r0, r1, r2 = rot[:, 0, 0], rot[:, 0, 1], rot[:, 0, 2]
    r3, r4, r5 = rot[:, 1, 0], rot[:, 1, 1], rot[:, 1, 2]
    r6, r7, r8 = rot[:, 2, 0], rot[:, 2, 1], rot[:, 2, 2]
    ex = 0.5 * ((zx * r1 + zy * r4 + zz * r7) - (yx * r2 + yy * r5 + yz * r8))
    ey = 0.5 * ((xx * r2 + xy * r5 + xz * r8) - (zx * r0 + zy * r3 + zz * r6))
    ez = 0.5 * ((yx * r0 + yy * r3 + yz * r6) - (xx * r1 + xy * r4 + xz * r7))
    akx, aky, akz = gains.attitude_p
    rx, ry, rz = -akx * ex, -aky * ey, -akz * ez
    # body torques: P on rates plus the gyroscopic term w x J w
    jx, jy, jz = af.inertia_kgm2
    rkx, rky, rkz = gains.rate_p
    wx, wy, wz = state.body_rates.unbind(-1)
    tx = jx * rkx * (rx - wx) + (wy * jz * wz - wz * jy * wy)
    ty = jy * rky * (ry - wy) + (wz * jx * wx - wx * jz * wz)
    tz = jz * rkz * (rz - wz) + (wx * jy * wy - wy * jx * wx)
    # mixer: the closed-form inverse of the allocation, rotor thrusts clipped to what the motors give
    a, b, c = tx / af.arm_y_m, ty / af.arm_x_m, tz / af.torque_coeff
    f = torch.stack([thrust - a - b + c, thrust + a + b + c, thrust - a + b - c, thrust + a - b - c], -1) / 4
    f = f.clamp(0.0, af.max_rotor_thrust_n)
    return torch.sqrt(f / af.thrust_coeff)
