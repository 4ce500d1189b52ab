"""Quadrotor dynamics + cascaded controller: signs, frames and tracking, on every physics back end.

Each test runs on real pybullet (skipped where it is not installed), the native back end's scalar
kernel and its array kernel (``BACKENDS``).
"""

import math

import numpy as np
import pytest

from vitfly.sim.controller import ControllerGains, desired_acceleration, mix, velocity_control
from vitfly.sim.physics import make_fleet, pybullet_available
from vitfly.sim.quadrotor import GRAVITY_MPS2, Airframe

AF, GAINS = Airframe(), ControllerGains()
START = (0.0, 0.0, 3.5)
NO_PYBULLET = pytest.mark.skipif(not pybullet_available(), reason="pybullet is not installed (no wheel here)")
BACKENDS = [
    pytest.param(("pybullet", {}), id="pybullet", marks=NO_PYBULLET),
    pytest.param(("native", {"vectorised": False}), id="native-scalar"),
    pytest.param(("native", {"vectorised": True}), id="native-array"),
]


@pytest.fixture(params=BACKENDS)
def backend(request):
    """(name, keyword arguments) of a physics back end, for ``new_fleet``."""
    return request.param


def new_fleet(backend, num_drones: int, physics_hz: float = 240.0):
    name, kwargs = backend
    return make_fleet(name, num_drones, AF, physics_hz, **kwargs)


def fly(backend, commands, seconds: float, physics_hz: float = 240.0):
    """Fly one drone per command (world-frame m/s) from START; returns times and per-drone states."""
    commands = [tuple(map(float, c)) for c in commands]
    with new_fleet(backend, len(commands), physics_hz) as fleet:
        fleet.reset(np.tile(START, (len(commands), 1)))
        states = fleet.states()
        history = []
        for _ in range(int(round(seconds * physics_hz))):
            fleet.step([velocity_control(c, s, AF, GAINS) for c, s in zip(commands, states, strict=True)], states)
            states = fleet.states()
            history.append((fleet.time_s, states))
    return history


def tilt_deg(state) -> float:
    """Angle between body z and world z."""
    return math.degrees(math.acos(max(-1.0, min(1.0, state.rotation[8]))))


def test_airframe_constants_are_the_papers():
    assert AF.mass_kg == 0.752
    assert AF.inertia_kgm2 == (0.0025, 0.0021, 0.0043)
    assert AF.max_rotor_thrust_n == pytest.approx(1.5625e-6 * 2800**2)
    # four rotors at hover carry the weight
    assert 4 * AF.thrust_coeff * AF.hover_omega_radps**2 == pytest.approx(AF.mass_kg * GRAVITY_MPS2)


def test_mix_inverts_the_allocation():
    thrust, torques = 8.0, (0.05, -0.03, 0.01)
    omega = np.array(mix(thrust, torques, AF))
    wrench = AF.allocation @ (AF.thrust_coeff * omega**2)
    np.testing.assert_allclose(wrench, [thrust, *torques], rtol=1e-9, atol=1e-12)


def test_motor_lag_reaches_63_percent_after_one_time_constant(backend):
    with new_fleet(backend, 1, 1000.0) as fleet:
        fleet.reset(np.array([START]))
        start = AF.hover_omega_radps
        target = start + 500.0
        for _ in range(int(round(AF.motor_time_constant_s * 1000))):
            fleet.step([[target] * 4])
        reached = (fleet.rotor_omega[0, 0] - start) / 500.0
    assert reached == pytest.approx(1 - math.exp(-1), abs=0.01)


def test_hover_holds_altitude_and_position(backend):
    (t, states), *_ = fly(backend, [(0, 0, 0)], 3.0)[-1:]
    p = states[0].position
    assert t == pytest.approx(3.0)
    assert abs(p[2] - 3.5) < 0.02 and abs(p[0]) < 0.01 and abs(p[1]) < 0.01
    assert tilt_deg(states[0]) < 0.5


