"""The privileged expert against hand-worked answers and a plain-loop reference."""

import itertools
import math

import numpy as np
import pytest

from vitfly.sim.expert import ExpertConfig, blocked_waypoints, expert_command, waypoint_grid

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
    column = np.array([[14.0, 0.0, 3.5 + z, 0.4] for z in np.arange(-12.0, 12.5, 0.5)])
    cmd = expert_command(CRUISE, column, 4.0)
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


def reference_expert(position, obstacles, speed):
    """The specification as plain loops (row-major scan, first nearest wins)."""
    offsets = [8.0 - 0.5 * k for k in range(33)]
    best = None
    for (i, z), (j, y) in itertools.product(enumerate(offsets), enumerate(offsets)):
        w = np.array([8.0, y, z])
        free = True
        for ox, oy, oz, r in obstacles:
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
def test_vectorised_expert_matches_plain_loops(seed):
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
    np.testing.assert_allclose(expert_command(position, obstacles, 4.5), reference_expert(position, obstacles, 4.5))
