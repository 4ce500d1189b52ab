"""The batched torch engine (vitfly.sim.batched) against the numpy engine: camera, expert, physics,
whole episodes, and gradients.

Every comparison runs in float64 on the CPU, eagerly; the worst gaps measured are in docs/simulator.md.
"""

import dataclasses
import shutil

import numpy as np
import pytest
import torch

from vitfly.sim.batched.camera import BatchedCamera, pixel_rays
from vitfly.sim.batched.controller import velocity_control
from vitfly.sim.batched.dynamics import hover_state, physics_step, quat_to_rotation
from vitfly.sim.batched.expert import expert_commands, visible_cover
from vitfly.sim.batched.policies import BatchedMixture, NumpyPolicy, as_batched_policy
from vitfly.sim.batched.rollout import BatchedSettings, run_batched
from vitfly.sim.batched.scenes import scene_batch
from vitfly.sim.camera import CAMERA_PRESETS, CameraConfig, DepthCamera
from vitfly.sim.controller import ControllerGains
from vitfly.sim.expert import ALL_SEEING, ExpertConfig, ExpertObstacles, expert_command
from vitfly.sim.physics.native import NativeFleet
from vitfly.sim.physics.parity import state_array, state_gaps
from vitfly.sim.policies import ExpertPolicy, MixturePolicy, StraightPolicy
from vitfly.sim.quadrotor import Airframe, quat_wxyz_to_matrix
from vitfly.sim.rollout import RolloutConfig, TaskConfig, run_episodes
from vitfly.sim.scenes import ENVS, Scene, make_scene

F64 = torch.float64
TOL_M = 1e-6  # depth (m) and states: the bound; measured gaps are ~1e-13


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def random_poses(env, scenes, rng):
    """Positions around the obstacles (in front of the wall for window scenes) and tilted attitudes."""
    n = len(scenes)
    pos = np.stack([rng.uniform([0.0, -3.0, 1.0], [50.0, 3.0, 6.0]) for _ in range(n)])
    if env == "window":
        pos[:, 0] = np.array([s.boxes[0, 0] for s in scenes]) - rng.uniform(0.2, 6.0, n)
    q = rng.normal(size=(n, 4)) * [1.0, 0.2, 0.2, 0.2]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return pos, quat_wxyz_to_matrix(q)


@pytest.mark.parametrize("preset", list(CAMERA_PRESETS))
@pytest.mark.parametrize("env", ENVS)
def test_depth_equals_the_numpy_camera_on_every_family_and_preset(env, preset):
    rng = np.random.default_rng(len(env) + len(preset))
    cfg = CameraConfig.from_preset(preset)
    scenes = [make_scene(env, "medium", s) for s in range(5)]
    pos, rot = random_poses(env, scenes, rng)
    ref = np.stack([DepthCamera(cfg).metric_depth(s, p, r) for s, p, r in zip(scenes, pos, rot, strict=True)])
    got = BatchedCamera(cfg).metric_depth(scene_batch(scenes), torch.tensor(pos), torch.tensor(rot)).numpy()
    assert np.array_equal(np.isfinite(got), np.isfinite(ref))
    hit = np.isfinite(ref)
    assert hit.mean() > 0.2  # the poses see something
    assert np.abs(got[hit] - ref[hit]).max() <= TOL_M
    image = BatchedCamera(cfg).render(scene_batch(scenes), torch.tensor(pos), torch.tensor(rot)).numpy()
    numpy_image = np.stack([DepthCamera(cfg).render(s, p, r) for s, p, r in zip(scenes, pos, rot, strict=True)])
    assert np.abs(image - numpy_image).max() <= TOL_M / cfg.max_range_m + 1e-7  # + float32 rounding


@pytest.mark.parametrize("preset", list(CAMERA_PRESETS))
def test_pair_kernels_compute_the_numpy_cameras_rays_bit_for_bit(preset):
    # the pair kernels compute each pixel's ray instead of gathering it: the same float64 values
    ref = DepthCamera(CameraConfig.from_preset(preset))
    h, w = ref.config.height, ref.config.width
    row, col = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    u, v = pixel_rays(row, col, ref._tan_h, ref._tan_v, h, w, F64)
    assert np.array_equal(u.numpy(), ref._u) and np.array_equal(v.numpy(), ref._v)


