"""The modular baselines (vitfly.planners): worked cases per stage, the latency rule, options, one real flight."""

import json
import math

import numpy as np
import pytest

from vitfly.cli import main
from vitfly.errors import VitflyError
from vitfly.eval.fingerprint import policy_fingerprint
from vitfly.eval.policy_source import PolicySource
from vitfly.planners import ModularPolicy, PlannerOptions, load_planner_options
from vitfly.planners.convex import ConvexSettings, carve_free_polytope, convex_plan
from vitfly.planners.mapping import LocalMap
from vitfly.planners.perception import depth_to_world_points
from vitfly.planners.search import SearchSettings, kinodynamic_search
from vitfly.planners.trajectory import Plan
from vitfly.sim.camera import CameraConfig, DepthCamera
from vitfly.sim.quadrotor import quat_wxyz_to_matrix
from vitfly.sim.rollout import Observation
from vitfly.sim.scenes import Scene

CAMERA = CameraConfig()
START = np.array([0.0, 0.0, 3.5])


def rot_z(deg):
    a = math.radians(deg)
    return quat_wxyz_to_matrix(np.array([math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)]))[0]


def rot_x(deg):
    a = math.radians(deg)
    return quat_wxyz_to_matrix(np.array([math.cos(a / 2), math.sin(a / 2), 0.0, 0.0]))[0]


def test_flat_wall_comes_back_at_its_distance_in_any_pose():
    depth = np.full((60, 90), 0.5, dtype=np.float32)  # planar depth 5 m everywhere
    level = depth_to_world_points(depth, START, np.eye(3), CAMERA)
    assert level.shape == (60 * 90, 3)
    np.testing.assert_allclose(level[:, 0], 5.3)  # 0.3 m camera mount + 5 m
    # the top-left pixel looks up (+z) and left (+y)
    assert level[0, 1] > 0 and level[0, 2] > START[2]
    yawed = depth_to_world_points(depth, START, rot_z(90.0), CAMERA)  # body x now along world +y
    np.testing.assert_allclose(yawed[:, 1], 5.3)
    np.testing.assert_allclose(yawed[:, 0], -level[:, 1], atol=1e-12)  # body left (+y) is world -x
    np.testing.assert_allclose(yawed[:, 2], level[:, 2], atol=1e-12)
    rolled = depth_to_world_points(depth, START, rot_x(90.0), CAMERA)  # body z (image up) now along world -y
    np.testing.assert_allclose(rolled[:, 0], 5.3)
    assert rolled[0, 1] < 0 and rolled[0, 2] > START[2]  # top row -> world -y; left column -> world +z


def test_rendered_wall_back_projects_onto_its_face_and_drops_empty_pixels():
    wall = Scene("window", "custom", 0, np.zeros((0, 4)), np.zeros((0, 5)), np.array([[6.0, -1.0, 3.0, 7.0, 1.0, 4.0]]))
    camera = CameraConfig(render_ground=False)
    for rotation in (np.eye(3), rot_z(10.0) @ rot_x(15.0)):
        depth = DepthCamera(camera).render(wall, START, rotation)
        points = depth_to_world_points(depth, START, rotation, camera)
        assert len(points) == int(np.sum(depth < 1)) > 0  # one point per pixel that hit the box
        np.testing.assert_allclose(points[:, 0], 6.0, atol=1e-4)  # its near face, x = 6 m
        assert np.all(np.abs(points[:, 1]) <= 1.0 + 1e-4)
        assert np.all((points[:, 2] >= 3.0 - 1e-4) & (points[:, 2] <= 4.0 + 1e-4))
    depth = np.zeros((60, 90), dtype=np.float32)  # no reading anywhere
    depth[0, 0] = 1.0  # nothing within range
    assert len(depth_to_world_points(depth, START, np.eye(3), camera)) == 0


