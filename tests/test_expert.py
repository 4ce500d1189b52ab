"""The privileged expert against hand-worked answers and a plain-loop reference."""

import itertools
import math

import numpy as np
import pytest

from vitfly.sim.expert import (
    ALL_SEEING,
    ExpertConfig,
    ExpertObstacles,
    blocked_waypoints,
    expert_command,
    visible_obstacles,
    waypoint_grid,
)
from vitfly.sim.scenes import Scene

CRUISE = np.array([10.0, 0.0, 3.5])  # past the take-off ramp, above the altitude floor


def unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def test_grid_is_33_by_33_half_metre_steps_8m_ahead():
    wpts, manhattan = waypoint_grid(ExpertConfig())
    assert wpts.shape == (33, 33, 3)
    assert np.all(wpts[..., 0] == 8.0)
    assert wpts[0, 0, 1] == 8.0 and wpts[0, 0, 2] == 8.0  # top-left: left and up
    assert wpts[16, 16, 1] == 0.0 and wpts[16, 16, 2] == 0.0
    assert wpts[0, 1, 1] == 7.5
    assert manhattan[16, 16] == 0 and manhattan[0, 0] == 32 and manhattan[16, 20] == 4


def test_no_obstacles_flies_straight_at_desired_speed():
    np.testing.assert_allclose(expert_command(CRUISE, np.zeros((0, 4)), 5.0), [5.0, 0.0, 0.0])


def test_sphere_dead_ahead_is_passed_over_with_hand_worked_offset():
    # sphere r = 1 m 4 m ahead, inflated to 1.6 m. The line to (8, s, 0) passes the centre at
    # 4 s / sqrt(64 + s^2); free when > 1.6, i.e. s > 3.49 m, so the nearest free waypoints are 3.5 m
    # off-centre on the axes (Manhattan 7), and the tie goes to the first in row-major order: up.
    cmd = expert_command(CRUISE, np.array([[14.0, 0.0, 3.5, 1.0]]), 5.0)
    np.testing.assert_allclose(cmd, unit([8.0, 0.0, 3.5]) * 5.0)
    assert np.linalg.norm(cmd) == pytest.approx(5.0)


def test_lateral_tie_goes_left():
    # a dense vertical column of spheres (inflated radius 1.0 m) 4 m ahead. The line to (8, y, 0)
    # passes the nearest centre at 4 |y| / sqrt(64 + y^2): 0.97 m for y = 2 (blocked), 1.19 m for
    # y = 2.5 (free); off the z = 0 row the column is just as close. Nearest free: y = +-2.5, z = 0,
    # a tie at equal Manhattan distance that goes to the left (+y), first in row-major order.
    # (All-seeing: the 10-nearest selection would cut the column to |dz| <= 2.5 m.)
    column = np.array([[14.0, 0.0, 3.5 + z, 0.4] for z in np.arange(-12.0, 12.5, 0.5)])
    cmd = expert_command(CRUISE, column, 4.0, ALL_SEEING)
    np.testing.assert_allclose(cmd, unit([8.0, 2.5, 0.0]) * 4.0)


def test_obstacles_behind_or_beyond_8m_are_ignored():
    obstacles = np.array([[9.0, 0.0, 3.5, 0.5], [18.5, 0.0, 3.5, 1.5], [10.0, 0.0, 3.5, 0.3]])
    # dx = -1 (behind), 8.5 (beyond the plane), 0 (not strictly ahead)
    np.testing.assert_allclose(expert_command(CRUISE, obstacles, 3.0), [3.0, 0.0, 0.0])


def test_blocking_uses_the_infinite_line_not_the_segment():
    # an obstacle beside the drone, 3 m to the right and just ahead. For the waypoint (8, 8, 0) up-left,
    # the closest point of the infinite line lies BEHIND the drone at 2.19 m from the centre; the
    # segment's closest point is the drone itself, 3.0 m away. Inflated radius 1.8 + 0.6 = 2.4.
    rel = np.array([[0.1, -3.0, 0.0, 1.8]])
    blocked = blocked_waypoints(rel, ExpertConfig())
    wpts, _ = waypoint_grid(ExpertConfig())
    i, j = np.argwhere((wpts[..., 1] == 8.0) & (wpts[..., 2] == 0.0))[0]
    d = unit(wpts[i, j])
    line_dist = np.linalg.norm(rel[0, :3] - (rel[0, :3] @ d) * d)
    assert line_dist == pytest.approx(24.8 / math.hypot(8, 8))
    assert line_dist < 2.4 < np.linalg.norm(rel[0, :3])
    assert blocked[i, j]


