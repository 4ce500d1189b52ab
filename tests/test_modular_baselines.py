"""The comparison with modular baselines (vitfly.eval.modular_baselines, the paired finding, the figure, the
reproduce config's modular section): hand-made records, values worked out by hand."""

import numpy as np
import pytest

from vitfly.errors import VitflyError
from vitfly.eval.aggregate import summarize
from vitfly.eval.modular_baselines import (
    cruise_speed_mps,
    cruise_speeds,
    planner_policies,
    replan_latency,
    velocity_matching,
)
from vitfly.eval.paired_findings import modular_baselines
from vitfly.eval.paper_figures import draw_modular_baselines, modular_baselines_figure
from vitfly.eval.records import TrialRecord
from vitfly.workflows.reproduce_config import load_reproduce_config

PLANNERS = {"fp": ("modular:fastplanner", False), "fps": ("modular:fastplanner_scaled", True),
            "cx": ("modular:convex", False)}


def rec(policy, scene, speed, success=True, forward_mps=None, replan_ms=None):
    """One spheres trial; ``forward_mps`` defaults to the desired speed (a policy that flies what it is asked)."""
    forward = speed if forward_mps is None else forward_mps
    extra = {"policy_source": policy}
    if policy in PLANNERS:
        extra = {"policy_source": PLANNERS[policy][0], "design_speed_mps": 3.0, "scaled": PLANNERS[policy][1],
                 "replan_ms": [] if replan_ms is None else replan_ms}
    return TrialRecord(policy=policy, env="spheres", speed=speed, trial=scene, scene_seed=7000 + scene,
                       success_paper=success, success_strict=success, reached_goal=True, end_reason="goal",
                       metrics={"collisions": 0 if success else 1, "forward_speed_mps": forward,
                                "speed_ratio": forward / speed}, path=cruise_path(forward), setup={}, setup_id="s",
                       extra=extra)


def cruise_path(forward_mps):
    """x = 0, 10 and 50 m at a constant forward speed: a cruise of exactly ``forward_mps``."""
    times = [0.0, 10.0 / forward_mps, 50.0 / forward_mps]
    return {"time": times, "position": [[x, 0.0, 2.0] for x in (0.0, 10.0, 50.0)]}


def study(vit_fails=()):
    """10 scenes at 1 and 7 m/s. ViT+LSTM flies the desired speed and never collides, except the (scene, speed)
    in ``vit_fails``; fp flies 2.0 m/s and never collides; cx flies 2.85 m/s and collides in scenes 0-4 at 7 m/s."""
    out = []
    for k in range(10):
        for v in (1.0, 7.0):
            out.append(rec("vit_lstm", k, v, success=(k, v) not in vit_fails))
            out.append(rec("fp", k, v, forward_mps=2.0))
            out.append(rec("cx", k, v, success=not (k < 5 and v == 7.0), forward_mps=2.85))
    return out


def test_modular_finding_partly_when_one_planner_is_as_safe():
    f = modular_baselines(study())
    by = {(d.b, d.metric): d for d in f.comparisons}
    assert sorted(by) == [("cx", "speed_error"), ("cx", "success"), ("fp", "speed_error"), ("fp", "success")]
    # speed error |forward / desired - 1|: ViT+LSTM 0; fp 1.0 at 1 m/s and 1 - 2/7 at 7 m/s, the same in every
    # scene, so the scene bootstrap has nothing to resample: the interval is the point
    fp = by[("fp", "speed_error")]
    assert fp.diff == pytest.approx(-(1.0 + 5 / 7) / 2) and fp.low == fp.high == pytest.approx(fp.diff)
    assert fp.better == "vit_lstm"
    cx = by[("cx", "speed_error")]
    assert cx.diff == pytest.approx(-(1.85 + (1 - 2.85 / 7)) / 2) and cx.better == "vit_lstm"
    # success: both never collide against fp (no discordant pair: cannot tell); against cx, +1 in 5 of the 20
    # pairs: +25 points, and the 10 scenes (5 at +0.5 per pair, 5 at 0) put 0 over 3 standard errors below it
    assert by[("fp", "success")].diff == 0 and by[("fp", "success")].better is None
    assert by[("cx", "success")].diff == pytest.approx(0.25) and by[("cx", "success")].low > 0
    assert f.verdict == "partly" and f.why == "3 of 4 claims decided for, 0 against"