def test_other_geometries_ground_off_and_rendering_a_subset():
    rng = np.random.default_rng(3)
    cfg = CameraConfig(height=24, width=40, horizontal_fov_deg=90.0, vertical_fov_deg=60.0,
                       mount_offset_m=(0.1, 0.05, -0.02), max_range_m=15.0, render_ground=False)
    scenes = [make_scene(env, "hard", 7) for env in ENVS]
    pos, rot = random_poses("spheres", scenes, rng)
    pos[2, 0] = scenes[2].boxes[0, 0] - 3.0
    envs = torch.tensor([i in (0, 2) for i in range(len(scenes))])  # a subset: the first and third families
    got = BatchedCamera(cfg).metric_depth(scene_batch(scenes), torch.tensor(pos), torch.tensor(rot), envs).numpy()
    for i in (0, 2):
        ref = DepthCamera(cfg).metric_depth(scenes[i], pos[i], rot[i])
        hit = np.isfinite(ref)
        assert np.array_equal(np.isfinite(got[i]), hit) and hit.any()
        assert np.abs(got[i][hit] - ref[hit]).max() <= TOL_M
    assert all(np.isinf(got[i]).all() for i in range(len(scenes)) if i not in (0, 2))  # not rendered


def test_noise_and_dropout_use_the_numpy_draws():
    cfg = CameraConfig(noise_std_m=0.05, dropout_prob=0.1)
    scene = make_scene("spheres", "medium", 2)
    pos, rot = np.array([10.0, 0.0, 3.5]), np.eye(3)
    ref = DepthCamera(cfg).render(scene, pos, rot, np.random.default_rng(5))
    draws = np.random.default_rng(5)
    noise = draws.normal(0.0, cfg.noise_std_m, ref.shape)
    dropout = draws.random(ref.shape)
    got = BatchedCamera(cfg).render(scene_batch([scene]), torch.tensor(pos[None]), torch.tensor(rot[None]),
                                    noise=torch.tensor(noise[None]), dropout=torch.tensor(dropout[None]))[0]
    assert (ref == 0).sum() > 100 and np.array_equal(got.numpy() == 0, ref == 0)
    assert np.abs(got.numpy() - ref).max() <= 1e-7


@pytest.mark.parametrize("config", [ExpertConfig(), ALL_SEEING], ids=["flightmare", "all_seeing"])
@pytest.mark.parametrize("env", ENVS)
def test_expert_commands_equal_the_numpy_expert(env, config):
    rng = np.random.default_rng(11)
    scenes = [make_scene(env, "medium", s) for s in range(24)]
    pos = np.stack([rng.uniform([0.0, -6.0, 0.5], [58.0, 6.0, 9.0]) for _ in scenes])
    if env == "window":
        pos[:, 0] = np.array([s.boxes[0, 0] for s in scenes]) - rng.uniform(-1.0, 9.0, len(scenes))
    speeds = rng.uniform(2.0, 7.0, len(scenes))
    ref = np.stack([expert_command(p, ExpertObstacles.from_scene(s), v, config)
                    for p, s, v in zip(pos, scenes, speeds, strict=True)])
    got = expert_commands(torch.tensor(pos), torch.tensor(speeds), scene_batch(scenes), config).numpy()
    assert np.abs(got - ref).max() <= 1e-12
    assert len({tuple(np.round(c, 6)) for c in ref}) > len(scenes) // 2  # varied answers, fallback included or not


def test_expert_fallback_and_ties_by_hand():
    # a sphere 4 m straight ahead: the four nearest free waypoints tie, "up" wins (the numpy docstring's case)
    sphere = Scene("spheres", "test", 0, np.array([[14.0, 0.0, 3.5, 1.0]]), np.zeros((0, 5)), np.zeros((0, 6)))
    wall = Scene("spheres", "test", 0, np.array([[11.0, 0.0, 3.5, 30.0]]), np.zeros((0, 5)), np.zeros((0, 6)))
    cmd = expert_commands(torch.tensor([[10.0, 0.0, 3.5], [1.0, 0.0, 1.0]]), torch.tensor([5.0, 5.0]),
                          scene_batch([sphere, wall]), ALL_SEEING).numpy()
    np.testing.assert_allclose(cmd[0], [4.5808, 0.0, 2.0041], atol=1e-4)
    np.testing.assert_allclose(cmd[1], [2.5, 0.0, 2.0])  # inside: fallback, then altitude floor and ramp


def test_expert_sees_the_ten_nearest_ties_in_scene_order():
    # twelve spheres 5 m from the drone along the axes (exactly tied distances) and one nearer, last: the
    # nearer one and the first nine of the twelve in scene order, as a stable sort by distance keeps them
    near = np.array([[12.0, 0.0, 3.5, 0.5]])
    ring = np.array([[10.0 + dx, dy, 3.5, 0.5] for dx, dy in
                     [(5, 0), (0, 5), (-5, 0), (0, -5), (5, 0), (0, 5), (-5, 0), (0, -5), (5, 0), (0, 5),
                      (-5, 0), (0, -5)]])
    scene = Scene("spheres", "test", 0, np.concatenate([ring, near]), np.zeros((0, 5)), np.zeros((0, 6)))
    seen = visible_cover(torch.tensor([[10.0, 0.0, 3.5]]), scene_batch([scene]), ExpertConfig())[0].numpy()
    assert seen.tolist() == [True] * 9 + [False] * 3 + [True]