def test_map_remembers_an_obstacle_out_of_view_then_forgets_it():
    local_map = LocalMap(voxel_m=0.2, memory_s=2.0, behind_m=1.0)
    obstacle = np.array([[5.0, 3.0, 3.5], [5.05, 3.05, 3.5]])  # one voxel
    local_map.insert(obstacle, 0.0, START)
    assert len(local_map) == 1
    for k in range(1, 30):  # it left the field of view: frames see nothing
        local_map.insert(np.zeros((0, 3)), k / 30, START + [0.1 * k, 0, 0])
    assert local_map.distance_m(np.array([5.0, 3.0, 3.5])) < 0.1
    assert local_map.distance_m(np.array([[0.0, 0.0, 0.0]]), upper_bound_m=1.0)[0] == np.inf
    local_map.insert(np.zeros((0, 3)), 2.5, START)  # older than memory_s
    assert len(local_map) == 0
    local_map.insert(obstacle, 3.0, START)
    local_map.insert(np.zeros((0, 3)), 3.1, [6.5, 0.0, 3.5])  # more than behind_m behind the drone
    assert len(local_map) == 0


def gap_wall(x_m=3.0, gap_y=(1.5, 4.0)):
    """A wall of points at x = x_m, y in [-6, 6], z in [0.5, 7], with an opening at gap_y for all z."""
    y, z = np.meshgrid(np.arange(-6.0, 6.0001, 0.1), np.arange(0.5, 7.0001, 0.1))
    keep = (y < gap_y[0]) | (y > gap_y[1])
    return np.stack([np.full(keep.sum(), x_m), y[keep], z[keep]], axis=1)


def test_kinodynamic_search_flies_through_the_gap():
    local_map = LocalMap()
    local_map.insert(gap_wall(), 0.0, START)
    settings = SearchSettings(primitive_s=0.6)
    plan = kinodynamic_search(local_map, START, [2.0, 0.0, 0.0], (1.0, 0.0, 0.0), settings)
    assert plan is not None and plan.position_m[-1, 0] > 3.3, "the plan crosses the wall"
    crossing = plan.position_m[np.argmin(np.abs(plan.position_m[:, 0] - 3.0))]
    assert 1.5 + 0.6 <= crossing[1] <= 4.0 - 0.6
    assert local_map.distance_m(plan.position_m).min() >= settings.margin_m - 1e-9
    assert np.linalg.norm(plan.velocity_mps, axis=1).max() <= settings.speed_mps + 1e-6


def test_convex_region_holds_the_seed_and_no_point_and_the_command_aims_at_the_gap():
    points = gap_wall()
    a, c = carve_free_polytope(points, START, START + [4.0, 4.0, 0.0], 0.6, 1000)
    # every point lies outside (beyond some face); the seed segment lies inside
    assert np.all(np.any(points @ a.T >= c + 1e-9, axis=1))
    segment = START + np.linspace(0, 1, 11)[:, None] * [4.0, 4.0, 0.0]
    assert np.all(segment @ a.T <= c[None] + 1e-9)
    local_map = LocalMap()
    local_map.insert(points, 0.0, START)
    plan = convex_plan(local_map, START, [0.0, 0.0, 0.0], (1.0, 0.0, 0.0), ConvexSettings())
    v = plan.velocity_mps[0]
    assert v[0] > 0
    y_at_wall = START[1] + v[1] / v[0] * 3.0
    assert 1.5 < y_at_wall < 4.0  # heading into the opening, not into the wall


def observation(t, tick):
    return Observation(depth=np.ones((1, 60, 90), dtype=np.float32), desired_speed=np.array([3.0]),
                       quat=np.array([[1.0, 0, 0, 0]]), position=START[None].copy(), velocity=np.zeros((1, 3)),
                       obstacles=[np.zeros((0, 4))], active=np.array([True]), time=np.array([t]), tick=tick)


