"""The contract every physics back end keeps: N quadrotors of one airframe, stepped together.

A back end integrates the rigid-body motion of drones that have no collision shapes (obstacles and
contact are vitfly's own geometry). What happens in one physics step of ``dt`` seconds is fixed
here, so that the back ends agree to rounding (``tests/test_physics_parity.py`` bounds the gap):

1. Motors: each rotor speed follows its command (clipped to ``[omega_min, omega_max]`` rad/s) as a
   first-order lag, discretised exactly: ``omega += (1 - exp(-dt / tau)) * (cmd - omega)``.
2. Wrench: rotor thrusts ``k omega^2``; collective thrust along body z, body torques from the
   rotor layout and reaction torques (:attr:`vitfly.sim.quadrotor.Airframe.allocation`), all
   taken with the attitude at the start of the step.
3. Semi-implicit Euler, the scheme of Bullet's ``btMultiBody`` that pybullet uses for a free base
   (with the zero linear and angular damping vitfly sets, gyroscopic term on, one sub-step):
   ``v += dt * (thrust * R e_z / m + g)``, then ``p += dt * v``;
   ``w += dt * J^-1 (tau - w x J w)`` (body frame), then the attitude turns by the exponential map
   of the new rate, ``q = q (x) exp(w dt / 2)``, normalised.

State read-out (:class:`vitfly.sim.quadrotor.DroneState`): world-frame position (m), velocity
(m/s), attitude (w, x, y, z) body-to-world and its rotation matrix, body rates (rad/s).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from vitfly.sim.controller import ControllerGains, make_velocity_controller
from vitfly.sim.quadrotor import Airframe, DroneState


class Fleet(ABC):
    """N quadrotors stepped together by one physics back end.

    Example::

        with make_fleet("native", num_drones=2, physics_hz=240) as fleet:
            fleet.reset(np.array([[0, 0, 3.5], [0, 0, 3.5]]))
            states = fleet.states()
            states = fleet.track([(5.0, 0.0, 0.0), (0.0, 1.0, 0.0)], states, ControllerGains())
            states[0].position
    """

    name: ClassVar[str]  # "pybullet" or "native": what datasets and trial records state

    def __init__(self, num_drones: int, airframe: Airframe | None = None, physics_hz: float = 240.0):
        self.airframe = airframe or Airframe()
        self.num_drones = int(num_drones)
        self.dt = 1.0 / float(physics_hz)
        # exact discretisation of the first-order motor lag over one step
        self.motor_alpha = 1.0 - math.exp(-self.dt / self.airframe.motor_time_constant_s)
        self._time_s = 0.0
        self._gains: ControllerGains | None = None  # the gains of the last track call, and their controller
        self._control = None

    @property
    def time_s(self) -> float:
        """Simulated time since the last reset (s)."""
        return self._time_s

    @property
    @abstractmethod
    def rotor_omega(self) -> np.ndarray:
        """(N, 4) current rotor speeds (rad/s)."""

    @abstractmethod
    def reset(self, positions: np.ndarray) -> None:
        """Place drone i at ``positions[i]`` (m, world), level, heading +x, at rest, rotors at hover speed."""

    @abstractmethod
    def states(self) -> list[DroneState]:
        """Current state of every drone (see :class:`DroneState`)."""

    @abstractmethod
    def step(self, rotor_omega_cmd, states: list[DroneState] | None = None) -> None:
        """Advance all drones one physics step.

        rotor_omega_cmd: N sequences of 4 commanded rotor speeds (rad/s). ``states``: :meth:`states`
        at the start of the step if the caller has it already (a cache, not an input).
        """

    def track(self, velocity_cmds: Sequence, states: list[DroneState], gains: ControllerGains) -> list[DroneState]:
        """One physics step with the cascaded controller tracking world-frame velocity commands (m/s).

        ``velocity_cmds``: N 3-sequences; ``states``: :meth:`states` now. Returns the states after
        the step. The same as ``step([velocity_control(c, s, airframe, gains) ...]); states()``;
        back ends override it to do the whole batch at once.
        """
        control = self.controller(gains)
        self.step([control(c, s) for c, s in zip(velocity_cmds, states, strict=True)], states)
        return self.states()

    def controller(self, gains: ControllerGains):
        """:func:`vitfly.sim.controller.make_velocity_controller` for these gains, built once per gains
        object (looked up by identity: hashing the gains every physics step would cost more)."""
        if gains is not self._gains:
            self._gains, self._control = gains, make_velocity_controller(self.airframe, gains)
        return self._control

    def close(self) -> None:  # noqa: B027 - optional: only back ends holding resources override it
        """Release what the back end holds (a pybullet client); the fleet is unusable afterwards."""

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
