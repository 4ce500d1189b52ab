"""Physics back ends: pybullet and native agree; native against closed forms; choosing a back end.

Parity: the same command sequences flown through pybullet and through both native kernels stay
within ``PARITY_TOLERANCE`` (position, attitude, velocity, body rates) over 60 s random flights.
Measured gaps are ~1e-13 (rounding), the bounds are 1e-9: anything that changes the scheme (a
damping term, explicit instead of semi-implicit Euler, another attitude update) moves them by
orders of magnitude more (see ``test_tolerance_would_catch_a_different_scheme``).
"""

import json
import math
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from vitfly.cli import main
from vitfly.errors import VitflyError
from vitfly.eval import records
from vitfly.sim import physics
from vitfly.sim.controller import ControllerGains
from vitfly.sim.physics import make_fleet, pybullet_available, resolve_physics
from vitfly.sim.physics.native import SCALAR_MAX_DRONES
from vitfly.sim.physics.parity import PARITY_TOLERANCE, state_array
from vitfly.sim.physics.parity import state_gaps as gaps
from vitfly.sim.policies import ExpertPolicy
from vitfly.sim.quadrotor import GRAVITY_MPS2, Airframe
from vitfly.sim.rollout import RolloutConfig, run_episodes
from vitfly.sim.scenes import make_scene

AF, GAINS, HZ = Airframe(), ControllerGains(), 240.0
START = (0.0, 0.0, 3.5)
TOLERANCE = PARITY_TOLERANCE
NEEDS_PYBULLET = pytest.mark.skipif(not pybullet_available(), reason="pybullet is not installed (no wheel here)")
KERNELS = [pytest.param({"vectorised": False}, id="scalar"), pytest.param({"vectorised": True}, id="array")]
BACKENDS = [pytest.param(("pybullet", {}), id="pybullet", marks=NEEDS_PYBULLET),
            *(pytest.param(("native", k.values[0]), id=f"native-{k.id}") for k in KERNELS)]


def random_commands(seed: int, num_drones: int, seconds: float) -> np.ndarray:
    """(ticks, drones, 3) world-frame velocity commands (m/s) at 30 Hz, drawn like an erratic policy."""
    rng = np.random.default_rng(seed)
    ticks = int(round(seconds * 30))
    low, high = np.array([-3.0, -4.0, -2.0]), np.array([8.0, 4.0, 2.0])
    return rng.uniform(low, high, size=(ticks, num_drones, 3))


def fly_commands(name: str, commands: np.ndarray, **kwargs) -> np.ndarray:
    """Fly (ticks, N, 3) velocity commands, 8 physics steps a tick; returns (ticks, N, 13) states at
    each tick's end: position, quaternion (w, x, y, z), velocity, body rates."""
    ticks, n, _ = commands.shape
    out = np.zeros((ticks, n, 13))
    with make_fleet(name, n, AF, HZ, **kwargs) as fleet:
        fleet.reset(np.tile(START, (n, 1)))
        states = fleet.states()
        for t in range(ticks):
            rows = [tuple(c) for c in commands[t].tolist()]
            for _ in range(8):
                states = fleet.track(rows, states, GAINS)
            out[t] = state_array(states)
    return out


def assert_within_tolerance(found: dict[str, float]) -> None:
    for key, bound in TOLERANCE.items():
        assert found[key] <= bound, (key, found)


@NEEDS_PYBULLET
@pytest.mark.parametrize("kernel", KERNELS)
def test_native_flies_60_s_random_commands_as_pybullet(kernel):
    commands = random_commands(seed=3, num_drones=4, seconds=60.0)
    reference = fly_commands("pybullet", commands)
    native = fly_commands("native", commands, **kernel)
    # a real flight: it went places, turned and tilted (else agreement would prove little)
    assert np.ptp(reference[..., 0:3], axis=0).max() > 50.0
    assert np.abs(reference[..., 10:13]).max() > 1.0
    assert_within_tolerance(gaps(reference, native))