def test_fallback_when_everything_is_blocked():
    huge = np.array([[14.0, 0.0, 3.5, 30.0]])
    np.testing.assert_allclose(expert_command(CRUISE, huge, 6.0), [0.5, 0.0, 0.25])


def test_altitude_floor_then_takeoff_ramp_override():
    free = np.zeros((0, 4))
    # below 2 m: vz = 2 (2 - z), whatever the waypoint said
    np.testing.assert_allclose(expert_command([10.0, 0.0, 1.0], free, 5.0), [5.0, 0.0, 2.0])
    # x < 2: vx = max(1, x / 2 * speed)
    np.testing.assert_allclose(expert_command([1.0, 0.0, 3.5], free, 5.0), [2.5, 0.0, 0.0])
    np.testing.assert_allclose(expert_command([0.2, 0.0, 3.5], free, 5.0), [1.0, 0.0, 0.0])
    # both, and on top of the fallback
    huge = np.array([[4.0, 0.0, 1.5, 30.0]])
    np.testing.assert_allclose(expert_command([1.0, 0.0, 1.5], huge, 4.0), [2.0, 0.0, 1.0])


def test_config_constants_are_used():
    cfg = ExpertConfig(inflate_m=0.0)
    # without inflation the sphere of the hand-worked case frees waypoints at s > 2.07 m: s = 2.5 m
    cmd = expert_command(CRUISE, np.array([[14.0, 0.0, 3.5, 1.0]]), 5.0, cfg)
    np.testing.assert_allclose(cmd, unit([8.0, 0.0, 2.5]) * 5.0)


def reference_expert(position, obstacles, speed, max_obstacles=10, max_range=10.0):
    """The specification as plain loops: Flightmare's selection (sort every obstacle by centre
    distance, keep the first ``max_obstacles`` within ``max_range``), then a row-major scan in which
    the first nearest free waypoint wins."""
    ranked = sorted(obstacles.tolist(), key=lambda o: np.linalg.norm(np.array(o[:3]) - position))
    if max_range is not None:
        ranked = [o for o in ranked if np.linalg.norm(np.array(o[:3]) - position) <= max_range]
    if max_obstacles is not None:
        ranked = ranked[:max_obstacles]
    offsets = [8.0 - 0.5 * k for k in range(33)]
    best = None
    for (i, z), (j, y) in itertools.product(enumerate(offsets), enumerate(offsets)):
        w = np.array([8.0, y, z])
        free = True
        for ox, oy, oz, r in ranked:
            c = np.array([ox, oy, oz]) - position
            if not 0 < c[0] < 8:
                continue
            dist = np.linalg.norm(np.cross(c, w)) / np.linalg.norm(w)
            if dist <= r + 0.6:
                free = False
                break
        manhattan = abs(i - 16) + abs(j - 16)
        if free and (best is None or manhattan < best[0]):
            best = (manhattan, w)
    cmd = np.array([0.5, 0.0, 0.25]) if best is None else unit(best[1]) * speed
    if position[2] < 2:
        cmd[2] = 2 * (2 - position[2])
    if position[0] < 2:
        cmd[0] = max(1.0, position[0] / 2 * speed)
    return cmd


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("limits", [(10, 10.0), (None, None), (4, None), (None, 7.0)])
def test_vectorised_expert_matches_plain_loops(seed, limits):
    rng = np.random.default_rng(seed)
    position = np.array([rng.uniform(0, 30), rng.uniform(-2, 2), rng.uniform(1, 5)])
    obstacles = np.column_stack(
        [
            position[0] + rng.uniform(-2, 10, 25),
            position[1] + rng.uniform(-6, 6, 25),
            position[2] + rng.uniform(-5, 5, 25),
            rng.uniform(0.3, 1.5, 25),
        ]
    )
    cfg = ExpertConfig(max_obstacles=limits[0], max_range_m=limits[1])
    np.testing.assert_allclose(
        expert_command(position, obstacles, 4.5, cfg), reference_expert(position, obstacles, 4.5, *limits)
    )


# -- what the expert sees: Flightmare's 10 nearest obstacles within 10 m ----------------------------

