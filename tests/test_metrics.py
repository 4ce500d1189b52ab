"""Metrics on hand-built paths; every expected value is worked out by hand in the comments, from the
original analysis code's formulas (analysis/gen_metrics.py, Analysis/gen_collision_plots.py,
envtest/ros/evaluation_node.py)."""

import math

import numpy as np
import pytest

from vitfly.errors import VitflyError
from vitfly.eval import metrics as m

GUARD = 1 / (1 + 1e-7)  # the original's dv * dt / (dt^2 + 1e-9) at dt = 0.1 s: (dv / dt) * 0.01 / (0.01 + 1e-9)


def test_collision_entries_count_rising_edges():
    assert m.collision_entries([False, True, True, False, True, False]) == 2
    # contact at the first sample is an entry; a contact run at the end is one entry
    assert m.collision_entries([True, False, True, True]) == 2
    assert m.collision_entries([False] * 5) == 0
    assert m.collision_entries([True] * 5) == 1


def test_contact_time_and_both_time_in_collision_variants():
    t = np.arange(6) * 0.1
    contact = [False, True, True, False, True, False]
    # samples 1, 2 and 4 hold contact for 0.1 s each -> 0.3 s; two entries -> 0.15 s per collision
    assert m.contact_time_s(t, contact) == pytest.approx(0.3)
    assert m.time_in_collision_s(t, contact) == pytest.approx(0.15)
    assert m.time_in_collision_colliding_s(t, contact) == pytest.approx(0.15)
    # the last sample holds for the last interval again (0.5 s)
    assert m.contact_time_s([0.0, 0.5, 1.0], [False, False, True]) == pytest.approx(0.5)
    # without a collision: 0 as the paper plots it, undefined in the per-colliding-trial variant
    assert m.time_in_collision_s(t, [False] * 6) == 0.0
    assert math.isnan(m.time_in_collision_colliding_s(t, [False] * 6))


def test_time_in_collision_over_three_trials_as_the_paper_plots_it():
    # gen_collision_plots.py: per trial (flagged rows * 0.045 s) / collisions, or 0 without a collision,
    # then the mean over ALL trials. With samples 0.045 s apart its formula and ours agree exactly:
    t = np.arange(6) * 0.045
    trials = [
        [False, True, True, False, True, False],  # 3 rows, 2 collisions -> 3 * 0.045 / 2 = 0.0675 s
        [False, False, True, True, True, False],  # 3 rows, 1 collision  -> 3 * 0.045 / 1 = 0.135 s
        [False] * 6,  # no collision -> 0 s
    ]
    paper = [m.time_in_collision_s(t, c) for c in trials]
    assert paper == pytest.approx([0.0675, 0.135, 0.0])
    # the paper's plotted value: (0.0675 + 0.135 + 0) / 3 = 0.0675 s
    assert m.spread(paper).mean == pytest.approx(0.0675)
    # vitfly's variant, over the colliding trials only: (0.0675 + 0.135) / 2 = 0.10125 s
    colliding = [m.time_in_collision_colliding_s(t, c) for c in trials]
    assert m.spread(colliding).mean == pytest.approx(0.10125) and m.spread(colliding).n == 2


def test_energy_cost_paper_and_avoidbench_variants():
    t = [0.0, 1.0, 2.0, 3.0]
    v = [[0, 0, 0], [1, 0, 0], [1, 0, 0], [3, 0, 0]]
    p = [[0, 0, 0], [0.5, 0, 0], [1.5, 0, 0], [3.5, 0, 0]]
    # a = [1, 0, 2] (all samples); |a1-a0| + |a2-a1| = 1 + 2 = 3
    assert m.acceleration_change_sum(t, v) == pytest.approx(3.0)
    # jerkCost divides by the distance over the samples with x > 0.1: 0.5 -> 1.5 -> 3.5 = 3 m -> 1.0
    assert m.distance_travelled_m(p) == pytest.approx(3.0)
    assert m.energy_cost(t, v, p) == pytest.approx(1.0)
    # AvoidBench: divide by the optimal length instead (6 m) -> 0.5
    assert m.energy_cost(t, v, p, reference_length_m=6.0) == pytest.approx(0.5)