@pytest.mark.parametrize("vectorised", [False, True], ids=["scalar_kernel", "array_kernel"])
def test_controller_and_physics_equal_the_native_back_end(vectorised):
    n, af, gains = 4, Airframe(), ControllerGains()
    rng = np.random.default_rng(2)
    fleet = NativeFleet(n, af, 240.0, vectorised=vectorised)
    start = np.tile([0.0, 0.0, 3.5], (n, 1))
    fleet.reset(start)
    states = fleet.states()
    state = hover_state(torch.tensor(start), af)
    worst = dict.fromkeys(("position_m", "attitude_rad", "velocity_mps", "body_rates_radps"), 0.0)
    for _ in range(60):  # 2 s of random commands at 30 Hz
        cmd = rng.uniform([-2.0, -3.0, -2.0], [7.0, 3.0, 2.0], (n, 3))
        rows = [tuple(c) for c in cmd.tolist()]
        for _ in range(8):
            states = fleet.track(rows, states, gains)
            state = physics_step(state, velocity_control(torch.tensor(cmd), state, af, gains), af, 1 / 240)
        mine = torch.cat([state.position, state.quat, state.velocity, state.body_rates], 1).numpy()
        gaps = state_gaps(state_array(states), mine)
        worst = {k: max(worst[k], gaps[k]) for k in worst}
    assert max(worst.values()) <= 1e-9, worst
    rot = np.array([s.rotation for s in states]).reshape(n, 3, 3)
    assert np.abs(state.rotation.numpy() - rot).max() <= 1e-9


def assert_same_episodes(ref, got, worst: dict):
    """Same outcomes, contacts, commands and labels; states, commands and depth within TOL_M (updates ``worst``)."""
    for a, b in zip(ref, got, strict=True):
        sa, sb = a.summary.to_dict(), b.summary.to_dict()
        fp_a, fp_b = sa.pop("final_position"), sb.pop("final_position")
        assert sa == sb
        assert np.abs(np.subtract(fp_a, fp_b)).max() <= TOL_M
        assert len(a.log) == len(b.log) and np.array_equal(a.log.time, b.log.time)
        assert np.array_equal(a.log.contact, b.log.contact)
        for name in ("position", "velocity", "quat", "command", "label", "depth"):
            x, y = getattr(a.log, name), getattr(b.log, name)
            assert (x is None) == (y is None), name
            if x is not None:
                gap = float(np.abs(x.astype(np.float64) - y.astype(np.float64)).max())
                worst[name] = max(worst.get(name, 0.0), gap)
                assert gap <= (TOL_M / 10.0 if name == "depth" else TOL_M), (name, gap)


def short_config(**task):
    return RolloutConfig(physics="native", task=TaskConfig(timeout_speed_factor=0.0, **task))


def short_scenes(env):
    """Three scenes and a start 12 m short of their obstacles: 2.5 s flights meet them."""
    if env == "window":  # three walls near x = 24.6 m
        scenes = sorted((make_scene(env, "medium", s) for s in range(60)), key=lambda s: abs(s.boxes[0, 0] - 25.0))
        return scenes[:3], (20.0, 0.0, 3.5)
    return [make_scene(env, "hard", s) for s in range(3)], (8.0, 0.0, 3.5)


@pytest.mark.parametrize("policy", [ExpertPolicy, StraightPolicy])
@pytest.mark.parametrize("env", ENVS)
def test_short_episodes_equal_the_numpy_engine(env, policy):
    scenes, start = short_scenes(env)
    cfg = dataclasses.replace(short_config(timeout_s=2.5, start=start), record_depth=True)
    ref = run_episodes(scenes, [7.0, 5.0, 3.0], policy(), cfg)
    got = run_batched(scenes, [7.0, 5.0, 3.0], policy(), cfg)
    assert_same_episodes(ref, got, {})
    if policy is StraightPolicy or env == "spheres":  # collisions happen (and are counted alike)
        assert sum(r.summary.n_collisions for r in got) >= 1


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                    reason="torch.compile on the CPU needs a C++ compiler")
def test_compiled_engine_equals_the_numpy_engine():
    # the fast path the benchmarks time: every kernel through torch.compile (inductor), still float64
    scenes, start = short_scenes("spheres")
    cfg = dataclasses.replace(short_config(timeout_s=2.5, start=start), record_depth=True)
    ref = run_episodes(scenes, [7.0, 5.0, 3.0], ExpertPolicy(), cfg)
    got = run_batched(scenes, [7.0, 5.0, 3.0], ExpertPolicy(), cfg, settings=BatchedSettings(compile=True))
    assert_same_episodes(ref, got, {})
    assert sum(r.summary.n_collisions for r in got) >= 1