def test_a_plan_is_used_only_once_its_latency_has_passed():
    policy = ModularPolicy(PlannerOptions(fixed_latency_s=0.25, replan_hz=10.0, position_gain_per_s=0.0))
    started = []

    def fake_plan(local_map, position, velocity):  # plan k flies at k m/s
        started.append(len(started) + 1)
        speed = float(len(started))
        path = np.stack([position, position + [speed, 0, 0]])
        return Plan(np.array([0.0, 1.0]), path, np.tile([speed, 0, 0], (2, 1)))

    policy.plan = fake_plan
    policy.reset(1)
    commands = {}
    for tick in range(24):  # 30 Hz, 0.8 s
        t = tick / 30
        commands[tick] = policy(observation(t, tick))[0, 0]
    # plan 1 started at t = 0, ready at 0.25 s: hover until tick 8 (0.267 s), then plan 1
    assert all(commands[k] == 0.0 for k in range(8))
    # no replan while one is pending (the 10 Hz replans at ticks 3 and 6 wait): plan 2 starts at tick 8,
    # when plan 1 is taken up, and is ready at 0.517 s (tick 16)
    assert all(commands[k] == 1.0 for k in range(8, 16))
    assert commands[16] == 2.0
    assert len(started) == 3  # plan 3 started at tick 16, still pending at tick 23


def test_measured_latency_delays_the_plan():
    import time

    policy = ModularPolicy(PlannerOptions(replan_hz=10.0, position_gain_per_s=0.0))

    def slow_plan(local_map, position, velocity):
        # 50 ms of the planning thread's CPU time (what the rule measures; a sleep costs none): over one 30 Hz tick
        end = time.thread_time() + 0.05
        while time.thread_time() < end:
            pass
        return Plan(np.array([0.0, 1.0]), np.stack([position, position + [1, 0, 0]]), np.tile([1.0, 0, 0], (2, 1)))

    policy.plan = slow_plan
    policy.reset(1)
    assert policy(observation(0.0, 0))[0, 0] == 0.0
    assert policy(observation(1 / 30, 1))[0, 0] == 0.0  # 33 ms later: not finished in simulated time
    assert policy.replan_ms[0] >= 50.0
    assert any(policy(observation(k / 30, k))[0, 0] == 1.0 for k in range(2, 30))


def test_bad_planner_options_are_one_clear_line(tmp_path):
    path = tmp_path / "planners.yaml"
    cases = {
        "fastplanner: {method: fastplanner, replan_hz: fast}": "field 'replan_hz' must be float",
        "fastplanner: {method: astar}": "field 'method' is 'astar'",
        "fastplanner: {search: {beam_widht: 3}}": "unknown field 'search.beam_widht'",
        "fastplanner: {search: {home_yz_m: [1, 2, 3]}}": "field 'search.home_yz_m' must be a list of 2 numbers",
        "common: {replan_hz: -1}\nfastplanner: {}": "field 'replan_hz' must be > 0",
        "convex: {}": "no planner 'fastplanner'",
        "fastplanner: {search: {speed_mps: 5}}": "'search.speed_mps' is set by 'design_speed_mps'",
        "fastplanner: {map: {voxel_m: 0}}": "field 'map.voxel_m' must be > 0",
    }
    for text, expected in cases.items():
        path.write_text(text)
        with pytest.raises(VitflyError, match=expected) as err:
            load_planner_options("fastplanner", path)
        assert "\n" not in str(err.value) and str(path) in str(err.value)
    path.write_text("common: {replan_hz: 5}\nfastplanner: {search: {beam_width: 8}}\n")
    options = load_planner_options("fastplanner", path)
    assert options.replan_hz == 5.0 and options.search.beam_width == 8 and options.method == "fastplanner"
    assert load_planner_options("convex_scaled").scaled


def test_options_and_code_version_key_the_trials(tmp_path):
    path = tmp_path / "planners.yaml"
    path.write_text("fastplanner: {search: {beam_width: 8}}\n")
    shipped = policy_fingerprint(PolicySource("modular:fastplanner"))
    assert shipped == policy_fingerprint(PolicySource("modular:fastplanner"))
    assert shipped != policy_fingerprint(PolicySource("modular:fastplanner", planner_config=str(path)))
    assert shipped != policy_fingerprint(PolicySource("modular:fastplanner_scaled"))


