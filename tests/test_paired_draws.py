"""Training draws in the paired comparisons (vitfly.eval.paired, two-level bootstrap): values worked out by hand."""

import numpy as np
import pytest
from helpers import load_script
from scipy.stats import bootstrap

from vitfly.eval.findings import draw_label, label, split_draw
from vitfly.eval.paired import paired_difference, pooled_draw_variance, two_level_bootstrap_interval
from vitfly.eval.paired_findings import lead_table, paired_findings, paired_findings_markdown, resnet_no_better
from vitfly.eval.records import TrialRecord


def rec(policy, scene, speed=7.0, collisions=0.0, env="spheres"):
    return TrialRecord(policy=policy, env=env, speed=speed, trial=scene, scene_seed=1000 + scene,
                       success_paper=collisions == 0, success_strict=collisions == 0, reached_goal=True,
                       end_reason="goal", metrics={"collisions": float(collisions)}, path={}, setup={}, setup_id="s")


def flights(policy, collisions, scenes=20, speed=7.0):
    return [rec(policy, k, speed, collisions(k)) for k in range(scenes)]


def test_draw_labels():
    assert draw_label("vit_lstm-nostate", 2) == "vit_lstm-nostate-s2"
    assert split_draw("vit_lstm-nostate-s2") == ("vit_lstm-nostate", 2)
    assert split_draw("resnet18") == ("resnet18", None) and split_draw("expert") == ("expert", None)
    assert label("vit_lstm-nostate-s2") == "ViT+LSTM (no state), seed 2"
    assert label("convnet-s10") == "ConvNet, seed 10" and label("convnet") == "ConvNet"
    assert label("convnet-state") == "ConvNet" and label("lstmnet-state-s1") == "LSTMnet, seed 1"  # run folders
    assert label("foo-state") == "foo-state"


def test_two_draws_by_hand():
    # a's draws: 1 collision in every trial, and 3; b: none. Scenes are all alike, so only the draws vary. The
    # draws are spread from their mean 2 by sqrt(2 / 1): 2 -+ sqrt(2). A resample of the two is (low, low) with
    # p 1/4, (high, high) 1/4, mixed 1/2 -> mean 2 - sqrt(2), 2 + sqrt(2) or 2; the 2.5 % and 97.5 % quantiles
    # of that are the two ends
    recs = flights("a", lambda k: 1) + flights("a-s1", lambda k: 3) + flights("b", lambda k: 0)
    d = paired_difference(recs, "a", "b", "spheres", "collisions", draws={"a": ["a", "a-s1"]})
    assert (d.mean_a, d.mean_b, d.diff) == (2.0, 0.0, 2.0)
    assert (d.low, d.high) == pytest.approx((2 - 2**0.5, 2 + 2**0.5))
    assert (d.draws_a, d.draws_b, d.pairs, d.scenes, d.mcnemar_p) == (2, 1, 20, 20, None)
    assert d.better == "b" and d.text().endswith("20 pairs, 2 vs 1 draws")
    # without the draws mapping, a is its own draw alone: 1 collision a trial, a constant difference
    alone = paired_difference(recs, "a", "b", "spheres", "collisions")
    assert (alone.low, alone.diff, alone.high, alone.draws_a) == (1.0, 1.0, 1.0, 1)


def test_equal_draws_give_exactly_zero():
    # every draw of a flies as b, scene by scene (varied outcomes): the difference is exactly 0 in every resample
    pattern = [(k * 7) % 3 for k in range(30)]
    recs = [r for p in ("a", "a-s1", "a-s2", "b", "b-s4") for r in flights(p, lambda k: pattern[k], scenes=30)]
    d = paired_difference(recs, "a", "b", "spheres", "success", draws={"a": ["a", "a-s1", "a-s2"], "b": ["b", "b-s4"]})
    assert (d.low, d.diff, d.high) == (0.0, 0.0, 0.0) and not d.decided


def test_one_draw_each_is_the_scene_bootstrap():
    # one draw a side: the two-level interval is a percentile bootstrap over scenes, which scipy computes alike
    rng = np.random.default_rng(5)
    diff = rng.normal(0.3, 1.0, 200)
    scene = np.repeat(np.arange(100), 2)  # two speeds per scene: scenes are resampled whole
    ours = two_level_bootstrap_interval(scene, diff[None, :], np.zeros((1, 200)))
    per_scene = diff.reshape(100, 2).mean(axis=1)  # equal pairs per scene: the mean of scene means
    ref = bootstrap((per_scene,), np.mean, n_resamples=10_000, method="percentile",
                    rng=np.random.default_rng(0)).confidence_interval
    assert ours == pytest.approx((ref.low, ref.high), abs=0.01)


