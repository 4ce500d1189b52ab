"""The native back end: vitfly's own rigid-body integrator of the airframe, numpy only.

It follows the step of :mod:`vitfly.sim.physics.base` (Bullet's semi-implicit Euler for a free
body, as pybullet integrates vitfly's drones), so it reproduces pybullet to rounding: the parity
test bounds the difference over 60 s random flights. What Bullet does beyond that and vitfly
never reaches is left out: its velocity clamp (100 m/s, 100 rad/s per component) and its limit
of a quarter turn per step on the attitude update (188 rad/s at 240 Hz).

Two kernels compute the same maths:

- array kernel: all N drones in one array operation per term, the state held component-major
  (rows: position 3, quaternion (w, x, y, z) 4, rotation row-major 9, velocity 3, body rates 3),
  with the cascaded controller of :mod:`vitfly.sim.controller` vectorised the same way
  (:meth:`NativeFleet.track`);
- scalar kernel: Python floats, one drone at a time, for fleets of a few drones, where numpy's
  per-call overhead (~0.3 us a call, ~60 calls a step) would cost more than the arithmetic.

``NativeFleet`` picks the array kernel above ``SCALAR_MAX_DRONES`` drones (the measured break-even
point, ``benchmarks/sim_speed.py``) unless told otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import partial

import numpy as np

from vitfly.sim.controller import ControllerGains
from vitfly.sim.physics.base import Fleet
from vitfly.sim.quadrotor import GRAVITY_MPS2, Airframe, DroneState

SCALAR_MAX_DRONES = 6

# Bullet replaces sin(|w| dt / 2) / |w| by its Taylor series below this rate (rad/s)
_TAYLOR_BELOW_RADPS = 1e-3
_MAKE_STATE = partial(tuple.__new__, DroneState)


def _coefficients(shape: tuple[int, int], entries) -> np.ndarray:
    """A matrix of the given shape with ``entries`` ((row, column, value), ...) added up."""
    m = np.zeros(shape)
    for row, column, value in entries:
        m[row, column] += value
    return m


# Bilinear terms as matrices over outer products, so one matrix product computes them for all drones.
# Quaternion (w, x, y, z) = (0, 1, 2, 3) to its rotation matrix (row-major), from the products q_a q_b at
# 4 a + b (for a unit quaternion: w^2 + x^2 - y^2 - z^2 = 1 - 2 (y^2 + z^2), etc.).
_QUAT_TO_ROT = _coefficients((9, 16), [
    *((0, 4 * a + a, s) for a, s in zip(range(4), (1, 1, -1, -1), strict=True)),
    (1, 6, 1), (1, 9, 1), (1, 3, -1), (1, 12, -1),  # 2 (xy - wz)
    (2, 7, 1), (2, 13, 1), (2, 2, 1), (2, 8, 1),  # 2 (xz + wy)
    (3, 6, 1), (3, 9, 1), (3, 3, 1), (3, 12, 1),  # 2 (xy + wz)
    *((4, 4 * a + a, s) for a, s in zip(range(4), (1, -1, 1, -1), strict=True)),
    (5, 11, 1), (5, 14, 1), (5, 1, -1), (5, 4, -1),  # 2 (yz - wx)
    (6, 7, 1), (6, 13, 1), (6, 2, -1), (6, 8, -1),  # 2 (xz - wy)
    (7, 11, 1), (7, 14, 1), (7, 1, 1), (7, 4, 1),  # 2 (yz + wx)
    *((8, 4 * a + a, s) for a, s in zip(range(4), (1, -1, -1, 1), strict=True)),
])  # fmt: skip
# cross product a x b from the products a_i b_j at 3 i + j
_CROSS = _coefficients((3, 9), [(0, 5, 1), (0, 7, -1), (1, 6, 1), (1, 2, -1), (2, 1, 1), (2, 3, -1)])
# Hamilton product p (x) d from the products p_a d_b at 4 a + b
_QUAT_PRODUCT = _coefficients((4, 16), [
    (0, 0, 1), (0, 5, -1), (0, 10, -1), (0, 15, -1),  # pw dw - px dx - py dy - pz dz
    (1, 1, 1), (1, 4, 1), (1, 11, 1), (1, 14, -1),  # pw dx + px dw + py dz - pz dy
    (2, 2, 1), (2, 8, 1), (2, 13, 1), (2, 7, -1),  # pw dy + py dw + pz dx - px dz
    (3, 3, 1), (3, 12, 1), (3, 6, 1), (3, 9, -1),  # pw dz + pz dw + px dy - py dx
])  # fmt: skip


def bullet_sign(w: float, x: float, y: float, z: float, r00: float, r11: float, r22: float) -> tuple:
    """The quaternion (w, x, y, z) with the sign pybullet reports for its rotation (diagonal r00, r11, r22).

    pybullet returns attitudes converted from the rotation matrix (Bullet's ``getRotation``): w > 0
    when the trace is positive, else the component of the largest diagonal entry positive (ties as
    Bullet breaks them). The native back end keeps its quaternion in that form, so that datasets
    store the same numbers whichever back end flew (q and -q are the same attitude, not the same input).
    """
    if r00 + r11 + r22 > 0.0:
        key = w
    else:
        key = (z if r11 < r22 else y) if r00 < r11 else (z if r00 < r22 else x)
    return (w, x, y, z) if key >= 0.0 else (-w, -x, -y, -z)


def make_scalar_step(airframe: Airframe, dt: float, motor_alpha: float):
    """One drone's physics step in Python floats: ``step(state, rotor_omega, cmd) -> DroneState``.

    ``rotor_omega``: the drone's 4 rotor speeds (rad/s), a list updated in place; ``cmd``: 4
    commanded speeds (rad/s). Returns the state after the step (tuples, as pybullet's).
    """
    k, kappa, alpha = airframe.thrust_coeff, airframe.torque_coeff, motor_alpha
    lo, hi = airframe.omega_min_radps, airframe.omega_max_radps
    arm_x, arm_y = airframe.arm_x_m, airframe.arm_y_m
    inv_m, g_dt, half_dt = 1.0 / airframe.mass_kg, GRAVITY_MPS2 * dt, 0.5 * dt
    taylor_dt3 = dt * dt * dt * 0.020833333333  # Bullet's constant, ~1/48
    jx, jy, jz = airframe.inertia_kgm2
    dt_jx, dt_jy, dt_jz = dt / jx, dt / jy, dt / jz
    jzy, jxz, jyx = jz - jy, jx - jz, jy - jx  # w x J w = (jzy wy wz, jxz wz wx, jyx wx wy)
    sqrt, sin, cos = math.sqrt, math.sin, math.cos

    def step(st: DroneState, omega: list, cmd) -> DroneState:
        # motors: clip to [lo, hi] (unrolled: cheaper than min/max calls at the physics rate), exact lag
        c0, c1, c2, c3 = cmd
        if lo > c0:
            c0 = lo
        if hi < c0:
            c0 = hi
        if lo > c1:
            c1 = lo
        if hi < c1:
            c1 = hi
        if lo > c2:
            c2 = lo
        if hi < c2:
            c2 = hi
        if lo > c3:
            c3 = lo
        if hi < c3:
            c3 = hi
        o0, o1, o2, o3 = omega
        o0 += alpha * (c0 - o0)
        o1 += alpha * (c1 - o1)
        o2 += alpha * (c2 - o2)
        o3 += alpha * (c3 - o3)
        omega[0], omega[1], omega[2], omega[3] = o0, o1, o2, o3
        f0, f1, f2, f3 = k * o0 * o0, k * o1 * o1, k * o2 * o2, k * o3 * o3
        # translation: v += dt a (thrust along body z = column 2 of R, gravity), then p += dt v
        r = st.rotation
        a_dt = (f0 + f1 + f2 + f3) * inv_m * dt
        vx, vy, vz = st.velocity
        vx += r[2] * a_dt
        vy += r[5] * a_dt
        vz += r[8] * a_dt - g_dt
        px, py, pz = st.position
        px += dt * vx
        py += dt * vy
        pz += dt * vz
        # rotation: w += dt J^-1 (tau - w x J w) in the body frame
        wx, wy, wz = st.body_rates
        tau_x = arm_y * (-f0 + f1 - f2 + f3)
        tau_y = arm_x * (-f0 + f1 + f2 - f3)
        tau_z = kappa * (f0 + f1 - f2 - f3)
        wx, wy, wz = (
            wx + dt_jx * (tau_x - jzy * wy * wz),
            wy + dt_jy * (tau_y - jxz * wz * wx),
            wz + dt_jz * (tau_z - jyx * wx * wy),
        )
        # attitude: q = q (x) (cos(|w| dt/2), w sin(|w| dt/2) / |w|), normalised
        rate = sqrt(wx * wx + wy * wy + wz * wz)
        s = half_dt - taylor_dt3 * rate * rate if rate < _TAYLOR_BELOW_RADPS else sin(half_dt * rate) / rate
        c = cos(half_dt * rate)
        bx, by, bz = wx * s, wy * s, wz * s
        qw, qx, qy, qz = st.quat
        qw, qx, qy, qz = (
            qw * c - qx * bx - qy * by - qz * bz,
            qw * bx + qx * c + qy * bz - qz * by,
            qw * by + qy * c + qz * bx - qx * bz,
            qw * bz + qz * c + qx * by - qy * bx,
        )
        n = 1.0 / sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw * n, qx * n, qy * n, qz * n
        xx, yy, zz = 2.0 * qx * qx, 2.0 * qy * qy, 2.0 * qz * qz
        xy, xz, yz = 2.0 * qx * qy, 2.0 * qx * qz, 2.0 * qy * qz
        wx_, wy_, wz_ = 2.0 * qw * qx, 2.0 * qw * qy, 2.0 * qw * qz
        rotation = (
            1.0 - yy - zz, xy - wz_, xz + wy_,
            xy + wz_, 1.0 - xx - zz, yz - wx_,
            xz - wy_, yz + wx_, 1.0 - xx - yy,
        )  # fmt: skip
        if qw <= 0.5:  # turned by 120 degrees or more: the sign pybullet reports may differ
            qw, qx, qy, qz = bullet_sign(qw, qx, qy, qz, rotation[0], rotation[4], rotation[8])
        return DroneState((px, py, pz), (qw, qx, qy, qz), rotation, (vx, vy, vz), (wx, wy, wz))

    return step


def _const(value, shape=()) -> np.ndarray:
    """A constant as an array of the operand's shape: numpy converts Python floats and broadcasts
    (3, 1) columns on every call, which costs more than these small operations themselves."""
    return np.array(np.broadcast_to(np.asarray(value, dtype=np.float64), shape))


class _ArrayKernel:
    """The array kernel's state for N drones, and its steps as closures over preallocated buffers.

    Every term is one numpy call on a block of rows, written into a buffer (``out`` given
    positionally), with constants as arrays of the operands' shapes (:func:`_const`). Bilinear terms
    are outer products, and every linear map after them one matrix product over a stack of such products
    (``terms``, rows below; ``np.dot`` with ``out``, which costs half of ``np.matmul`` on these sizes): at
    ~0.3 us a numpy call, the number of calls is the cost.

    ``terms`` rows: 0 commanded collective thrust; 1-18 the products d_i[k] R[k, j] of the attitude
    error; 19-21 body rates; 22-30 their products w_i w_j (gyroscopic term, kept current with the
    rates); 31-34 omega^2 of the rotors. The motor lag is folded in: ``cmd`` holds ``motor_alpha``
    times the clipped rotor speed commands.
    """

    def __init__(self, airframe: Airframe, n: int, dt: float, motor_alpha: float):
        self.airframe, self.n, self.motor_alpha = airframe, n, motor_alpha
        self.s = np.zeros((19, n))  # position, quaternion, rotation, velocity (see the module docstring)
        self.rotor = np.zeros((4, n))  # rotor speeds (rad/s)
        self.cmd = np.zeros((4, n))  # motor_alpha * clipped rotor speed commands (rad/s)
        self.terms = np.zeros((35, n))
        self.rates = self.terms[19:22]  # body rates (rad/s): the state's last block, kept among the terms
        self.blocks = (self.s[0:3].T, self.s[3:7].T, self.s[7:16].T, self.s[16:19].T, self.rates.T)
        self.integrate = _make_integrator(self, dt)
        self._trackers: dict[ControllerGains, Callable[[np.ndarray], None]] = {}

    def reset(self, positions: np.ndarray) -> None:
        s = self.s
        s[:] = 0.0
        self.terms[:] = 0.0  # body rates and their products
        s[0:3] = positions.T
        s[3] = 1.0  # quaternion (1, 0, 0, 0)
        s[[7, 11, 15]] = 1.0  # identity rotation
        self.rotor[:] = self.airframe.hover_omega_radps

    def states(self) -> list[DroneState]:
        p, q, r, v, w = self.blocks
        return list(map(_MAKE_STATE, zip(p.tolist(), q.tolist(), r.tolist(), v.tolist(), w.tolist(), strict=False)))

    def step(self, rotor_omega_cmd: np.ndarray) -> None:
        """One physics step from rotor speed commands (4, N) rad/s."""
        af = self.airframe
        np.multiply(np.clip(rotor_omega_cmd, af.omega_min_radps, af.omega_max_radps), self.motor_alpha, self.cmd)
        self.integrate()

    def tracker(self, gains: ControllerGains) -> Callable[[np.ndarray], None]:
        """``track(velocity_cmd)``: controller and one physics step for world-frame commands (3, N) m/s."""
        track = self._trackers.get(gains)
        if track is None:
            control, integrate = _make_controller(self, gains), self.integrate

            def track(velocity_cmd: np.ndarray) -> None:
                control(velocity_cmd)
                integrate()

            self._trackers[gains] = track
        return track


def _make_integrator(kn: _ArrayKernel, dt: float) -> Callable[[], None]:
    """``integrate()``: one physics step from ``kn.cmd`` and the gyro products (see ``physics.base``)."""
    af, n, s = kn.airframe, kn.n, kn.s
    pos, quat, rot, vel, rates = s[0:3], s[3:7], s[7:16], s[16:19], kn.rates
    body_z, quat_w = s[9:16:3], s[3]  # column 2 of R: body z in the world frame
    cmd, rotor, terms = kn.cmd, kn.rotor, kn.terms
    omega_sq, step_terms, products = terms[31:35], terms[22:35], terms[22:31]
    rates_a, rates_b, products_3x3 = rates[:, None, :], rates[None, :, :], products.reshape(3, 3, n)
    # [dt T / m (3 rows), dt J^-1 (tau - w x J w)] = step_map @ [w_i w_j, omega^2]
    jx, jy, jz = af.inertia_kgm2
    dt_inv_inertia = dt / np.array(af.inertia_kgm2)[:, None]
    thrust_k = af.allocation * af.thrust_coeff  # [T, tau] = thrust_k @ omega^2
    gyro_map = _coefficients((3, 9), [(0, 5, jz - jy), (1, 6, jx - jz), (2, 1, jy - jx)])  # w x J w from w_i w_j
    step_map = np.zeros((6, 13))
    step_map[0:3, 9:] = thrust_k[0] * dt / af.mass_kg
    step_map[3:, :9] = -dt_inv_inertia * gyro_map
    step_map[3:, 9:] = dt_inv_inertia * thrust_k[1:]
    increments = np.zeros((6, n))
    dv_thrust, dw = increments[0:3], increments[3:6]
    rate_sq_map = _coefficients((3, 9), [(r, c, 1.0) for r in range(3) for c in (0, 4, 8)])  # |w|^2, every row
    t3, u3 = np.zeros((3, n)), np.zeros((3, n))
    t3_z, half_angle = t3[2], t3[0]
    delta = np.zeros((4, n))  # the attitude increment (cos(|w| dt/2), w sin(|w| dt/2) / |w|)
    delta_cos, delta_axis = delta[0], delta[1:4]
    outer = np.zeros((4, 4, n))
    outer_flat = outer.reshape(16, n)
    quat_a, quat_b, delta_b = quat[:, None, :], quat[None, :, :], delta[None, :, :]
    # from the products q_a q_b of the unnormalised quaternion: R |q|^2 (9 rows), |q|^2 (9 rows), |q|^2 (4 rows)
    rot_map = np.concatenate([_QUAT_TO_ROT, np.tile(np.eye(4).reshape(1, 16), (13, 1))])
    rot_terms = np.zeros((22, n))
    rot_scaled, norm_sq_9, norm_4 = rot_terms[0:9], rot_terms[9:18], rot_terms[18:22]
    keep, dt_, g_dt, half_dt, tiny = (_const(v) for v in (1.0 - kn.motor_alpha, dt, GRAVITY_MPS2 * dt, 0.5 * dt,
                                                            1e-300))
    add, sub, mul, div, dot, fmax = np.add, np.subtract, np.multiply, np.divide, np.dot, np.fmax
    sqrt, sin, cos, least = np.sqrt, np.sin, np.cos, np.minimum.reduce

    def integrate() -> None:
        # motors: exact first-order lag towards the commands; then omega^2
        mul(rotor, keep, rotor)
        add(rotor, cmd, rotor)
        mul(rotor, rotor, omega_sq)
        dot(step_map, step_terms, increments)
        # translation: v += dt (T R e_z / m + g), then p += dt v
        mul(body_z, dv_thrust, t3)
        sub(t3_z, g_dt, t3_z)
        add(vel, t3, vel)
        mul(vel, dt_, t3)
        add(pos, t3, pos)
        # body rates: w += dt J^-1 (tau - w x J w); their products for the next step
        add(rates, dw, rates)
        mul(rates_a, rates_b, products_3x3)
        # attitude increment; for tiny rates sin(x) / |w| equals Bullet's Taylor series to rounding, so
        # the array kernel takes the quotient (guarded against 0 / 0)
        dot(rate_sq_map, products, u3)  # |w|^2 in every row
        sqrt(u3, u3)
        mul(u3, half_dt, t3)
        cos(half_angle, delta_cos)
        sin(t3, t3)
        fmax(u3, tiny, u3)
        div(t3, u3, t3)
        mul(rates, t3, delta_axis)
        # q = q (x) delta, normalised, and its rotation matrix (from the products of q before normalising)
        mul(quat_a, delta_b, outer)
        dot(_QUAT_PRODUCT, outer_flat, quat)
        mul(quat_a, quat_b, outer)
        dot(rot_map, outer_flat, rot_terms)
        div(rot_scaled, norm_sq_9, rot)
        sqrt(norm_4, norm_4)
        div(quat, norm_4, quat)
        if least(quat_w) <= 0.5:  # some drone turned by 120 degrees or more: pybullet's sign (see bullet_sign)
            for i in np.flatnonzero(quat_w <= 0.5).tolist():
                quat[:, i] = bullet_sign(*quat[:, i].tolist(), rot[0, i], rot[4, i], rot[8, i])

    return integrate


def _make_controller(kn: _ArrayKernel, gains: ControllerGains) -> Callable[[np.ndarray], None]:
    """``control(velocity_cmd)``: :func:`vitfly.sim.controller.velocity_control` for all drones at once.

    The same laws on (3, N) blocks, in force units (m a), with the attitude, rate and mixer stages as
    one linear map of ``kn.terms`` (rounding differs from the scalar version, not the maths).
    World-frame commands (3, N) m/s in; ``motor_alpha`` times the rotor speed commands into ``kn.cmd``.
    """
    af, n, s = kn.airframe, kn.n, kn.s
    vel, rot_flat = s[16:19], s[7:16]
    body_z = s[9:16:3]
    terms, rotor_cmd = kn.terms, kn.cmd
    thrust_row, thrust, att_terms = terms[0:1], terms[0], terms[1:19]
    control_terms = terms[0:31]
    col, m = np.array, af.mass_kg
    m_velocity_p = _const(m * col(gains.velocity_p)[:, None], (3, n))
    m_down, m_up, weight, tan_tilt, one, zero = (_const(v) for v in (
        -m * gains.max_accel_down_mps2, m * gains.max_accel_up_mps2, m * GRAVITY_MPS2, math.tan(gains.max_tilt_rad),
        1.0, 0.0))  # fmt: skip
    # rotor thrusts clipped to the thrusts of [omega_min, omega_max], then alpha omega = sqrt(alpha^2 f / k)
    f_lo, f_hi = _const(af.thrust_coeff * max(af.omega_min_radps, 0.0) ** 2), _const(af.max_rotor_thrust_n)
    to_cmd = _const(kn.motor_alpha**2 / af.thrust_coeff)
    c, si = math.cos(gains.yaw_rad), math.sin(gains.yaw_rad)
    heading_cross = col([[0.0, 0.0, -si], [0.0, 0.0, c], [si, -c, 0.0]])  # z_des x (cos yaw, sin yaw, 0)
    # desired rates = -attitude_p e, e = vee(R_d^T R - R^T R_d) / 2 with (R_d^T R)[i, j] = sum_k d_i[k] R[k, j]:
    # the 18 products d_i[k] R[k, j] it needs, gathered from d (flat 3 i + k) and R (flat 3 k + j)
    kp = gains.attitude_p
    att = [(r, sign, i, j, k) for r, plus, minus in [(0, (2, 1), (1, 2)), (1, (0, 2), (2, 0)), (2, (1, 0), (0, 1))]
           for sign, (i, j) in ((1, plus), (-1, minus)) for k in range(3)]
    pick_desired = col([3 * i + k for _, _, i, _, k in att])
    pick_rot = col([3 * k + j for _, _, _, j, k in att])
    attitude_map = _coefficients((3, 18), [(r, t, sign * -0.5 * kp[r]) for t, (r, sign, *_) in enumerate(att)])
    # tau = rate_p J (rates_des - w) + w x J w; [T, tau] = wrench_map @ terms[0:31]; rotor thrusts = mix @ [T, tau]
    jx, jy, jz = af.inertia_kgm2
    rate_p_j = col(gains.rate_p) * col(af.inertia_kgm2)
    wrench_map = np.zeros((4, 31))
    wrench_map[0, 0] = 1.0
    wrench_map[1:, 1:19] = rate_p_j[:, None] * attitude_map
    wrench_map[1:, 19:22] = -np.diag(rate_p_j)
    wrench_map[1:, 22:31] = _coefficients((3, 9), [(0, 5, jz - jy), (1, 6, jx - jz), (2, 1, jy - jx)])
    control_map = np.linalg.inv(af.allocation) @ wrench_map
    ones13 = np.ones((1, 3))
    desired = np.zeros((3, 3, n))  # [i] = desired body axis i (world frame)
    desired_flat = desired.reshape(9, n)
    d_x, d_y, d_z = desired
    d_yz = desired_flat[3:9]
    force = d_z  # the force is computed in place of the desired z axis, which is its direction
    force_x, force_y, force_z = force
    force_xy = force[0:2]
    t1, u1, t3 = np.zeros(n), np.zeros(n), np.zeros((3, n))
    sq6, nrm6 = np.zeros((6, n)), np.zeros((6, n))
    norms_map = np.kron(np.eye(2), np.ones((3, 3)))  # |y|^2 in rows 0-2, |z|^2 in rows 3-5
    yz_outer = np.zeros((3, 3, n))
    yz_flat, y_a, z_b = yz_outer.reshape(9, n), d_y[:, None, :], d_z[None, :, :]
    att_d = np.zeros((18, n))
    rotor_thrust = np.zeros((4, n))
    add, sub, mul, div, dot, fmax, fmin = np.add, np.subtract, np.multiply, np.divide, np.dot, np.fmax, np.fmin
    sqrt, hypot = np.sqrt, np.hypot

    def control(velocity_cmd: np.ndarray) -> None:
        # desired_acceleration (times the mass): P on velocity, climb / sink limits, tilt limit horizontally
        sub(velocity_cmd, vel, force)
        mul(force, m_velocity_p, force)
        fmax(force_z, m_down, force_z)
        fmin(force_z, m_up, force_z)
        add(force_z, weight, t1)
        mul(t1, tan_tilt, t1)  # largest horizontal force, > 0 (the sink limit is below g)
        hypot(force_x, force_y, u1)
        div(u1, t1, u1)
        fmax(u1, one, u1)
        div(force_xy, u1, force_xy)  # scaled down to the largest, direction kept
        add(force_z, weight, force_z)
        # thrust_and_attitude: thrust = force along body z; desired z along the force, y = z x heading
        # (both normalised in one pass), x = y x z
        mul(force, body_z, t3)
        dot(ones13, t3, thrust_row)
        fmax(thrust, zero, thrust)
        dot(heading_cross, force, d_y)
        mul(d_yz, d_yz, sq6)
        dot(norms_map, sq6, nrm6)
        sqrt(nrm6, nrm6)
        div(d_yz, nrm6, d_yz)
        mul(y_a, z_b, yz_outer)
        dot(_CROSS, yz_flat, d_x)
        # attitude error products, body rates; then [T, tau] and the mixer in one matrix product
        desired_flat.take(pick_desired, 0, att_d)
        rot_flat.take(pick_rot, 0, att_terms)
        mul(att_terms, att_d, att_terms)
        dot(control_map, control_terms, rotor_thrust)
        fmax(rotor_thrust, f_lo, rotor_thrust)
        fmin(rotor_thrust, f_hi, rotor_thrust)
        mul(rotor_thrust, to_cmd, rotor_thrust)
        sqrt(rotor_thrust, rotor_cmd)

    return control


class NativeFleet(Fleet):
    """N quadrotors integrated by vitfly (numpy only), stepped together.

    ``vectorised``: True for the array kernel, False for the scalar one, None (default) to choose
    by size (array kernel above ``SCALAR_MAX_DRONES`` drones). Example::

        fleet = NativeFleet(num_drones=16, physics_hz=240)
        fleet.reset(np.tile([0.0, 0.0, 3.5], (16, 1)))
        states = fleet.states()
        states = fleet.track([(5.0, 0.0, 0.0)] * 16, states, ControllerGains())  # all 16 in one array step
    """

    name = "native"

    def __init__(
        self,
        num_drones: int,
        airframe: Airframe | None = None,
        physics_hz: float = 240.0,
        vectorised: bool | None = None,
    ):
        super().__init__(num_drones, airframe, physics_hz)
        self.vectorised = self.num_drones > SCALAR_MAX_DRONES if vectorised is None else bool(vectorised)
        if self.vectorised:
            self._kernel = _ArrayKernel(self.airframe, self.num_drones, self.dt, self.motor_alpha)
            self._cmd_rows: tuple = ()  # the last velocity commands converted by track (reused per tick)
            self._cmd_array = np.zeros((3, self.num_drones))
            self._tracked_gains: ControllerGains | None = None
        else:
            self._scalar_step = make_scalar_step(self.airframe, self.dt, self.motor_alpha)
        self.reset(np.zeros((self.num_drones, 3)))

    @property
    def rotor_omega(self) -> np.ndarray:
        return self._kernel.rotor.T.copy() if self.vectorised else np.array(self._rotor)

    def reset(self, positions: np.ndarray) -> None:
        positions = np.asarray(positions, dtype=np.float64).reshape(self.num_drones, 3)
        hover = self.airframe.hover_omega_radps
        if self.vectorised:
            self._kernel.reset(positions)
        else:
            identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
            self._states = [
                DroneState(tuple(p), (1.0, 0.0, 0.0, 0.0), identity, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
                for p in positions.tolist()
            ]
            self._rotor = [[hover] * 4 for _ in range(self.num_drones)]
        self._time_s = 0.0

    def states(self) -> list[DroneState]:
        return self._kernel.states() if self.vectorised else list(self._states)

    def step(self, rotor_omega_cmd, states: list[DroneState] | None = None) -> None:
        if self.vectorised:
            kn = self._kernel
            kn.step(np.asarray(rotor_omega_cmd, dtype=np.float64).reshape(self.num_drones, 4).T)
        else:
            advance = self._scalar_step
            cmds = list(rotor_omega_cmd)
            if len(cmds) != self.num_drones:
                raise ValueError(f"got {len(cmds)} rotor commands for {self.num_drones} drones")
            self._states = [
                advance(st, omega, [float(c) for c in cmd])
                for st, omega, cmd in zip(self._states, self._rotor, cmds, strict=True)
            ]
        self._time_s += self.dt

    def track(self, velocity_cmds: Sequence, states: list[DroneState], gains: ControllerGains) -> list[DroneState]:
        """One physics step under the cascaded controller; the fleet's own state is the input.

        Array kernel: controller and step for all drones in one pass of array operations (commands
        are converted to an array only when they differ from the last step's, i.e. once per tick).
        """
        if not self.vectorised:
            control = self.controller(gains)
            advance = self._scalar_step
            self._states = new = [
                advance(st, omega, control(c, st))
                for c, st, omega in zip(velocity_cmds, self._states, self._rotor, strict=True)
            ]
            self._time_s += self.dt
            return list(new)
        kn = self._kernel
        rows = tuple(map(tuple, velocity_cmds))  # cheap for tuples (the rollout's): no copies
        if rows != self._cmd_rows:
            cmds = np.asarray(rows, dtype=np.float64)
            if cmds.shape != (self.num_drones, 3):
                raise ValueError(f"velocity commands of shape {cmds.shape}, expected ({self.num_drones}, 3)")
            self._cmd_array[:] = cmds.T
            self._cmd_rows = rows
        if gains is not self._tracked_gains:  # by identity, as Fleet.controller
            self._tracked_gains, self._track = gains, kn.tracker(gains)
        self._track(self._cmd_array)
        self._time_s += self.dt
        return kn.states()