# Ten small spheres BEHIND the drone (dx < 0, so the waypoint test ignores them), 1..5 m away: they
# are still the nearest and fill Flightmare's ten slots.
BEHIND = np.array([[10.0 - 0.5 * (k + 1), 0.0, 3.5 + (0.3 if k % 2 else -0.3), 0.1] for k in range(10)])
# 11th nearest: r = 1 m, 6 m straight ahead (centre distance 6). 12th: off the path, 9 m away.
BLOCKER = np.array([[16.0, 0.0, 3.5, 1.0]])
FAR_SIDE = np.array([[13.0, 8.485, 3.5, 0.3]])  # distance sqrt(9 + 72) = 9.0 m, 8.5 m to the side


def test_the_eleventh_nearest_obstacle_is_not_seen():
    obstacles = np.concatenate([BEHIND, BLOCKER, FAR_SIDE])
    # Flightmare's selection: the ten behind take the slots, the blocker is the 11th: straight ahead
    np.testing.assert_allclose(expert_command(CRUISE, obstacles, 5.0), [5.0, 0.0, 0.0])
    # all-seeing: the blocker (inflated 1.6 m, 6 m ahead) blocks the lines to (8, s) with
    # 6 s / sqrt(64 + s^2) <= 1.6, i.e. s <= 2.21 m; the nearest free waypoints are 2.5 m off-centre on
    # the axes (Manhattan 5; (2, 0.5) and (1.5, 1) are still blocked), the tie goes to "up"
    np.testing.assert_allclose(expert_command(CRUISE, obstacles, 5.0, ALL_SEEING), unit([8.0, 0.0, 2.5]) * 5.0)
    # with one slot more the blocker is seen by the limited expert too
    np.testing.assert_allclose(
        expert_command(CRUISE, obstacles, 5.0, ExpertConfig(max_obstacles=11)), unit([8.0, 0.0, 2.5]) * 5.0
    )


def test_obstacles_beyond_10m_are_not_seen():
    # a big sphere (r = 8 m) whose centre is 6.3 m ahead and 8.4 m to the right: centre distance
    # sqrt(6.3^2 + 8.4^2) = 10.5 m. Its inflated radius 8.6 m exceeds the 8.4 m to the flight line,
    # so it would block flying straight, but Flightmare published nothing beyond 10 m.
    far = np.array([[10.0 + 6.3, -8.4, 3.5, 8.0]])
    np.testing.assert_allclose(expert_command(CRUISE, far, 5.0), [5.0, 0.0, 0.0])
    assert not np.allclose(expert_command(CRUISE, far, 5.0, ALL_SEEING), [5.0, 0.0, 0.0])
    # the same geometry scaled to 9.5 m (5.7 ahead, 7.6 right, r = 7.2: inflated 7.8 > 7.6) is seen
    near = np.array([[10.0 + 5.7, -7.6, 3.5, 7.2]])
    assert not np.allclose(expert_command(CRUISE, near, 5.0), [5.0, 0.0, 0.0])


def test_selection_ranks_by_centre_distance_including_behind():
    # distances from the drone at (10, 0, 3.5): 3 (behind), 9.5 (ahead), 4 (left), 10 (exactly at the
    # range: kept), 10.01 (dropped), 2 (below)
    obstacles = np.array(
        [
            [7.0, 0.0, 3.5, 0.2],
            [19.5, 0.0, 3.5, 0.2],
            [10.0, 4.0, 3.5, 0.2],
            [10.0, 0.0, 13.5, 0.2],
            [20.01, 0.0, 3.5, 0.2],
            [10.0, 0.0, 1.5, 0.2],
        ]
    )
    view = ExpertObstacles.from_spheres(obstacles)
    seen = visible_obstacles(CRUISE, view, ExpertConfig())
    assert sorted(map(tuple, seen)) == sorted(map(tuple, obstacles[[0, 1, 2, 3, 5]]))
    three = visible_obstacles(CRUISE, view, ExpertConfig(max_obstacles=3))
    assert sorted(map(tuple, three)) == sorted(map(tuple, obstacles[[0, 2, 5]]))  # 2 m, 3 m, 4 m
    np.testing.assert_array_equal(visible_obstacles(CRUISE, view, ALL_SEEING), obstacles)