def test_modular_finding_not_when_vit_lstm_collides_more():
    # ViT+LSTM collides in all 10 scenes at 7 m/s, fp in none: ViT+LSTM - fp = -10 / 20 in every scene, against
    f = modular_baselines(study(vit_fails={(k, 7.0) for k in range(10)}))
    fp = next(d for d in f.comparisons if d.b == "fp" and d.metric == "success")
    assert fp.diff == pytest.approx(-0.5) and fp.better == "fp"
    assert f.verdict == "not"


def test_modular_finding_not_applicable_without_planners_or_vit_lstm():
    assert modular_baselines([]).verdict == "n/a"
    assert modular_baselines([r for r in study() if r.policy != "vit_lstm"]).verdict == "n/a"
    assert modular_baselines([r for r in study() if r.policy == "vit_lstm"]).verdict == "n/a"


def test_velocity_matching_target_by_hand():
    rows = [{"policy": "vit_lstm", "speed": s, "forward_speed_mean": f, "speed_ratio_mean": f / s}
            for s, f in ((1.0, 0.95), (4.0, 4.3), (7.0, 6.4))]  # ratios 0.95, 1.075, 0.914: within 10 %
    rows += [{"policy": "fp", "speed": s, "forward_speed_mean": f, "speed_ratio_mean": f / s}
             for s, f in ((1.0, 2.0), (7.0, 3.2))]  # 3.2 <= 1.1 x 3 m/s: saturates
    rows += [{"policy": "fps", "speed": 7.0, "forward_speed_mean": 5.0, "speed_ratio_mean": 5 / 7}]  # scaled: no target
    planners = {"fp": {"design_speed_mps": 3.0, "scaled": False}, "fps": {"design_speed_mps": 3.0, "scaled": True}}
    targets = {t.policy: t for t in velocity_matching(rows, planners)}
    assert sorted(targets) == ["fp", "vit_lstm"]
    assert targets["vit_lstm"].met is True and targets["vit_lstm"].ratio == pytest.approx((0.95, 1.075, 6.4 / 7))
    assert targets["fp"].met is True and targets["fp"].forward_mps == (2.0, 3.2)
    rows[2]["speed_ratio_mean"] = 6.2 / 7  # 0.886: 11.4 % short
    rows[4]["forward_speed_mean"] = 3.4  # over 3.3 m/s
    targets = {t.policy: t for t in velocity_matching(rows, planners)}
    assert targets["vit_lstm"].met is False and targets["fp"].met is False
    assert velocity_matching([], {})[0].met is None  # ViT+LSTM not flown


def test_replan_latency_pools_every_replan_of_a_planner():
    recs = [rec("fp", 0, 1.0, replan_ms=[10.0, 20.0]), rec("fp", 1, 1.0, replan_ms=[30.0]),
            rec("cx", 0, 1.0, replan_ms=[4.0]), rec("vit_lstm", 0, 1.0)]
    lat = replan_latency(recs)
    assert sorted(lat) == ["cx", "fp"]
    # [10, 20, 30]: mean 20; 95th percentile (linear) at rank 0.95 x 2 = 1.9: 20 + 0.9 x 10 = 29
    assert lat["fp"] == {"trials": 2, "replans": 3, "mean_ms": 20.0, "p95_ms": pytest.approx(29.0), "max_ms": 30.0}
    assert planner_policies(recs) == {"cx": {"design_speed_mps": 3.0, "scaled": False},
                                      "fp": {"design_speed_mps": 3.0, "scaled": False}}