def test_energy_cost_uses_vector_norms_and_dt():
    t = [0.0, 0.5, 1.0]
    v = [[0, 0, 0], [3, 4, 0], [3, 4, 0]]
    p = [[0, 0, 0], [3, 4, 0], [6, 8, 0]]
    # a0 = (3,4,0)/0.5 = (6,8,0), a1 = 0 -> |a1-a0| = 10; distance past x = 0.1: (3,4) -> (6,8) = 5 m -> 2.0
    assert m.energy_cost(t, v, p) == pytest.approx(2.0)
    # a hovering drone has no path: undefined
    assert math.isnan(m.energy_cost(t, np.zeros((3, 3)), np.zeros((3, 3))))


def test_commands_are_smoothed_as_np_convolve_same():
    # np.convolve(c, ones(4)/4, "same") keeps 6 samples; sample i = (c[i-2] + c[i-1] + c[i] + c[i+1]) / 4,
    # zeros outside the sequence:
    #   x: c = 0 0 4 4 4 4 -> (0+0+0+0)/4, (0+0+0+4)/4, (0+0+4+4)/4, (0+4+4+4)/4, (4+4+4+4)/4, (4+4+4+0)/4
    #                       = 0, 1, 2, 3, 4, 3
    #   y: c = 0 0 0 0 3 3 -> 0, 0, 0, 0.75, 1.5, 1.5
    cmd = np.zeros((6, 3))
    cmd[:, 0] = [0, 0, 4, 4, 4, 4]
    cmd[:, 1] = [0, 0, 0, 0, 3, 3]
    smooth = m.smooth_commands(cmd)
    assert smooth[:, 0].tolist() == pytest.approx([0, 1, 2, 3, 4, 3])
    assert smooth[:, 1].tolist() == pytest.approx([0, 0, 0, 0.75, 1.5, 1.5])
    assert smooth[:, 2].tolist() == [0.0] * 6


def test_commanded_acceleration_as_gen_metrics():
    # 7 ticks 0.1 s apart: the first at the start (x = 0, dropped: the original keeps pos_x > 0.1), then the
    # six commands of the smoothing test at x = 1 .. 6 m
    t = np.arange(7) * 0.1
    p = np.zeros((7, 3))
    p[:, 0] = np.arange(7.0)
    cmd = np.zeros((7, 3))
    cmd[0] = [9.0, 9.0, 9.0]  # dropped with its sample
    cmd[1:, 0] = [0, 0, 4, 4, 4, 4]
    cmd[1:, 1] = [0, 0, 0, 0, 3, 3]
    # smoothed deltas (x, y): (1, 0), (1, 0), (1, .75), (1, .75), (-1, 0) -> norms 1, 1, 1.25, 1.25, 1 = 5.5 m/s,
    # over 0.1 s each -> 55 m/s^2; distance over the kept samples x = 1 .. 6 -> 5 m; 55 / 5 = 11
    assert m.commanded_acceleration(t, cmd, p) == pytest.approx(11.0 * GUARD, rel=1e-12)
    # a constant command is not free: "same" pads with zeros, so c/2, 3c/4, c, ..., c, 3c/4 -> deltas c/4,
    # c/4, 0, ..., -c/4. With c = 2 m/s: 3 * 0.5 / 0.1 = 15 m/s^2 over 5 m -> 3
    const = np.zeros((7, 3))
    const[:, 0] = 2.0
    assert m.commanded_acceleration(t, const, p) == pytest.approx(3.0 * GUARD, rel=1e-12)
    # fewer than 4 samples past the start: undefined (the original's "same" output would outgrow the path)
    assert math.isnan(m.commanded_acceleration(t[:4], cmd[:4], p[:4]))