def test_a_tree_counts_once_whatever_its_covering_spheres():
    # Flightmare published one entry per tree. A trunk 3 m to the left and 1 m ahead (horizontal
    # distance sqrt(1 + 9) = 3.16 m), 9 m tall, r = 0.3, is covered by 18 spheres (0.5 m apart), about
    # 12 of which are nearer than the blocker 6 m ahead. Counted per object, the tree and the blocker
    # are 2 objects: the blocker is seen and the expert climbs over it as in the hand-worked case.
    sc = Scene("trees", "test", 0, BLOCKER, np.array([[11.0, 3.0, 0.0, 9.0, 0.3]]), np.zeros((0, 6)))
    view = ExpertObstacles.from_scene(sc)
    assert len(view) == 1 + 18 and view.object_index.max() == 1
    cover_dist = np.linalg.norm(view.spheres[1:, :3] - CRUISE, axis=1)
    assert np.sum(cover_dist < 6.0) >= 10  # per covering sphere, the blocker would not make the ten
    np.testing.assert_allclose(expert_command(CRUISE, view, 5.0), unit([8.0, 0.0, 2.5]) * 5.0)
    # the tree's distance is the horizontal distance to its axis while the drone is below its top
    seen = visible_obstacles(CRUISE, view, ExpertConfig(max_obstacles=1))
    assert len(seen) == 18 and np.all(seen[:, 0] == 11.0)  # the whole trunk, nearer than the blocker


def test_canopy_on_a_trunk_is_the_same_object_and_boxes_are_objects():
    canopy = [[30.0, 2.0, 6.0, 1.2]]  # centred on the trunk's top
    loose = [[40.0, 0.0, 3.0, 1.0]]
    trunk = [[30.0, 2.0, 0.0, 6.0, 0.25]]
    box = [[20.0, -10.0, 0.0, 20.3, -1.0, 10.0]]
    sc = Scene("trees", "test", 0, np.array(canopy + loose), np.array(trunk), np.array(box))
    spheres, objects, lo, hi = sc.expert_objects()
    np.testing.assert_array_equal(spheres, sc.expert_obstacles())
    assert objects[0] == objects[2] and objects[1] != objects[0]  # canopy with its trunk (rows 2..)
    assert len(lo) == 3  # the loose sphere, the tree, the box
    np.testing.assert_array_equal(lo[objects[0]], [30.0, 2.0, 0.0])
    np.testing.assert_array_equal(hi[objects[0]], [30.0, 2.0, 6.0])
    # the box's distance is to its nearest point: from (19, -0.5, 3.5) that is (20, -1, 3.5), 1.118 m
    view = ExpertObstacles.from_scene(sc)
    seen = visible_obstacles(np.array([19.0, -0.5, 3.5]), view, ExpertConfig(max_obstacles=1))
    assert len(seen) == int(np.sum(objects == objects[-1])) and np.all(seen[:, 0] < 20.31)


def test_expert_policy_selects_from_the_whole_scene():
    from vitfly.sim.policies import ExpertPolicy
    from vitfly.sim.rollout import Observation

    # the tree-and-blocker scene of the test above: given the scene, the policy counts the tree once and
    # climbs over the blocker; given only the cover spheres (no scenes), each covering sphere counts
    sc = Scene("trees", "test", 0, BLOCKER, np.array([[11.0, 3.0, 0.0, 9.0, 0.3]]), np.zeros((0, 6)))

    def obs(scenes):
        return Observation(
            depth=np.zeros((1, 60, 90), np.float32),
            desired_speed=np.array([5.0]),
            quat=np.array([[1.0, 0.0, 0.0, 0.0]]),
            position=CRUISE[None],
            velocity=np.zeros((1, 3)),
            obstacles=[sc.expert_obstacles()],
            active=np.array([True]),
            time=np.zeros(1),
            tick=0,
            scenes=scenes,
        )

    policy = ExpertPolicy()
    policy.reset(1)
    np.testing.assert_allclose(policy(obs([sc]))[0], unit([8.0, 0.0, 2.5]) * 5.0)
    policy.reset(1)
    np.testing.assert_allclose(policy(obs(None))[0], [5.0, 0.0, 0.0])  # the blocker is the 11th+ sphere
    np.testing.assert_allclose(ExpertPolicy(ALL_SEEING)(obs(None))[0], unit([8.0, 0.0, 2.5]) * 5.0)