def test_a_trial_missing_in_one_draw_drops_that_pair_for_all():
    missing = [r for r in flights("a-s1", lambda k: 1) if r.trial != 3]  # draw s1 never flew scene 3
    recs = flights("a", lambda k: 0) + missing + flights("b", lambda k: 0)
    d = paired_difference(recs, "a", "b", "spheres", "collisions", draws={"a": ["a", "a-s1"]})
    assert (d.pairs, d.mean_a) == (19, 0.5)


def test_a_draw_not_flown_yet_is_left_out_of_its_group():
    recs = flights("a", lambda k: k % 2) + flights("b", lambda k: 0)
    alone = paired_difference(recs, "a", "b", "spheres", "success")
    grouped = paired_difference(recs, "a", "b", "spheres", "success", draws={"a": ["a", "a-s1"]})
    assert grouped == alone and grouped.draws_a == 1 and grouped.mcnemar_p is not None


def test_findings_and_lead_table_pool_draws():
    # ResNet-18: one draw, always succeeds. ConvNet: its own draw never succeeds, its second always: pooled
    # 50 %, so ResNet-18 leads by 50 points; ConvNet's draws spread to 50 -+ 50 sqrt(2) %, so the resample puts
    # its mean at 50 - 70.7, 50 or 50 + 70.7 %, the difference at 120.7 (clipped to 100), 50 or -20.7 points
    spheres = (flights("resnet18", lambda k: 0) + flights("convnet", lambda k: 1) + flights("convnet-s1", lambda k: 0)
               + flights("vit_lstm", lambda k: 0))
    draws = {"convnet": ["convnet", "convnet-s1"]}
    one = resnet_no_better(spheres)  # ConvNet's own draw only: +100 points, decided, not reproduced
    pooled = resnet_no_better(spheres, draws)
    assert one.verdict == "not" and one.comparisons[0].diff == 1.0
    d = pooled.comparisons[0]
    assert (d.diff, d.high) == (0.5, 1.0) and d.low == pytest.approx(0.5 - 0.5 * 2**0.5)
    assert pooled.verdict == "reproduced"
    md = paired_findings_markdown(paired_findings(spheres, None, None, None, draws=draws))
    assert "training draws (a model by its draws' mean; one trained once borrows" in md
    lead = lead_table(spheres, "spheres", draws=draws)
    assert "seed 1" not in lead  # a draw is no row of its own
    assert "| ConvNet | +50 points [-21, +100], 20 pairs, 1 vs 2 draws |" in lead


def test_pooled_draw_variance_by_hand():
    # run 1: draws' means 1 and 3 (squares about their mean 2: 1 + 1, 1 degree of freedom); run 2: means 0, 0, 3
    # (mean 1; squares 1 + 1 + 4 = 6, 2 degrees); a run of one draw adds nothing: (2 + 6) / (1 + 2) = 8 / 3
    run1 = np.array([[1.0, 1.0], [2.0, 4.0]])
    run2 = np.array([[0.0, 0.0], [0.0, 0.0], [3.0, 3.0]])
    assert pooled_draw_variance([run1, run2, np.array([[5.0, 9.0]])]) == (pytest.approx(8 / 3), 3)
    assert pooled_draw_variance([np.array([[5.0, 9.0]])]) is None


def test_a_run_trained_once_borrows_the_pooled_spread():
    # ConvNet's two draws: 0 and 2 collisions a trial, so one draw's variance is 2. Every scene alike, so the
    # intervals are the borrowed normal terms alone: ResNet-18 (trained once, 1 collision) against the expert
    # (never trains: borrows nothing) 1 -+ 1.96 sqrt(2); against UNet+LSTM (trained once, 0) 1 -+ 1.96 sqrt(2 + 2)
    recs = (flights("convnet", lambda k: 0) + flights("convnet-s1", lambda k: 2) + flights("resnet18", lambda k: 1)
            + flights("unet_lstm", lambda k: 0) + flights("expert", lambda k: 0))
    draws = {"convnet": ["convnet", "convnet-s1"], "resnet18": ["resnet18"], "unet_lstm": ["unet_lstm"]}
    vs_expert = paired_difference(recs, "resnet18", "expert", "spheres", "collisions", draws=draws)
    assert vs_expert.borrowed_sd == pytest.approx(2**0.5) and vs_expert.diff == 1.0
    assert (vs_expert.low, vs_expert.high) == pytest.approx((1 - 1.96 * 2**0.5, 1 + 1.96 * 2**0.5), abs=0.08)
    assert "1 vs 1 draws (trained once: the pooled draw sd 1.41 borrowed)" in vs_expert.text()
    both = paired_difference(recs, "resnet18", "unet_lstm", "spheres", "collisions", draws=draws)
    assert (both.low, both.high) == pytest.approx((1 - 1.96 * 2, 1 + 1.96 * 2), abs=0.1)
    # the expert and straight flight against each other: no training, no borrowing, the constant difference
    plain = paired_difference(recs + flights("straight", lambda k: 3), "straight", "expert", "spheres",
                              "collisions", draws=draws)
    assert (plain.low, plain.diff, plain.high, plain.borrowed_sd) == (3.0, 3.0, 3.0, 0.0)