def test_native_kernels_agree_over_60_s():
    """The scalar and the array kernel are the same maths (runs where pybullet is absent too)."""
    commands = random_commands(seed=4, num_drones=3, seconds=60.0)
    assert_within_tolerance(gaps(fly_commands("native", commands, vectorised=False),
                                 fly_commands("native", commands, vectorised=True)))


@NEEDS_PYBULLET
@pytest.mark.parametrize("kernel", KERNELS)
def test_native_steps_rotor_commands_as_pybullet(kernel):
    """Open loop (no controller): the same rotor speed commands for 1 s give the same motion."""
    rng = np.random.default_rng(5)
    cmds = AF.hover_omega_radps + rng.uniform(-40.0, 40.0, size=(240, 3, 4))
    cmds[:10, 0] = 3000.0  # beyond omega_max: both clip
    cmds[:, 2] = AF.hover_omega_radps + np.array([300.0, -200.0, 250.0, -150.0])  # drone 2 tumbles
    finals = []
    for name, kwargs in (("pybullet", {}), ("native", kernel)):
        with make_fleet(name, 3, AF, HZ, **kwargs) as fleet:
            fleet.reset(np.tile(START, (3, 1)))
            for c in cmds:
                fleet.step(c.tolist())
            finals.append((state_array(fleet.states()), fleet.rotor_omega, fleet.time_s))
    (a, rotor_a, time_a), (b, rotor_b, time_b) = finals
    assert_within_tolerance(gaps(a[None], b[None]))
    # the same quaternion, sign included, also for the drone that turned over (see native.bullet_sign)
    assert a[2, 3] < 0.5
    np.testing.assert_allclose(b[:, 3:7], a[:, 3:7], atol=TOLERANCE["attitude_rad"])
    np.testing.assert_allclose(rotor_a, rotor_b, rtol=1e-12)
    assert time_a == pytest.approx(time_b) == pytest.approx(1.0)


