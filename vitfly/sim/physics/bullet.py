"""The pybullet back end: the reference integrator, pybullet in DIRECT mode.

pybullet integrates the rigid body (gravity, Newton-Euler, Bullet's ``btMultiBody`` semi-implicit
Euler; see :mod:`vitfly.sim.physics.base`); this module models what pybullet does not: first-order
motor lag, the rotor thrust map, and the rotor forces and reaction torques, which it applies to the
body every physics step.

Several drones (one per lockstep scene) share one pybullet client. The drone bodies have no
collision shapes, so they never touch each other or an obstacle (obstacles are not in pybullet at
all: contact is detected geometrically by ``vitfly.sim.collision``), and one ``stepSimulation``
advances every scene.

The per-step maths is written with Python floats rather than numpy: it runs 240+ times per
simulated second per drone on 3-vectors, where numpy's per-call overhead would dominate.
"""

from __future__ import annotations

import contextlib
import os

import numpy as np

from vitfly.quiet import silence_fds
from vitfly.sim.physics.base import Fleet
from vitfly.sim.quadrotor import GRAVITY_MPS2, Airframe, DroneState

with silence_fds():  # pybullet prints "pybullet build time: ..." from C at import
    import pybullet


# Connecting a pybullet client costs ~15 ms, a noticeable part of a short episode: closed fleets
# leave their client here, emptied by resetSimulation (which rebuilds the dynamics world), for the
# next fleet of this process. Every fleet sets gravity, time step and engine parameters itself.
_IDLE_CLIENTS: list[tuple[int, int]] = []  # (process id, client id)
_MAX_IDLE_CLIENTS = 4


def _acquire_client() -> int:
    pid = os.getpid()
    while _IDLE_CLIENTS:
        owner, cid = _IDLE_CLIENTS.pop()
        if owner == pid and pybullet.isConnected(physicsClientId=cid):
            return cid
    with silence_fds(1):  # some pybullet builds print a banner on connect; keep it off stdout
        return pybullet.connect(pybullet.DIRECT)


def _release_client(cid: int) -> None:
    if len(_IDLE_CLIENTS) < _MAX_IDLE_CLIENTS and pybullet.isConnected(physicsClientId=cid):
        pybullet.resetSimulation(physicsClientId=cid)
        _IDLE_CLIENTS.append((os.getpid(), cid))
    else:
        pybullet.disconnect(physicsClientId=cid)


