"""Cascaded velocity controller for one drone, as pure functions.

velocity command (world, m/s) -> desired acceleration -> desired attitude + collective thrust
-> desired body rates -> body torques -> rotor speeds. The heading is held at a fixed yaw (the
camera looks along +x). Each stage is a function of plain tuples so tests can call it on its own;
:func:`velocity_control` chains them. Rotation matrices are body-to-world 9-tuples, row-major
(as ``pybullet.getMatrixFromQuaternion`` returns them): column j is body axis j in the world frame.

Python floats rather than numpy: this runs every physics step (240+ Hz) on 3-vectors, where
numpy's per-call overhead would cost more than the arithmetic.

Example::

    af, gains = Airframe(), ControllerGains()
    state = fleet.states()[0]
    omega_cmd = velocity_control((5.0, 0.0, 0.0), state, af, gains)   # 4 rotor speeds, rad/s
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from vitfly.sim.quadrotor import GRAVITY_MPS2, Airframe, DroneState

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class ControllerGains:
    """Gains and limits of the cascade (SI units)."""

    velocity_p: Vec3 = (2.5, 2.5, 4.0)  # 1/s, world x, y, z
    max_tilt_rad: float = 0.75  # ~43 degrees
    max_accel_up_mps2: float = 2.0 * GRAVITY_MPS2
    max_accel_down_mps2: float = 0.7 * GRAVITY_MPS2
    attitude_p: Vec3 = (12.0, 12.0, 4.0)  # rad/s per rad, body x, y, z
    rate_p: Vec3 = (24.0, 24.0, 10.0)  # 1/s, body x, y, z
    yaw_rad: float = 0.0  # held heading (0 = looking along +x)


def desired_acceleration(velocity_cmd: Vec3, velocity: Vec3, gains: ControllerGains) -> Vec3:
    """Desired acceleration, world frame, m/s^2, gravity not included, limits applied.

    The horizontal part is scaled down so the thrust direction stays within ``max_tilt_rad`` of
    vertical; the vertical part is clipped to the climb and sink limits.
    """
    kx, ky, kz = gains.velocity_p
    ax = kx * (velocity_cmd[0] - velocity[0])
    ay = ky * (velocity_cmd[1] - velocity[1])
    az = min(max(kz * (velocity_cmd[2] - velocity[2]), -gains.max_accel_down_mps2), gains.max_accel_up_mps2)
    max_h = (GRAVITY_MPS2 + az) * math.tan(gains.max_tilt_rad)
    norm_h = math.hypot(ax, ay)
    if norm_h > max_h:
        ax, ay = ax * max_h / norm_h, ay * max_h / norm_h
    return ax, ay, az


def thrust_and_attitude(accel: Vec3, rotation: tuple, mass_kg: float, yaw_rad: float) -> tuple[float, tuple]:
    """Collective thrust (N) and desired rotation (9-tuple, row-major) for an acceleration.

    The desired body z axis points along accel + g; the thrust is the required force projected on
    the current body z axis (so a drone that is still turning neither climbs nor sinks much).
    """
    fx, fy, fz = mass_kg * accel[0], mass_kg * accel[1], mass_kg * (accel[2] + GRAVITY_MPS2)
    n = math.sqrt(fx * fx + fy * fy + fz * fz)
    zx, zy, zz = fx / n, fy / n, fz / n
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    # y_des = z_des x heading, heading = (c, s, 0)
    yx, yy, yz = -zz * s, zz * c, zx * s - zy * c
    ny = math.sqrt(yx * yx + yy * yy + yz * yz)
    yx, yy, yz = yx / ny, yy / ny, yz / ny
    # x_des = y_des x z_des
    xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
    r_des = (xx, yx, zx, xy, yy, zy, xz, yz, zz)
    thrust = fx * rotation[2] + fy * rotation[5] + fz * rotation[8]
    return max(thrust, 0.0), r_des


def attitude_to_rates(rotation: tuple, r_des: tuple, gains: ControllerGains) -> Vec3:
    """Desired body rates (rad/s) from the geometric attitude error e_R = vee(R_d^T R - R^T R_d) / 2."""

    def e(i: int, j: int) -> float:  # (R_des^T R)[i, j] = desired axis i . actual axis j
        return r_des[i] * rotation[j] + r_des[3 + i] * rotation[3 + j] + r_des[6 + i] * rotation[6 + j]

    ex = 0.5 * (e(2, 1) - e(1, 2))
    ey = 0.5 * (e(0, 2) - e(2, 0))
    ez = 0.5 * (e(1, 0) - e(0, 1))
    kx, ky, kz = gains.attitude_p
    return -kx * ex, -ky * ey, -kz * ez


def rates_to_torques(rates_des: Vec3, body_rates: Vec3, inertia: Vec3, gains: ControllerGains) -> Vec3:
    """Body torques (N m): proportional rate loop plus gyroscopic compensation omega x J omega."""
    jx, jy, jz = inertia
    wx, wy, wz = body_rates
    kx, ky, kz = gains.rate_p
    return (
        jx * kx * (rates_des[0] - wx) + (wy * jz * wz - wz * jy * wy),
        jy * ky * (rates_des[1] - wy) + (wz * jx * wx - wx * jz * wz),
        jz * kz * (rates_des[2] - wz) + (wx * jy * wy - wy * jx * wx),
    )


def mix(thrust: float, torques: Vec3, airframe: Airframe) -> tuple[float, float, float, float]:
    """Rotor speed commands (rad/s) for a collective thrust (N) and body torques (N m).

    Closed-form inverse of :attr:`Airframe.allocation` for the rotor order of ``vitfly.sim.quadrotor``;
    rotor thrusts are clipped to what the motors can give.
    """
    a = torques[0] / airframe.arm_y_m
    b = torques[1] / airframe.arm_x_m
    c = torques[2] / airframe.torque_coeff
    f_max, k = airframe.max_rotor_thrust_n, airframe.thrust_coeff
    f0 = min(max((thrust - a - b + c) / 4, 0.0), f_max)
    f1 = min(max((thrust + a + b + c) / 4, 0.0), f_max)
    f2 = min(max((thrust - a + b - c) / 4, 0.0), f_max)
    f3 = min(max((thrust + a - b - c) / 4, 0.0), f_max)
    return math.sqrt(f0 / k), math.sqrt(f1 / k), math.sqrt(f2 / k), math.sqrt(f3 / k)


def velocity_control(
    velocity_cmd: Vec3, state: DroneState, airframe: Airframe, gains: ControllerGains
) -> tuple[float, float, float, float]:
    """The whole cascade: a world-frame velocity command (m/s) -> 4 rotor speed commands (rad/s)."""
    accel = desired_acceleration(velocity_cmd, state.velocity, gains)
    thrust, r_des = thrust_and_attitude(accel, state.rotation, airframe.mass_kg, gains.yaw_rad)
    rates = attitude_to_rates(state.rotation, r_des, gains)
    torques = rates_to_torques(rates, state.body_rates, airframe.inertia_kgm2, gains)
    return mix(thrust, torques, airframe)


def make_velocity_controller(airframe: Airframe, gains: ControllerGains):
    """:func:`velocity_control` for a fixed airframe and gains, as one fused function.

    Returns ``control(velocity_cmd, state) -> 4 rotor speed commands (rad/s)``, computing exactly
    what :func:`velocity_control` computes (same operations in the same order, so bit for bit the
    same result) with the constants looked up once: the rollout engine calls it every physics step.
    """
    g = GRAVITY_MPS2
    vkx, vky, vkz = gains.velocity_p
    down, up = -gains.max_accel_down_mps2, gains.max_accel_up_mps2
    tan_tilt = math.tan(gains.max_tilt_rad)
    mass = airframe.mass_kg
    c_yaw, s_yaw = math.cos(gains.yaw_rad), math.sin(gains.yaw_rad)
    akx, aky, akz = gains.attitude_p
    jx, jy, jz = airframe.inertia_kgm2
    rkx, rky, rkz = gains.rate_p
    jkx, jky, jkz = jx * rkx, jy * rky, jz * rkz
    arm_y, arm_x, kappa = airframe.arm_y_m, airframe.arm_x_m, airframe.torque_coeff
    f_max, k = airframe.max_rotor_thrust_n, airframe.thrust_coeff
    sqrt, hypot = math.sqrt, math.hypot

    def control(velocity_cmd: Vec3, state: DroneState) -> tuple[float, float, float, float]:
        # desired_acceleration (max(x, lo) is "lo if lo > x else x", min(x, hi) "hi if hi < x else x")
        vel = state.velocity
        ax = vkx * (velocity_cmd[0] - vel[0])
        ay = vky * (velocity_cmd[1] - vel[1])
        az = vkz * (velocity_cmd[2] - vel[2])
        if down > az:
            az = down
        if up < az:
            az = up
        max_h = (g + az) * tan_tilt
        norm_h = hypot(ax, ay)
        if norm_h > max_h:
            ax, ay = ax * max_h / norm_h, ay * max_h / norm_h
        # thrust_and_attitude
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = state.rotation
        fx, fy, fz = mass * ax, mass * ay, mass * (az + g)
        n = sqrt(fx * fx + fy * fy + fz * fz)
        zx, zy, zz = fx / n, fy / n, fz / n
        yx, yy, yz = -zz * s_yaw, zz * c_yaw, zx * s_yaw - zy * c_yaw
        ny = sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / ny, yy / ny, yz / ny
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
        thrust = fx * r2 + fy * r5 + fz * r8
        if 0.0 > thrust:
            thrust = 0.0
        # attitude_to_rates, with r_des = (xx, yx, zx, xy, yy, zy, xz, yz, zz)
        ex = 0.5 * ((zx * r1 + zy * r4 + zz * r7) - (yx * r2 + yy * r5 + yz * r8))
        ey = 0.5 * ((xx * r2 + xy * r5 + xz * r8) - (zx * r0 + zy * r3 + zz * r6))
        ez = 0.5 * ((yx * r0 + yy * r3 + yz * r6) - (xx * r1 + xy * r4 + xz * r7))
        rx, ry, rz = -akx * ex, -aky * ey, -akz * ez
        # rates_to_torques
        wx, wy, wz = state.body_rates
        tx = jkx * (rx - wx) + (wy * jz * wz - wz * jy * wy)
        ty = jky * (ry - wy) + (wz * jx * wx - wx * jz * wz)
        tz = jkz * (rz - wz) + (wx * jy * wy - wy * jx * wx)
        # mix
        a, b, c = tx / arm_y, ty / arm_x, tz / kappa
        f0 = (thrust - a - b + c) / 4
        f1 = (thrust + a + b + c) / 4
        f2 = (thrust - a + b - c) / 4
        f3 = (thrust + a - b - c) / 4
        # clip each to [0, f_max], unrolled: this runs at the physics rate and builtin min/max calls cost more
        if 0.0 > f0:
            f0 = 0.0
        if f_max < f0:
            f0 = f_max
        if 0.0 > f1:
            f1 = 0.0
        if f_max < f1:
            f1 = f_max
        if 0.0 > f2:
            f2 = 0.0
        if f_max < f2:
            f2 = f_max
        if 0.0 > f3:
            f3 = 0.0
        if f_max < f3:
            f3 = f_max
        return sqrt(f0 / k), sqrt(f1 / k), sqrt(f2 / k), sqrt(f3 / k)

    return control