def test_contact_goal_bounds_and_body_radius_equal_the_numpy_engine():
    # straight flight: through a sphere (a collision), grazing one 5 cm off (contact only with a body
    # radius), out of bounds over the ceiling, and to a goal 5 m ahead
    grazing = Scene("spheres", "test", 1, np.array([[4.0, 1.05, 3.5, 1.0]]), np.zeros((0, 5)), np.zeros((0, 6)))
    through = Scene("spheres", "test", 2, np.array([[4.0, 0.0, 3.5, 1.0]]), np.zeros((0, 5)), np.zeros((0, 6)))
    trunk = Scene("trees", "test", 3, np.zeros((0, 4)), np.array([[4.0, 0.0, 0.0, 5.0, 0.3]]), np.zeros((0, 6)))
    box = Scene("window", "test", 4, np.zeros((0, 4)), np.zeros((0, 5)), np.array([[4.0, -1.0, 0.0, 4.3, 1.0, 9.0]]))
    scenes = [grazing, through, trunk, box]
    for radius in (0.0, 0.125):
        cfg = short_config(timeout_s=2.0, goal_x_m=5.0, body_radius_m=radius)
        ref = run_episodes(scenes, [4.0] * 4, StraightPolicy(), cfg)
        got = run_batched(scenes, [4.0] * 4, StraightPolicy(), cfg)
        assert_same_episodes(ref, got, {})
        assert [r.summary.n_collisions for r in got] == [int(radius > 0), 1, 1, 1]
    climb = short_config(timeout_s=3.0, bounds_max=(65.0, 10.0, 4.0))
    up = _Climb()
    got = run_batched([through], [4.0], up, climb)
    assert got[0].summary.end_reason == "out_of_bounds"
    assert_same_episodes(run_episodes([through], [4.0], _Climb(), climb), got, {})


class _Climb:
    """A numpy policy (runs through the batched engine's adapter) that climbs at 3 m/s; needs depth."""

    needs_depth = True

    def reset(self, num_envs):
        self.n = num_envs

    def __call__(self, obs):
        assert obs.depth.dtype == np.float32 and obs.depth.shape == (self.n, 60, 90)
        return np.tile([1.0, 0.0, 3.0], (self.n, 1))


def test_labelled_numpy_policy_and_camera_noise_equal_the_numpy_engine():
    scenes = [make_scene("spheres", "medium", s) for s in range(3)]
    camera = CameraConfig(noise_std_m=0.02, dropout_prob=0.05)
    cfg = dataclasses.replace(short_config(timeout_s=1.5), camera=camera, record_depth=True)

    def mixture():
        return MixturePolicy(ExpertPolicy(), StraightPolicy(), beta=0.5, seeds=3)

    ref = run_episodes(scenes, [5.0] * 3, mixture(), cfg, camera_seed=9)
    got = run_batched(scenes, [5.0] * 3, NumpyPolicy(mixture()), cfg, camera_seed=9)  # the host adapter's labels
    assert got[0].log.label is not None
    assert_same_episodes(ref, got, {})
    # the device's own generator: same pixels dropped out as often, other draws
    torch_noise = run_batched(scenes, [5.0] * 3, mixture(), cfg, camera_seed=9,
                              settings=BatchedSettings(noise_source="torch"))
    dropped = np.mean(torch_noise[0].log.depth == 0)
    assert 0.03 < dropped < 0.07