def test_cruise_speed_by_hand():
    # accelerating: x crosses 10 m at t = 2 + 2 * (10 - 4) / (12 - 4) = 3.5 s and 50 m at t = 8 + 2 * 10 / 16 = 9.25 s
    r = rec("vit_lstm", 0, 7.0)
    r.path = {"time": [0, 2, 4, 6, 8, 10], "position": [[x, 0, 2] for x in (0, 4, 12, 24, 40, 56)]}
    assert cruise_speed_mps(r) == pytest.approx(40 / 5.75)
    stalled = rec("fp", 1, 7.0)
    stalled.path = {"time": [0, 5, 40], "position": [[0, 0, 2], [20, 0, 2], [30, 0, 2]]}
    assert np.isnan(cruise_speed_mps(stalled))
    assert cruise_speeds([r, stalled, rec("vit_lstm", 1, 7.0, forward_mps=6.0)]) == {
        ("vit_lstm", 7.0): pytest.approx((40 / 5.75 + 6.0) / 2)}  # the stalled trial has no cruise
    # the target on cruise speeds: ViT+LSTM's whole-trial means (0.8 x desired) miss it, its cruise meets it
    rows = [{"policy": "vit_lstm", "speed": s, "forward_speed_mean": 0.8 * s, "speed_ratio_mean": 0.8} for s in (1, 7)]
    cruise = {("vit_lstm", 1.0): 0.98, ("vit_lstm", 7.0): 6.6}
    assert velocity_matching(rows, {})[0].met is False
    target = velocity_matching(rows, {}, cruise=cruise)[0]
    assert target.met is True and target.ratio == pytest.approx((0.98, 6.6 / 7)) and "cruise" in target.target
    assert velocity_matching(rows, {}, cruise={("vit_lstm", 1.0): 0.98})[0].met is False  # no cruise at 7 m/s


def test_figure_draws_collision_rate_speed_against_desired_and_latency(tmp_path):
    recs = study()
    for r in recs:
        if r.policy in PLANNERS:
            r.extra["replan_ms"] = [10.0, 20.0, 30.0] if r.policy == "fp" else [5.0]
    rows = summarize(recs)
    fig = draw_modular_baselines(rows, recs)
    ax_col, ax_speed, ax_lat = fig.axes[:3]
    lines = {ln.get_label(): ln for ln in ax_col.lines}
    # collision rate in %: cx collides in 5 of 10 scenes at 7 m/s, never at 1
    assert lines["cx"].get_ydata().tolist() == [0.0, 50.0] and lines["vit_lstm"].get_ydata().tolist() == [0.0, 0.0]
    speeds = [ln.get_ydata().tolist() for ln in ax_speed.lines]
    assert [2.0, 2.0] in speeds and [1.0, 7.0] in speeds  # fp at 2 m/s whatever; ViT+LSTM on y = x
    diagonal = next(ln for ln in ax_speed.lines if ln.get_label().startswith("y = x"))
    assert np.allclose(diagonal.get_xdata(), diagonal.get_ydata())
    heights = sorted(round(p.get_height(), 6) for p in ax_lat.patches)
    # cx: 5 ms; fp: 20 trials of [10, 20, 30] pooled, 60 values whose 95th percentile (rank 0.95 x 59 = 56.05)
    # falls among the twenty 30s
    assert heights == [5.0, 5.0, 20.0, 30.0]
    path = modular_baselines_figure(rows, recs, tmp_path / "modular.png")
    assert path.stat().st_size > 10_000


@pytest.mark.parametrize("modular, message", [
    ({"planners": ["astar"]}, "modular.planners: modular:astar: no planner 'astar'"),
    ({"models": ["convnet_large"]}, "modular.models has 'convnet_large'; known: "),
    ({"planner_speeds": {"convex": [1.0]}, "planners": ["fastplanner"]}, "modular.planner_speeds has 'convex'"),
    ({"planner_speeds": {"fastplanner": "fast"}}, "modular.planner_speeds.fastplanner must be a list"),
    ({"trials": 0}, "modular.trials, modular.num_envs and modular.workers must be >= 1"),
    ({"baselines": ["random"]}, "modular.baselines has 'random'"),
    ({"speeeds": [1.0]}, "speeeds"),
])
def test_bad_modular_settings_are_one_line(modular, message):
    with pytest.raises(VitflyError, match=None) as err:
        load_reproduce_config("reproduce", "shipped", overrides={"modular": modular})
    assert message in str(err.value) and "\n" not in str(err.value)


def test_modular_settings_of_the_shipped_preset():
    cfg = load_reproduce_config("reproduce", "shipped")
    m = cfg.modular
    assert m.seed == 7070 and m.models == ["vit_lstm"] and m.baselines == ["expert"]
    assert m.speeds_of("fastplanner_scaled") == [1.0, 3.0, 5.0, 7.0] and m.trials == 30
    assert m.speeds_of("fastplanner") == m.speeds_of("convex") == [3.0, 7.0]  # the same flight at every speed