def test_forward_5mps_tracked_within_10_percent_after_1_5_s(backend):
    history = fly(backend, [(5, 0, 0)], 3.0)
    after = [s[0] for t, s in history if t >= 1.5]
    vx = np.array([s.velocity[0] for s in after])
    assert np.all(np.abs(vx - 5.0) <= 0.5), (vx.min(), vx.max())
    assert max(abs(s.velocity[1]) for s in after) < 0.05
    assert max(abs(s.velocity[2]) for s in after) < 0.3
    assert after[-1].position[0] > 10.0  # it went forward (+x), not backward


def test_forward_acceleration_pitches_the_nose_down(backend):
    history = fly(backend, [(5, 0, 0)], 0.3)
    state = history[-1][1][0]
    # body x axis in the world frame is column 0 of R: its z component is negative when pitched down,
    # and the thrust axis (column 2) leans forward
    assert state.rotation[6] < -0.1
    assert state.rotation[2] > 0.1


@pytest.mark.parametrize(
    "command, axis, sign",
    [((0, 2, 0), 1, +1), ((0, -2, 0), 1, -1), ((0, 0, 1), 2, +1), ((0, 0, -1), 2, -1), ((-2, 0, 0), 0, -1)],
)
def test_lateral_and_vertical_commands_move_the_right_way(backend, command, axis, sign):
    history = fly(backend, [command], 2.0)
    final = history[-1][1][0]
    moved = final.position[axis] - START[axis]
    assert sign * moved > 1.0
    assert sign * final.velocity[axis] == pytest.approx(abs(sum(command)), rel=0.1)
    others = [i for i in range(3) if i != axis]
    assert all(abs(final.position[i] - START[i]) < 0.15 for i in others)


def test_lockstep_drones_are_independent(backend):
    """Two drones in one fleet fly exactly as each does alone (no coupling, no collisions)."""
    together = fly(backend, [(5, 0, 0), (0, -2, 1)], 1.0)[-1][1]
    alone_a = fly(backend, [(5, 0, 0)], 1.0)[-1][1][0]
    alone_b = fly(backend, [(0, -2, 1)], 1.0)[-1][1][0]
    np.testing.assert_allclose(together[0].position, alone_a.position, atol=1e-9)
    np.testing.assert_allclose(together[1].position, alone_b.position, atol=1e-9)


def test_long_random_flight_has_no_nan_and_bounded_attitude(backend):
    rng = np.random.default_rng(0)
    hz = 240.0
    with new_fleet(backend, 1, hz) as fleet:
        fleet.reset(np.array([START]))
        states = fleet.states()
        max_tilt = 0.0
        command = (0.0, 0.0, 0.0)
        for k in range(int(60 * hz)):
            if k % 8 == 0:  # a new command at 30 Hz, drawn like an erratic policy
                z = states[0].position[2]
                command = (rng.uniform(-3, 8), rng.uniform(-4, 4), rng.uniform(-2, 2) + 0.5 * (3.5 - z))
            fleet.step([velocity_control(command, states[0], AF, GAINS)], states)
            states = fleet.states()
            max_tilt = max(max_tilt, tilt_deg(states[0]))
        final = states[0]
    values = np.array([*final.position, *final.velocity, *final.quat, *final.body_rates])
    assert np.all(np.isfinite(values))
    assert np.linalg.norm(final.quat) == pytest.approx(1.0, abs=1e-6)
    assert max_tilt < math.degrees(GAINS.max_tilt_rad) + 15.0


def test_desired_acceleration_respects_the_tilt_limit():
    acc = desired_acceleration((100.0, 0.0, 0.0), (0.0, 0.0, 0.0), GAINS)
    assert acc[0] == pytest.approx(GRAVITY_MPS2 * math.tan(GAINS.max_tilt_rad))
    assert acc[1] == 0.0 and acc[2] == 0.0