def test_borrowing_against_draws_matches_the_mixture_by_hand():
    # collisions per trial, every scene alike. ResNet-18 (trained once): 1. ConvNet's draws: 1 and 0 (variance
    # 1/2), spread to 0.5 -+ 0.5 sqrt(2), so their resampled mean is 0.5 - 0.707, 0.5 or 0.5 + 0.707 (p 1/4, 1/2,
    # 1/4); ResNet-18 adds a normal term of variance 1/2. The difference is a mixture of three normals (sd
    # sqrt(1/2)) at 0.5 + 0.707, 0.5, 0.5 - 0.707; its 2.5 % and 97.5 % quantiles, by root-finding, are the interval
    from scipy.optimize import brentq
    from scipy.stats import norm

    recs = flights("resnet18", lambda k: 1) + flights("convnet", lambda k: 1) + flights("convnet-s1", lambda k: 0)
    draws = {"convnet": ["convnet", "convnet-s1"], "resnet18": ["resnet18"]}
    d = paired_difference(recs, "resnet18", "convnet", "spheres", "collisions", draws=draws)
    centres = [0.5 + 0.5 * 2**0.5, 0.5, 0.5 - 0.5 * 2**0.5]

    def cdf(x):
        return sum(w * norm.cdf(x, c, 0.5**0.5) for w, c in zip([0.25, 0.5, 0.25], centres, strict=True))

    low, high = (brentq(lambda x, q=q: cdf(x) - q, -10, 10) for q in (0.025, 0.975))
    assert d.diff == 0.5 and (d.low, d.high) == pytest.approx((low, high), abs=0.04)
    assert (round(low, 2), round(high, 2)) == (-1.19, 2.19)  # wider than ConvNet's draws alone: 0.5 -+ 0.707


def test_calibration_script_shows_one_draw_deciding_between_equal_networks(capsys):
    calibration = load_script("paired_calibration")
    assert calibration.main(["--draws", "1x1", "4x4", "--studies", "60", "--resamples", "500",
                             "--draw-sd-points", "25"]) == 0
    rows = [line.split("|") for line in capsys.readouterr().out.splitlines() if line.startswith("| 1 vs 1")
            or line.startswith("| 4 vs 4")]
    one, four = (float(r[3]) for r in rows)  # the spread column
    # draws 25 points apart on the logit scale: one draw each decides most equal pairs, four each few
    assert one > 0.5 and four < 0.2
    # borrowing the spread of the other networks' draws (5, 3, 3) brings one draw each down to few
    assert float(rows[0][4]) < 0.2 and float(rows[1][4]) == four
    assert calibration.main(["--draws", "3"]) == 2 and "expected AxB" in capsys.readouterr().err
    # a lead of 10 points over scenes whose difficulty is N(0, 1) on the logit scale, checked by sampling
    difficulty = np.random.default_rng(0).normal(0.0, 1.0, 1_000_000)
    lead = calibration.logit_lead(10)
    gain = 1 / (1 + np.exp(difficulty - lead)) - 1 / (1 + np.exp(difficulty))
    assert gain.mean() == pytest.approx(0.10, abs=0.002)
    # the power: a network 30 points better, draws 1 point apart, 200 scenes: nearly every study decides it better;
    # the same lead drowned in draws 40 points apart, one draw each borrowing their spread: fewer than half do
    assert calibration.main(["--draws", "1x1", "--studies", "20", "--resamples", "500", "--scenes", "200",
                             "--draw-sd-points", "1", "--difference-points", "30"]) == 0
    out = capsys.readouterr().out
    assert "30 points better better (the power)" in out
    assert float(next(line for line in out.splitlines() if line.startswith("| 1 vs 1")).split("|")[4]) >= 0.9
    assert calibration.main(["--draws", "1x1", "--studies", "20", "--resamples", "500", "--scenes", "200",
                             "--draw-sd-points", "40", "--difference-points", "30"]) == 0
    assert float(next(line for line in capsys.readouterr().out.splitlines()
                      if line.startswith("| 1 vs 1")).split("|")[4]) < 0.5