def test_a_mixture_with_a_learned_student_equals_the_numpy_engine():
    # DAgger's flights: the expert and a recurrent student, one of them per env and tick; on the batched engine
    # both run as tensor code (BatchedMixture, the network's own path) with the numpy mixture's draws and counts
    from vitfly.eval.learned_policy import LearnedPolicy
    from vitfly.zoo import create_model

    torch.manual_seed(1)
    net = create_model("lstmnet")
    scenes = [make_scene("spheres", "medium", s) for s in range(3)]
    cfg = short_config(timeout_s=2.0, goal_x_m=8.0)

    def mixture():
        return MixturePolicy(ExpertPolicy(), LearnedPolicy(net), beta=0.5, seeds=[[0, 1, k] for k in range(3)])

    ref_mix, got_mix = mixture(), mixture()
    assert isinstance(as_batched_policy(got_mix), BatchedMixture)
    ref = run_episodes(scenes, [7.0, 5.0, 3.0], ref_mix, cfg)
    got = run_batched(scenes, [7.0, 5.0, 3.0], got_mix, cfg)
    assert_same_episodes(ref, got, {})
    assert len({len(r.log) for r in got}) > 1  # episodes end on different ticks: the draws follow who flies
    np.testing.assert_array_equal(got_mix.ticks, [len(r.log) for r in got])
    np.testing.assert_array_equal(got_mix.expert_ticks, ref_mix.expert_ticks)
    for r, flown_by_expert in zip(got, got_mix.expert_ticks, strict=True):  # each flew both, the labels always
        student_ticks = np.any(r.log.command != r.log.label, axis=1).sum()
        assert 0 < flown_by_expert and student_ticks == len(r.log) - flown_by_expert


def test_float32_runs_close_to_float64():
    scenes = [make_scene("spheres", "medium", s) for s in range(2)]
    cfg = short_config(timeout_s=1.0)
    a = run_batched(scenes, [5.0] * 2, ExpertPolicy(), cfg)
    b = run_batched(scenes, [5.0] * 2, ExpertPolicy(), cfg, settings=BatchedSettings(dtype=torch.float32))
    assert np.abs(a[0].log.position - b[0].log.position).max() < 1e-3


def test_depth_is_differentiable_in_the_pose_and_the_obstacles():
    cfg = CameraConfig(height=4, width=6, render_ground=False)
    # a sphere up left, a trunk below right, a wall up right
    scene = Scene("trees", "test", 0, np.array([[4.0, 1.5, 4.8, 1.5]]), np.array([[3.5, -1.0, 0.0, 3.4, 0.5]]),
                  np.array([[4.0, -5.0, 3.8, 4.4, -0.5, 9.0]]))
    batch = scene_batch([scene])
    camera = BatchedCamera(cfg)

    def depth(position, quat, spheres, cylinders, boxes):
        rot = quat_to_rotation(quat / quat.norm(dim=-1, keepdim=True))
        b = batch.replace(spheres=spheres, cylinders=cylinders, boxes=boxes)
        return camera.render(b, position, rot)

    inputs = (torch.tensor([[0.0, 0.0, 3.6]], dtype=F64), torch.tensor([[1.0, 0.01, -0.02, 0.02]], dtype=F64),
              batch.spheres.clone(), batch.cylinders.clone(), batch.boxes.clone())
    inputs = tuple(t.requires_grad_() for t in inputs)
    out = depth(*inputs)
    assert ((out > 0) & (out < 1)).sum() >= 10  # 11 of the 24 pixels see one of the three shapes
    assert torch.autograd.gradcheck(depth, inputs, eps=1e-7, atol=1e-6)


def test_dynamics_are_differentiable_in_the_commands():
    af, gains = Airframe(), ControllerGains()
    start = hover_state(torch.tensor([[0.0, 0.0, 3.5], [1.0, 0.5, 2.0]], dtype=F64), af)

    def fly(command):
        state = start
        for _ in range(2):
            state = physics_step(state, velocity_control(command, state, af, gains), af, 1 / 240)
        return torch.cat([state.position, state.quat, state.velocity, state.body_rates, state.rotor], 1)

    command = torch.tensor([[3.0, 0.5, -0.2], [0.0, 0.0, 0.0]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(fly, (command,), eps=1e-6, atol=1e-7)


@pytest.mark.slow
def test_whole_expert_episodes_equal_the_numpy_engine():
    # every family's scenes in one lockstep batch (a batch holds every kind of obstacle), each family at 3, 4, 5
    # and 7 m/s: 16 whole episodes, the longest 905 ticks (eager: about 40 s here, twice that for 8 a family)
    per_family = 4
    scenes = [make_scene(env, "medium", 100 + s) for env in ENVS for s in range(per_family)]
    speeds = [3.0, 5.0, 7.0, 4.0] * (per_family // 4) * len(ENVS)
    cfg = RolloutConfig(physics="native", record_depth=True)
    ref, got = run_episodes(scenes, speeds, ExpertPolicy(), cfg), run_batched(scenes, speeds, ExpertPolicy(), cfg)
    for i, env in enumerate(ENVS):
        worst: dict = {}
        family = slice(per_family * i, per_family * (i + 1))
        assert_same_episodes(ref[family], got[family], worst)
        print(env, worst)
    assert sum(r.summary.n_collisions for r in got) >= 1  # contacts are compared too