def test_tolerance_would_catch_a_different_scheme():
    """Explicit Euler on position (p += dt v_old) instead of semi-implicit moves the path by far more
    than the tolerance: worked out by hand, after a 1 s climb at a ~ 1 m/s^2 the gap is about
    sum(dt * dv) = dt * v_end ~ 4e-3 m, i.e. the bound is sensitive to the scheme."""
    dt, accel, steps = 1.0 / HZ, 1.0, int(HZ)
    v = np.arange(1, steps + 1) * dt * accel  # velocity after each step
    semi_implicit = dt * v.sum()
    explicit = dt * np.concatenate([[0.0], v[:-1]]).sum()
    assert semi_implicit - explicit == pytest.approx(dt * v[-1])
    assert semi_implicit - explicit > 1e6 * TOLERANCE["position_m"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_spin_down_fall_matches_the_closed_form(backend):
    """Rotors commanded to 0 from hover: omega_k = omega_h (1 - alpha)^k (exact lag), thrust 4 k omega_k^2,
    semi-implicit Euler v_k = v_k-1 + dt (T_k / m - g), z_k = z_k-1 + dt v_k; worked out here with numpy sums."""
    name, kwargs = backend
    steps, dt = 120, 1.0 / HZ
    alpha = 1.0 - math.exp(-dt / AF.motor_time_constant_s)
    omega = AF.hover_omega_radps * (1.0 - alpha) ** np.arange(1, steps + 1)
    v = np.cumsum(dt * (4.0 * AF.thrust_coeff * omega**2 / AF.mass_kg - GRAVITY_MPS2))
    z = START[2] + np.cumsum(dt * v)
    with make_fleet(name, 1, AF, HZ, **kwargs) as fleet:
        fleet.reset(np.array([START]))
        for _ in range(steps):
            fleet.step([[0.0] * 4])
        s = fleet.states()[0]
    assert s.velocity[2] == pytest.approx(v[-1], abs=1e-12)
    assert s.position[2] == pytest.approx(z[-1], abs=1e-12)
    # level and still, to rounding (the array kernel's matmuls sum the equal rotor torques in another order)
    assert max(abs(s.position[0]), abs(s.position[1]), *map(abs, s.body_rates)) < 1e-12
    np.testing.assert_allclose(s.quat, [1.0, 0.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_yaw_torque_turns_by_the_closed_form_angle(backend):
    """Rotors 0, 1 (reaction +kappa T) faster than 2, 3: a pure yaw torque tau_z = kappa k sum(s_i omega_i^2)
    (roll and pitch torques cancel), no gyroscopic term about a principal axis, so w_z,k = w_z,k-1 +
    dt tau_z,k / J_z and the yaw angle is sum(dt w_z,k) (rotations about one axis compose exactly);
    quaternion (cos(psi/2), 0, 0, sin(psi/2)). Worked out here from the airframe constants."""
    name, kwargs = backend
    steps, dt, delta = 240, 1.0 / HZ, 150.0
    alpha = 1.0 - math.exp(-dt / AF.motor_time_constant_s)
    hover = AF.hover_omega_radps
    cmd = np.array([hover + delta, hover + delta, hover - delta, hover - delta])
    decay = (1.0 - alpha) ** np.arange(1, steps + 1)[:, None]
    omega = cmd + (hover - cmd) * decay  # (steps, 4)
    tau_z = AF.torque_coeff * AF.thrust_coeff * (omega**2 @ np.array([1.0, 1.0, -1.0, -1.0]))
    rate_z = np.cumsum(dt * tau_z / AF.inertia_kgm2[2])
    yaw = np.sum(dt * rate_z)
    with make_fleet(name, 1, AF, HZ, **kwargs) as fleet:
        fleet.reset(np.array([START]))
        for _ in range(steps):
            fleet.step([cmd.tolist()])
        s = fleet.states()[0]
    assert yaw > 1.0  # turned left (counter-clockwise from above) by more than a radian
    assert s.body_rates[2] == pytest.approx(rate_z[-1], rel=1e-12)
    assert abs(s.body_rates[0]) < 1e-12 and abs(s.body_rates[1]) < 1e-12
    # yaw > pi: cos(yaw / 2) < 0, and pybullet reports -q (w > 0 while the trace 1 + 2 cos(yaw) > 0)
    assert 2 * math.pi - math.acos(-0.5) < yaw < 2 * math.pi  # cos(yaw) > -1/2: trace > 0
    np.testing.assert_allclose(s.quat, [-math.cos(yaw / 2), 0.0, 0.0, -math.sin(yaw / 2)], atol=1e-12)
    np.testing.assert_allclose(np.reshape(s.rotation, (3, 3))[:2, :2],
                               [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]], atol=1e-12)


@NEEDS_PYBULLET
@pytest.mark.parametrize("num_scenes", [1, SCALAR_MAX_DRONES + 1], ids=["scalar", "array"])
def test_expert_episodes_agree_between_back_ends(num_scenes):
    """Whole episodes (expert, contact tests, end conditions) on both back ends: same outcomes, paths
    within the tolerance."""
    scenes = [make_scene("spheres", "medium", 300 + i) for i in range(num_scenes)]
    speeds = [4.0 + 0.25 * i for i in range(num_scenes)]
    runs = {name: run_episodes(scenes, speeds, ExpertPolicy(), RolloutConfig(physics=name))
            for name in ("pybullet", "native")}
    for ref, nat in zip(runs["pybullet"], runs["native"], strict=True):
        ref_s, nat_s = ref.summary, nat.summary
        assert (ref_s.end_reason, ref_s.n_collisions, ref_s.success) == (nat_s.end_reason, nat_s.n_collisions,
                                                                         nat_s.success)
        assert ref_s.duration_s == pytest.approx(nat_s.duration_s, abs=1e-9)
        assert len(ref.log) == len(nat.log) > 100
        np.testing.assert_allclose(nat.log.position, ref.log.position, atol=TOLERANCE["position_m"])
        np.testing.assert_allclose(nat.log.velocity, ref.log.velocity, atol=TOLERANCE["velocity_mps"])
        np.testing.assert_allclose(nat.log.command, ref.log.command, atol=1e-9)


def test_resolving_a_back_end(monkeypatch, capfd):
    monkeypatch.delenv(physics._NOTICE_ENV, raising=False)
    assert resolve_physics("native") == "native"
    with pytest.raises(VitflyError, match="physics back end 'bullet' unknown; expected one of auto, pybullet, native"):
        resolve_physics("bullet")
    monkeypatch.setattr(physics, "_PYBULLET", [True])
    assert resolve_physics("auto") == resolve_physics(None) == "pybullet"
    monkeypatch.setattr(physics, "_PYBULLET", [False])
    with pytest.raises(VitflyError, match=r"my.yaml: field physics: physics back end 'pybullet' is not installed"):
        resolve_physics("pybullet", "my.yaml: field physics")
    assert capfd.readouterr().err == ""
    assert resolve_physics("auto") == resolve_physics("auto") == "native"
    err = capfd.readouterr().err
    assert err.count("pybullet is not installed") == 1 and "native physics back end" in err
    assert os.environ[physics._NOTICE_ENV] == "1"  # inherited by worker processes: they stay quiet


BLOCK_PYBULLET = "import sys; sys.modules['pybullet'] = None; "  # as on a Python without a pybullet wheel


def run_without_pybullet(code: str, tmp_path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != physics._NOTICE_ENV}
    return subprocess.run([sys.executable, "-c", BLOCK_PYBULLET + code], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=300)


def test_without_pybullet_vitfly_flies_natively_and_says_so_once(tmp_path):
    code = (
        "from vitfly.sim import ExpertPolicy, RolloutConfig, TaskConfig, make_scene, run_episodes\n"
        "scenes = [make_scene('spheres', 'medium', s) for s in range(2)]\n"
        "task = TaskConfig(timeout_s=1.0, timeout_speed_factor=0.0)\n"
        "for _ in range(2):\n"
        "    r = run_episodes(scenes, [5.0, 5.0], ExpertPolicy(), RolloutConfig(task=task))\n"
        "print(r[0].summary.end_reason, len(r[0].log))\n"
    )
    proc = run_without_pybullet(code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["timeout", "30"]
    assert proc.stderr.count("pybullet is not installed") == 1, proc.stderr


def test_without_pybullet_asking_for_it_is_one_line(tmp_path):
    code = "from vitfly.cli import main; raise SystemExit(main(['collect', '--physics', 'pybullet', '--out', 'x.h5']))"
    proc = run_without_pybullet(code, tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "physics back end 'pybullet' is not installed" in lines[0], proc.stderr
    assert not (tmp_path / "x.h5").exists()


def test_collect_and_evaluate_state_their_back_end(tmp_path):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text("trajectories: 1\nspeeds: [7.0, 7.0]\ntimeout_s: 2.0\n")
    data = tmp_path / "d.h5"
    assert main(["collect", "--config", str(cfg), "--out", str(data), "--physics", "native", "--no-progress"]) == 0
    with h5py.File(data, "r") as f:
        assert json.loads(f.attrs["config"])["collect"]["physics"] == "native"
    out = tmp_path / "eval"
    assert main(["evaluate", "--policy", "straight", "--speeds", "5", "--trials", "2", "--timeout", "1",
                 "--physics", "native", "--out", str(out), "--no-gif", "--no-plots", "--no-progress"]) == 0
    flown = records.read_sweep(out)
    assert len(flown) == 2 and {r.extra["physics"] for r in flown} == {"native"}
    # auto is stored as what it resolved to, never as "auto"
    auto = tmp_path / "eval-auto"
    assert main(["evaluate", "--policy", "straight", "--speeds", "5", "--trials", "1", "--timeout", "1",
                 "--out", str(auto), "--no-gif", "--no-plots", "--no-progress"]) == 0
    assert records.read_sweep(auto)[0].extra["physics"] == ("pybullet" if pybullet_available() else "native")
