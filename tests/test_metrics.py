"""Metrics on hand-built paths; every expected value is worked out by hand in the comments."""

import math

import numpy as np
import pytest

from vitfly.errors import VitflyError
from vitfly.eval import metrics as m


def test_collision_entries_count_rising_edges():
    assert m.collision_entries([False, True, True, False, True, False]) == 2
    # contact at the first sample is an entry; a contact run at the end is one entry
    assert m.collision_entries([True, False, True, True]) == 2
    assert m.collision_entries([False] * 5) == 0
    assert m.collision_entries([True] * 5) == 1


def test_contact_time_and_time_per_obstacle():
    t = np.arange(6) * 0.1
    contact = [False, True, True, False, True, False]
    # samples 1, 2 and 4 hold contact for 0.1 s each -> 0.3 s; two entries -> 0.15 s per obstacle
    assert m.contact_time_s(t, contact) == pytest.approx(0.3)
    assert m.time_in_collision_per_obstacle_s(t, contact) == pytest.approx(0.15)
    # the last sample holds for the last interval again (0.5 s)
    assert m.contact_time_s([0.0, 0.5, 1.0], [False, False, True]) == pytest.approx(0.5)
    assert math.isnan(m.time_in_collision_per_obstacle_s(t, [False] * 6))


def test_energy_cost_paper_and_avoidbench_variants():
    t = [0.0, 1.0, 2.0, 3.0]
    v = [[0, 0, 0], [1, 0, 0], [1, 0, 0], [3, 0, 0]]
    p = [[0, 0, 0], [0.5, 0, 0], [1.5, 0, 0], [3.5, 0, 0]]
    # a = [1, 0, 2]; |a1-a0| + |a2-a1| = 1 + 2 = 3; path length 3.5 m
    assert m.acceleration_change_sum(t, v) == pytest.approx(3.0)
    assert m.energy_cost(t, v, p) == pytest.approx(3.0 / 3.5)
    # AvoidBench: divide by the optimal length instead (6 m) -> 0.5
    assert m.energy_cost(t, v, p, reference_length_m=6.0) == pytest.approx(0.5)


def test_energy_cost_uses_vector_norms_and_dt():
    t = [0.0, 0.5, 1.0]
    v = [[0, 0, 0], [3, 4, 0], [3, 4, 0]]
    p = [[0, 0, 0], [3, 4, 0], [6, 8, 0]]
    # a0 = (3,4,0)/0.5 = (6,8,0), a1 = 0 -> |a1-a0| = 10; path 10 m -> 1.0
    assert m.energy_cost(t, v, p) == pytest.approx(1.0)
    # a hovering drone has no path: undefined
    assert math.isnan(m.energy_cost(t, np.zeros((3, 3)), np.zeros((3, 3))))


def test_commanded_acceleration_smooths_over_four_samples():
    t = np.arange(8) * 0.1
    cmd = np.zeros((8, 3))
    cmd[4:, 0] = 4.0  # step from 0 to 4 m/s
    p = np.zeros((8, 3))
    p[:, 0] = np.linspace(0.0, 8.0, 8)  # 8 m flown
    # 4-sample means: 0, 1, 2, 3, 4 -> four steps of 1 m/s over 0.1 s = 10 m/s^2 each -> 40; / 8 m = 5
    assert m.moving_average(cmd[:, 0]).tolist() == pytest.approx([0, 1, 2, 3, 4])
    assert m.commanded_acceleration(t, cmd, p) == pytest.approx(5.0)
    # a constant command has zero commanded acceleration
    assert m.commanded_acceleration(t, np.ones((8, 3)), p) == 0.0


def test_lateral_deviation_speed_and_time_to_goal():
    p = np.zeros((4, 3))
    p[:, 1] = [0.5, 1.5, -1.5, 1.5]  # |y - 0.5| = 0, 1, 2, 1 -> mean 1, max 2
    assert m.lateral_deviation_m(p) == pytest.approx((1.0, 2.0))
    assert m.mean_forward_speed_mps([[2, 9, 9], [4, 0, 0], [6, 0, 0]]) == pytest.approx(4.0)
    x = np.zeros((5, 3))
    x[:, 0] = [0, 30, 59.9, 60.0, 61]
    assert m.time_to_goal_s([1, 2, 3, 4, 5], x, 60.0) == pytest.approx(3.0)  # from t0 = 1 s
    assert math.isnan(m.time_to_goal_s([1, 2, 3, 4, 5], x, 70.0))


def _straight_flight(n=61, speed=3.0, dt=0.1):
    t = np.arange(n) * dt
    pos = np.zeros((n, 3))
    pos[:, 0] = speed * t
    pos[:, 2] = 3.5
    vel = np.zeros((n, 3))
    vel[:, 0] = speed
    return t, pos, vel, vel.copy()


def test_trial_metrics_straight_flight_without_contact_succeeds():
    t, pos, vel, cmd = _straight_flight()
    r = m.trial_metrics(t, pos, vel, cmd, np.zeros(len(t), bool), desired_speed_mps=3.0, goal_x_m=18.0,
                        reached_goal=True, processing_ms=2.0)
    assert r.success and r.collisions == 0
    assert r.path_length_m == pytest.approx(18.0)
    assert r.energy_cost == 0.0 and r.cmd_acc == 0.0
    assert r.speed_ratio == pytest.approx(1.0)
    assert r.time_to_goal_s == pytest.approx(6.0)
    assert math.isnan(r.time_in_collision_s)
    assert r.processing_ms == 2.0


def test_trial_metrics_collision_breaks_success():
    t, pos, vel, cmd = _straight_flight()
    contact = np.zeros(len(t), bool)
    contact[10:13] = True  # 3 samples x 0.1 s
    r = m.trial_metrics(t, pos, vel, cmd, contact, desired_speed_mps=6.0, goal_x_m=18.0, reached_goal=True)
    assert not r.success and r.reached_goal and r.collisions == 1
    assert r.time_in_collision_s == pytest.approx(0.3)
    assert r.speed_ratio == pytest.approx(0.5)


def test_trial_metrics_rejects_bad_shapes():
    t, pos, vel, cmd = _straight_flight(5)
    with pytest.raises(VitflyError, match="velocity"):
        m.trial_metrics(t, pos, vel[:, :2], cmd, np.zeros(5, bool), desired_speed_mps=3, goal_x_m=60,
                        reached_goal=False)
    with pytest.raises(VitflyError, match="increasing"):
        m.trial_metrics(t[::-1], pos, vel, cmd, np.zeros(5, bool), desired_speed_mps=3, goal_x_m=60,
                        reached_goal=False)


def test_spread_skips_undefined_values():
    s = m.spread([1.0, 2.0, 3.0, None, math.nan])
    assert (s.mean, s.std, s.n) == (pytest.approx(2.0), pytest.approx(1.0), 3)
    assert m.spread([4.0]).std == 0.0
    assert m.spread([None]).n == 0 and math.isnan(m.spread([]).mean)