class PybulletFleet(Fleet):
    """N quadrotors in one pybullet DIRECT client, stepped together (the reference back end).

    Example::

        fleet = PybulletFleet(num_drones=2, airframe=Airframe(), physics_hz=240)
        fleet.reset(np.array([[0, 0, 3.5], [0, 0, 3.5]]))
        hover = [fleet.airframe.hover_omega_radps] * 4
        fleet.step([hover, hover])          # one 1/240 s step of both drones
        fleet.states()[0].position
    """

    name = "pybullet"

    def __init__(self, num_drones: int, airframe: Airframe | None = None, physics_hz: float = 240.0):
        super().__init__(num_drones, airframe, physics_hz)
        self._cid = _acquire_client()
        pybullet.setGravity(0.0, 0.0, -GRAVITY_MPS2, physicsClientId=self._cid)
        pybullet.setTimeStep(self.dt, physicsClientId=self._cid)
        pybullet.setPhysicsEngineParameter(numSubSteps=1, deterministicOverlappingPairs=1, physicsClientId=self._cid)
        self._bodies = [self._create_body() for _ in range(self.num_drones)]
        self._rotor_omega = [[0.0] * 4 for _ in range(self.num_drones)]
        self._time_s = 0.0

    def _create_body(self) -> int:
        af = self.airframe
        # no collision shape: drones never touch each other (contact with obstacles is geometric)
        body = pybullet.createMultiBody(baseMass=af.mass_kg, baseCollisionShapeIndex=-1, physicsClientId=self._cid)
        pybullet.changeDynamics(
            body,
            -1,
            localInertiaDiagonal=list(af.inertia_kgm2),
            linearDamping=0.0,
            angularDamping=0.0,
            physicsClientId=self._cid,
        )
        return body

    @property
    def rotor_omega(self) -> np.ndarray:
        """(N, 4) current rotor speeds (rad/s)."""
        return np.array(self._rotor_omega)

    def close(self) -> None:
        if self._cid is not None:
            _release_client(self._cid)
            self._cid = None

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def reset(self, positions: np.ndarray) -> None:
        """Place drone i at ``positions[i]`` (m, world), level, heading +x, at rest, rotors at hover speed."""
        positions = np.asarray(positions, dtype=np.float64).reshape(self.num_drones, 3)
        for body, pos in zip(self._bodies, positions, strict=True):
            pybullet.resetBasePositionAndOrientation(
                body, pos.tolist(), [0.0, 0.0, 0.0, 1.0], physicsClientId=self._cid
            )
            pybullet.resetBaseVelocity(body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=self._cid)
        hover = self.airframe.hover_omega_radps
        self._rotor_omega = [[hover] * 4 for _ in range(self.num_drones)]
        self._time_s = 0.0

    def states(self) -> list[DroneState]:
        """Current state of every drone (see :class:`DroneState`)."""
        cid = self._cid
        get_pose, get_velocity, to_matrix = (
            pybullet.getBasePositionAndOrientation,
            pybullet.getBaseVelocity,
            pybullet.getMatrixFromQuaternion,
        )
        out = []
        for body in self._bodies:
            pos, q = get_pose(body, cid)
            vel, w = get_velocity(body, cid)
            r = to_matrix(q)
            # body rates = R^T omega_world
            rates = (
                r[0] * w[0] + r[3] * w[1] + r[6] * w[2],
                r[1] * w[0] + r[4] * w[1] + r[7] * w[2],
                r[2] * w[0] + r[5] * w[1] + r[8] * w[2],
            )
            out.append(DroneState(pos, (q[3], q[0], q[1], q[2]), r, vel, rates))
        return out

    def step(self, rotor_omega_cmd, states: list[DroneState] | None = None) -> None:
        """Advance all drones one physics step.

        rotor_omega_cmd: N sequences of 4 commanded rotor speeds (rad/s), clipped to the motors'
        range; the motors follow with a first-order lag. ``states`` is :meth:`states` at the start
        of the step if the caller has it already (saves querying pybullet twice).
        """
        af, cid = self.airframe, self._cid
        if states is None:
            states = self.states()
        k, kappa, alpha = af.thrust_coeff, af.torque_coeff, self.motor_alpha
        lo, hi = af.omega_min_radps, af.omega_max_radps
        ax, ay = af.arm_x_m, af.arm_y_m
        apply_force, apply_torque = pybullet.applyExternalForce, pybullet.applyExternalTorque
        world = pybullet.WORLD_FRAME
        for body, omega, cmd, st in zip(self._bodies, self._rotor_omega, rotor_omega_cmd, states, strict=True):
            # clip to [lo, hi] (as min(max(c, lo), hi)), unrolled because this runs at the physics rate and
            # builtin min/max calls cost more; then the exact discretisation of the first-order lag
            c0, c1, c2, c3 = cmd
            c0, c1, c2, c3 = float(c0), float(c1), float(c2), float(c3)
            o0, o1, o2, o3 = omega
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
            o0 += alpha * (c0 - o0)
            o1 += alpha * (c1 - o1)
            o2 += alpha * (c2 - o2)
            o3 += alpha * (c3 - o3)
            omega[0], omega[1], omega[2], omega[3] = o0, o1, o2, o3
            f0, f1, f2, f3 = k * o0 * o0, k * o1 * o1, k * o2 * o2, k * o3 * o3
            thrust = f0 + f1 + f2 + f3
            tau_x = ay * (-f0 + f1 - f2 + f3)
            tau_y = ax * (-f0 + f1 + f2 - f3)
            tau_z = kappa * (f0 + f1 - f2 - f3)
            r = st.rotation
            force = (r[2] * thrust, r[5] * thrust, r[8] * thrust)
            torque = (
                r[0] * tau_x + r[1] * tau_y + r[2] * tau_z,
                r[3] * tau_x + r[4] * tau_y + r[5] * tau_z,
                r[6] * tau_x + r[7] * tau_y + r[8] * tau_z,
            )
            # (the client id passed by position: keyword parsing costs more than these calls' work)
            apply_force(body, -1, force, st.position, world, cid)
            apply_torque(body, -1, torque, world, cid)
        pybullet.stepSimulation(cid)
        self._time_s += self.dt