def test_vitfly_evaluate_flies_a_modular_planner(tmp_path, capsys):
    out = tmp_path / "eval"
    args = ["evaluate", "--policy", "modular:fastplanner", "--speeds", "3", "--trials", "1", "--seed", "3",
            "--timeout", "2.5", "--out", str(out), "--no-gif", "--no-plots", "--no-progress", "--physics", "native"]
    assert main(args) == 0
    [record] = [json.loads(line) for line in (out / "trials.jsonl").read_text().splitlines()]
    assert record["policy"] == "fastplanner" and record["extra"]["policy_source"] == "modular:fastplanner"
    x = [p[0] for p in record["path"]["position"]]
    assert x[-1] > 2.5, "it flew forward"
    assert main([*args[:2], "modular:nope", *args[3:]]) == 2
    assert "no planner 'nope'" in capsys.readouterr().err


def ball_ahead(centre_x_m=0.95, radius_m=0.5):
    """Points on a sphere of radius 0.5 m centred 0.95 m ahead of START (a Fibonacci lattice of 400, and its
    pole toward the drone, (0.45, 0, 3.5)): the nearest point is 0.45 m away."""
    k = np.arange(400) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / 400), np.pi * (1 + 5**0.5) * k
    unit = np.stack([np.cos(polar), np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth)], axis=1)
    return START + [centre_x_m, 0, 0] + radius_m * np.vstack([unit, [[-1.0, 0.0, 0.0]]])


def test_a_drone_that_braked_inside_the_margin_plans_its_way_out():
    # the stall of issue 24: braking for an obstacle seen late left the drone 0.45 m from it, inside the
    # 0.6 m margin; every primitive (every seed) then "collided" and the drone held position there until
    # the timeout
    local_map = LocalMap(voxel_m=0.01)  # fine voxels: every point of the ball kept
    local_map.insert(ball_ahead(), 0.0, START)
    start_clearance = float(local_map.distance_m(START))
    assert start_clearance == pytest.approx(0.45)
    settings = SearchSettings()
    plan = kinodynamic_search(local_map, START, [0.0, 0.0, 0.0], (1.0, 0.0, 0.0), settings)
    assert plan is not None and not plan.stop
    clearance = local_map.distance_m(plan.position_m)
    assert clearance.min() >= start_clearance - 1e-9  # never closer than it started
    assert clearance[-1] > settings.margin_m and plan.position_m[-1, 0] > 1.45  # out of the margin, past the ball
    convex = convex_plan(local_map, START, [0.0, 0.0, 0.0], (1.0, 0.0, 0.0), ConvexSettings())
    assert convex is not None and not convex.stop
    assert local_map.distance_m(convex.position_m[:5]).min() >= start_clearance - 1e-9  # its first 0.2 s


def test_a_drone_outside_the_box_flies_on():
    # y = 9.6 m is 0.6 m past the planners' |y| <= 9 m box (a drift while avoiding): an empty map, no reason
    # to stop; before the escape rule every primitive and every seed "left the box"
    local_map = LocalMap()
    start = np.array([20.0, 9.6, 3.5])
    plan = kinodynamic_search(local_map, start, [0.0, 0.0, 0.0], (1.0, 0.0, 0.0), SearchSettings())
    assert plan is not None and not plan.stop
    assert np.abs(plan.position_m[:, 1]).max() <= 9.6 + 1e-9  # never further out than it started
    assert plan.position_m[-1, 0] > start[0] + 1.0  # on along the course
    convex = convex_plan(local_map, start, [0.0, 0.0, 0.0], (1.0, 0.0, 0.0), ConvexSettings())
    assert convex is not None and convex.velocity_mps[0, 0] > 0 and convex.velocity_mps[0, 1] <= 0