def test_time_to_goal_interpolates_both_crossings():
    # evaluation_node.py: the clock starts when x first exceeds 0.5 m and stops when x reaches the goal
    t = [0.0, 0.5, 1.0, 1.5]
    x = np.zeros((4, 3))
    x[:, 0] = [0.0, 0.2, 1.2, 2.2]
    # 0.5 m between 0.2 (0.5 s) and 1.2 (1.0 s): 0.5 + 0.3 / 1.0 * 0.5 = 0.65 s
    # 2.0 m between 1.2 (1.0 s) and 2.2 (1.5 s): 1.0 + 0.8 / 1.0 * 0.5 = 1.4 s  -> 0.75 s
    assert m.crossing_time_s(t, x[:, 0], 0.5) == pytest.approx(0.65)
    assert m.time_to_goal_s(t, x, 2.0) == pytest.approx(0.75)
    assert math.isnan(m.time_to_goal_s(t, x, 3.0))


def test_time_to_goal_uses_the_end_state_past_the_last_tick():
    # no control tick reaches x = 60: the episode ends at the physics step that does (3.1 s, x = 60.4)
    t = [0.0, 1.0, 2.0, 3.0]
    x = np.zeros((4, 3))
    x[:, 0] = [0.0, 20.0, 40.0, 58.0]
    # start: 0.5 m at 0 + 0.5 / 20 * 1 = 0.025 s; goal: 60 m at 3.0 + 2 / 2.4 * 0.1 = 3.083333 s -> 3.058333 s
    assert m.time_to_goal_s(t, x, 60.0, end_time_s=3.1, end_position=[60.4, 0, 3.5]) == pytest.approx(
        3.0 + 0.2 / 2.4 - 0.025)
    assert math.isnan(m.time_to_goal_s(t, x, 60.0))  # ticks alone never reach it


def test_lateral_deviation_and_speed():
    p = np.zeros((4, 3))
    p[:, 1] = [0.5, 1.5, -1.5, 1.5]  # |y - 0.5| = 0, 1, 2, 1 -> mean 1, max 2
    assert m.lateral_deviation_m(p) == pytest.approx((1.0, 2.0))
    assert m.mean_forward_speed_mps([[2, 9, 9], [4, 0, 0], [6, 0, 0]]) == pytest.approx(4.0)


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
    assert r.success_paper and r.success_strict and r.collisions == 0
    assert r.path_length_m == pytest.approx(18.0)
    assert r.energy_cost == 0.0
    # constant 3 m/s: smoothed edges give 3 * 0.75 m/s per 0.1 s = 22.5 m/s^2, over 18 - 0.3 = 17.7 m
    assert r.cmd_acc == pytest.approx(22.5 / 17.7 * GUARD, rel=1e-12)
    assert r.speed_ratio == pytest.approx(1.0)
    # clock from x = 0.5 m (t = 0.1 + 0.2 / 0.3 * 0.1 = 1/6 s) to x = 18 m (t = 6 s)
    assert r.time_to_goal_s == pytest.approx(6.0 - 1 / 6)
    assert r.time_in_collision_s == 0.0 and math.isnan(r.time_in_collision_colliding_s)
    assert r.processing_ms == 2.0


def test_success_paper_and_strict():
    t, pos, vel, cmd = _straight_flight()
    contact = np.zeros(len(t), bool)
    contact[10:13] = True  # 3 samples x 0.1 s
    hit = m.trial_metrics(t, pos, vel, cmd, contact, desired_speed_mps=6.0, goal_x_m=18.0, reached_goal=True)
    assert not hit.success_paper and not hit.success_strict and hit.reached_goal and hit.collisions == 1
    assert hit.time_in_collision_s == pytest.approx(0.3) and hit.time_in_collision_colliding_s == pytest.approx(0.3)
    assert hit.speed_ratio == pytest.approx(0.5)
    # no collision but the goal not reached (e.g. a timeout): a success for the paper, not for the strict rule
    stalled = m.trial_metrics(t, pos, vel, cmd, np.zeros(len(t), bool), desired_speed_mps=3.0, goal_x_m=60.0,
                              reached_goal=False)
    assert stalled.success_paper and not stalled.success_strict and math.isnan(stalled.time_to_goal_s)


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
