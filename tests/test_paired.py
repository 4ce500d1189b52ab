"""Paired comparisons over shared scenes (vitfly.eval.paired): values worked out by hand."""

import math

import numpy as np
import pytest
from helpers import load_script
from scipy.stats import beta

from vitfly.errors import VitflyError
from vitfly.eval.paired import mcnemar_exact, paired_difference, pairs, scene_bootstrap_interval
from vitfly.eval.records import TrialRecord


def rec(policy, scene, speed, success=True, collisions=0.0, env="spheres"):
    return TrialRecord(policy=policy, env=env, speed=speed, trial=scene, scene_seed=1000 + scene,
                       success_paper=success, success_strict=success, reached_goal=True, end_reason="goal",
                       metrics={"collisions": collisions, "energy_cost": math.nan}, path={}, setup={},
                       setup_id="s")


def test_mcnemar_exact_by_hand():
    # 10 pairs where a alone succeeded, 2 where b alone did: 2 * P(X <= 2), X ~ Bin(12, 1/2) = 2 * 79 / 4096
    assert mcnemar_exact(10, 2) == pytest.approx(2 * 79 / 4096)
    assert mcnemar_exact(2, 10) == pytest.approx(2 * 79 / 4096)
    assert mcnemar_exact(0, 0) == 1.0
    assert mcnemar_exact(3, 3) == 1.0


def test_pairs_match_scene_and_speed_only():
    recs = [rec("a", 0, 3.0), rec("a", 1, 3.0), rec("a", 2, 5.0), rec("b", 0, 3.0), rec("b", 2, 5.0),
            rec("b", 1, 5.0),                      # b flew scene 1 at 5 m/s, a at 3 m/s: no pair
            rec("b", 0, 3.0, env="trees")]         # another env: never paired
    scene, speed, va, vb = pairs(recs, "a", "b", "spheres", "success")
    assert scene.tolist() == [1000, 1002] and speed.tolist() == [3.0, 5.0]
    # a metric undefined for a trial drops its pair
    assert len(pairs(recs, "a", "b", "spheres", "energy_cost")[2]) == 0


def test_success_difference_counts_discordant_pairs():
    # 40 scenes: both succeed in 20, a alone in 12, b alone in 3, neither in 5 -> diff (12 - 3) / 40
    outcomes = [(1, 1)] * 20 + [(1, 0)] * 12 + [(0, 1)] * 3 + [(0, 0)] * 5
    recs = [r for k, (x, y) in enumerate(outcomes) for r in (rec("a", k, 3.0, bool(x)), rec("b", k, 3.0, bool(y)))]
    d = paired_difference(recs, "a", "b", "spheres")
    assert (d.pairs, d.scenes, d.a_only, d.b_only) == (40, 40, 12, 3)
    assert d.mean_a == pytest.approx(32 / 40) and d.mean_b == pytest.approx(23 / 40)
    assert d.diff == pytest.approx(9 / 40)
    assert d.mcnemar_p == pytest.approx(2 * (1 + 15 + 105 + 455) / 2**15)  # 2 P(X <= 3), X ~ Bin(15, 1/2)
    # the exact interval behind McNemar's test: Clopper-Pearson of 12 of the 15 discordant pairs (beta quantiles),
    # as a difference (2 p - 1) * 15 / 40
    lo, hi = beta.ppf(0.025, 12, 4), beta.ppf(0.975, 13, 3)
    assert (d.low, d.high) == pytest.approx(((2 * lo - 1) * 15 / 40, (2 * hi - 1) * 15 / 40))
    assert d.low > 0  # McNemar's p = 0.035 < 0.05: the interval excludes 0
    assert d.decided and d.better == "a" and d.verdict == "a better"
    assert d.text().startswith("+22 points [")


def test_lower_collisions_is_better():
    recs = [r for k in range(30) for r in (rec("a", k, 7.0, collisions=0.0), rec("b", k, 7.0, collisions=1.0 + k % 3))]
    d = paired_difference(recs, "a", "b", "spheres", "collisions")
    assert d.diff == pytest.approx(-2.0) and d.high < 0 and d.better == "a"


def test_constant_difference_is_its_own_interval():
    recs = [r for k in range(10) for r in (rec("a", k, 3.0, collisions=2.0), rec("b", k, 3.0, collisions=1.0))]
    d = paired_difference(recs, "a", "b", "spheres", "collisions")
    assert (d.low, d.diff, d.high) == (1.0, 1.0, 1.0)
    same = [r for k in range(10) for r in (rec("a", k, 3.0), rec("b", k, 3.0))]
    d = paired_difference(same, "a", "b", "spheres")
    assert (d.low, d.high) == (0.0, 0.0) and not d.decided and d.verdict == "cannot tell"


def test_bootstrap_width_matches_the_standard_error():
    # 400 scenes of normal differences, sd 1: a 95 % interval of the mean spans about 2 x 1.96 / sqrt(400)
    rng = np.random.default_rng(3)
    diff = rng.normal(0.5, 1.0, 400)
    low, high = scene_bootstrap_interval(np.arange(400), diff)
    half = 1.96 * diff.std(ddof=1) / math.sqrt(400)
    assert low < diff.mean() < high
    assert (high - low) / 2 == pytest.approx(half, rel=0.1)


def test_bootstrap_resamples_scenes_not_pairs():
    # each scene flown at three speeds with the same difference: no more information than one speed,
    # so the interval must not narrow (a bootstrap over pairs would narrow it by sqrt(3))
    rng = np.random.default_rng(4)
    per_scene = rng.normal(0.0, 1.0, 60)
    one = scene_bootstrap_interval(np.arange(60), per_scene)
    three = scene_bootstrap_interval(np.repeat(np.arange(60), 3), np.repeat(per_scene, 3))
    assert three == pytest.approx(one, abs=1e-9)


def test_no_pairs_and_bad_metric():
    assert paired_difference([rec("a", 0, 3.0)], "a", "b", "spheres") is None
    with pytest.raises(VitflyError, match="paired metric 'speed'"):
        paired_difference([], "a", "b", "spheres", "speed")


# -- the paper's findings decided on pairs (vitfly.eval.paired_findings) ----------------------------------

from vitfly.eval.paired_findings import (  # noqa: E402
    beats_expert_fast,
    lead_table,
    lowest_collisions_fast,
    paired_findings,
    paired_findings_markdown,
    resnet_no_better,
    state_helps_vit_lstm,
)


def flights(policy, collisions, speed=7.0, env="spheres", scenes=30):
    """``scenes`` trials of one policy; ``collisions(k)`` per scene k; success = no collision."""
    return [rec(policy, k, speed, success=collisions(k) == 0, collisions=float(collisions(k)), env=env)
            for k in range(scenes)]


def test_lowest_collisions_verdicts():
    base = flights("vit_lstm", lambda k: 0) + flights("convnet", lambda k: 1 + k % 2)
    f = lowest_collisions_fast(base)
    assert f.verdict == "reproduced" and [(d.a, d.b) for d in f.comparisons] == [("vit_lstm", "convnet")]
    # a model flying exactly as ViT+LSTM: that claim is undecided, so only partly
    assert lowest_collisions_fast(base + flights("lstmnet", lambda k: 0)).verdict == "partly"
    # a model decided better than ViT+LSTM: not
    worse = flights("vit_lstm", lambda k: 1) + flights("convnet", lambda k: 0)
    assert lowest_collisions_fast(worse).verdict == "not"
    # nobody at 6-7 m/s
    assert lowest_collisions_fast(flights("vit_lstm", lambda k: 0, speed=3.0)).verdict == "n/a"


def test_cannot_tell_when_no_claim_is_decided():
    # ViT+LSTM one collision fewer in 1 of 30 scenes and one more in another: mean 0, interval spans 0
    noisy = flights("vit_lstm", lambda k: {0: 0, 1: 2}.get(k, 1)) + flights("convnet", lambda k: 1)
    assert lowest_collisions_fast(noisy).verdict == "cannot tell"


def test_only_vit_lstm_below_the_expert():
    expert = flights("expert", lambda k: 2)
    alone = beats_expert_fast(expert + flights("vit_lstm", lambda k: 0) + flights("convnet", lambda k: 2))
    assert alone.verdict == "reproduced"
    shared = beats_expert_fast(expert + flights("vit_lstm", lambda k: 0) + flights("convnet", lambda k: 0))
    assert shared.verdict == "partly" and "ConvNet" in shared.why
    assert beats_expert_fast(expert + flights("vit_lstm", lambda k: 3)).verdict == "not"


def test_resnet_and_state_findings():
    better = flights("resnet18", lambda k: 0, speed=3.0) + flights("convnet", lambda k: 1, speed=3.0)
    assert resnet_no_better(better).verdict == "not"
    alike = flights("resnet18", lambda k: k % 2, speed=3.0) + flights("convnet", lambda k: (k + 1) % 2, speed=3.0)
    f = resnet_no_better(alike)
    assert f.verdict == "reproduced" and "at most +" in f.why
    abl = [*flights("vit_lstm", lambda k: 0, env="spheres"), *flights("vit_lstm-nostate", lambda k: 1, env="spheres"),
           *flights("vit_lstm", lambda k: 0, env="trees"), *flights("vit_lstm-nostate", lambda k: 0, env="trees")]
    f = state_helps_vit_lstm(abl)
    assert f.verdict == "partly" and len(f.comparisons) == 2  # decided in spheres, a tie in trees


def test_findings_table_and_lead_table():
    spheres = (flights("vit_lstm", lambda k: 0) + flights("convnet", lambda k: 1) + flights("expert", lambda k: 1)
               + flights("straight", lambda k: 3))
    findings = paired_findings(spheres, None, None, None)
    md = paired_findings_markdown(findings)
    assert "| ViT+LSTM vs ConvNet, spheres | collisions per trial | -1.00 [-1.00, -1.00], 30 pairs | for |" in md
    assert "Verdicts:" in md and "n/a" in md  # trees, window, ablation not flown
    lead = lead_table(spheres, "spheres")
    # success: ViT+LSTM 30/30, ConvNet 0/30 -> +100 points at 7 m/s, all 30 pairs discordant: Clopper-Pearson
    # lower bound of 30/30 is 0.025 ** (1 / 30), so the difference's is 2 * 0.8843 - 1 = +77 points; decided (*)
    assert "| ConvNet | +100 points [+77, +100], 30 pairs, McNemar p=1.9e-09 * |" in lead


def test_paired_csv_rows_per_speed_and_pooled():
    from vitfly.eval.paired import paired_csv, paired_rows

    recs = (flights("a", lambda k: 0, speed=3.0, scenes=5) + flights("a", lambda k: 1, speed=7.0, scenes=5)
            + flights("b", lambda k: 1, speed=3.0, scenes=5) + flights("b", lambda k: 1, speed=7.0, scenes=5))
    rows = paired_rows(recs)
    # one pair (a, b), one env, two metrics, speeds 3, 7 and all
    assert [(r["metric"], r["speed"]) for r in rows] == [("success", "3"), ("success", "7"), ("success", "all"),
                                                        ("collisions", "3"), ("collisions", "7"), ("collisions", "all")]
    pooled = rows[2]
    assert pooled["pairs"] == 10 and pooled["scenes"] == 5 and pooled["diff"] == pytest.approx(0.5)
    assert pooled["mcnemar_p"] is None  # pooled pairs share scenes: not independent, bootstrap only
    text = paired_csv(rows)
    assert text.splitlines()[0].startswith("env,metric,a,b,speed,pairs")
    # 5 of 5 discordant for a: Clopper-Pearson lower bound 0.025 ** (1 / 5) = 0.4782 -> 2 * 0.4782 - 1
    assert text.splitlines()[1] == "spheres,success,a,b,3,5,5,1,0,1,-0.0436475,1,0.0625,cannot tell"


def test_paired_findings_figure_draws_each_claim_where_its_interval_lies(tmp_path):
    import matplotlib.colors as mcolors

    from vitfly.eval.paired_findings import PairedFinding
    from vitfly.eval.paper_figures import (
        DECIDED_COLOURS,
        draw_paired_differences,
        finding_panels,
        paired_findings_figure,
    )

    # collisions per trial, ViT+LSTM 1 a scene: ConvNet 2 (-1, for), LSTMnet 1 (0, cannot tell), UNet+LSTM 0 (+1,
    # against: fewer collisions is better); every scene alike, so each interval is its difference alone
    spheres = (flights("vit_lstm", lambda k: 1) + flights("convnet", lambda k: 2) + flights("lstmnet", lambda k: 1)
               + flights("unet_lstm", lambda k: 0))
    finding = lowest_collisions_fast(spheres)
    by_b = {d.b: d for d in finding.comparisons}
    assert {b: (d.diff, d.low, d.high) for b, d in by_b.items()} == {
        "convnet": (-1.0, -1.0, -1.0), "lstmnet": (0.0, 0.0, 0.0), "unet_lstm": (1.0, 1.0, 1.0)}
    # success in points: ViT+LSTM 30 of 30, ConvNet 0 of 30: +100 [+77, +100] (test_findings_table_and_lead_table)
    success = paired_difference(flights("vit_lstm", lambda k: 0) + flights("convnet", lambda k: 1),
                                "vit_lstm", "convnet", "spheres", "success")
    fig = draw_paired_differences([("collisions", finding.comparisons), ("success", [success])])
    ax_collisions, ax_success = fig.axes
    colour = {k: mcolors.to_rgba(c) for k, c in DECIDED_COLOURS.items()}
    dots = [line for line in ax_collisions.lines if line.get_marker() == "o"]
    drawn = sorted((float(line.get_xdata()[0]), mcolors.to_rgba(line.get_color())) for line in dots)
    assert drawn == [(-1.0, colour["for"]), (0.0, colour["undecided"]), (1.0, colour["against"])]
    bars = [seg for coll in ax_collisions.collections for seg in coll.get_segments()]
    assert sorted((s[0][0], s[1][0]) for s in bars) == [(-1.0, -1.0), (0.0, 0.0), (1.0, 1.0)]
    (dot,) = [line for line in ax_success.lines if line.get_marker() == "o"]
    (bar,) = ax_success.collections[0].get_segments()
    assert dot.get_xdata()[0] == 100.0 and round(bar[0][0]) == 77 and bar[1][0] == 100.0
    assert [t.get_text() for t in ax_success.get_yticklabels()] == ["ViT+LSTM - ConvNet, spheres, 7 m/s (30 pairs)"]
    assert ax_success.get_xlabel() == "A - B: success (points)"
    with pytest.raises(ValueError, match="one panel, one metric"):
        draw_paired_differences([("mixed", [success, by_b["convnet"]])])

    # a finding on two metrics: a panel each; none compared: no figure
    two = PairedFinding("two", "claim", "success", "rule", "partly", [by_b["convnet"], success])
    assert finding_panels([two, lowest_collisions_fast([])]) == [("claim: partly", [by_b["convnet"]]),
                                                                  ("claim: partly", [success])]
    path = paired_findings_figure([two, lowest_collisions_fast([])], tmp_path / "paired.png")
    assert path.stat().st_size > 10_000
    assert paired_findings_figure([lowest_collisions_fast([])], tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


def test_paired_figure_script_draws_a_published_outcomes_file(tmp_path, capsys):

    from vitfly.eval.records import write_outcomes

    script = load_script("paired_figure")
    recs = (flights("a", lambda k: 0) + flights("b", lambda k: 1) + flights("a", lambda k: 0, speed=3.0)
            + flights("b", lambda k: k % 2, speed=3.0))
    write_outcomes(tmp_path / "outcomes.jsonl.gz", recs)
    out = tmp_path / "fig.png"
    assert script.main([str(tmp_path), "--pair", "a", "b", "--envs", "spheres", "--metrics", "success",
                        "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    # 7 m/s: a 30 of 30, b 0 of 30, as test_findings_table_and_lead_table; 3 m/s: b fails on the 15 odd scenes, so
    # 15 discordant pairs, all a's: Clopper-Pearson's lower bound 0.025 ** (1 / 15) = 0.782 makes the difference's
    # (2 * 0.782 - 1) * 15 / 30 = +28 points; McNemar p = 2 * 0.5 ** 15 = 6.1e-05
    assert lines[0] == "success    a - b, spheres, 3 m/s: +50 points [+28, +50], 30 pairs, McNemar p=6.1e-05"
    assert lines[1] == "success    a - b, spheres, 7 m/s: +100 points [+77, +100], 30 pairs, McNemar p=1.9e-09"
    assert lines[2].startswith("success    a - b, spheres, 3/7 m/s: +75 points [")  # the 60 pairs pooled
    assert out.stat().st_size > 10_000
    assert script.main([str(tmp_path), "--pair", "a", "c", "--out", str(tmp_path / "no.png")]) == 1
    assert "no shared trials of c (flown: a, b)" in capsys.readouterr().err and not (tmp_path / "no.png").exists()


def test_paired_figure_script_pairs_two_sweeps_that_flew_one_label(tmp_path, capsys):
    from vitfly.eval.records import write_outcomes

    script = load_script("paired_figure")
    # both sweeps flew a "convnet" on the same scenes: at 7 m/s the first's 30 trials succeed, the second's fail
    (tmp_path / "new").mkdir(), (tmp_path / "old").mkdir()
    write_outcomes(tmp_path / "new" / "outcomes.jsonl.gz",
                   flights("convnet", lambda k: 0) + flights("convnet", lambda k: 1, speed=3.0))
    write_outcomes(tmp_path / "old" / "outcomes.jsonl.gz",
                   flights("convnet", lambda k: 1) + flights("convnet", lambda k: 1, speed=3.0))
    out = tmp_path / "fig.png"
    assert script.main([f"new={tmp_path / 'new'}", f"old={tmp_path / 'old'}", "--speeds", "7", "--pair",
                        "new/convnet", "old/convnet", "--envs", "spheres", "--metrics", "success",
                        "--out", str(out)]) == 0
    # 7 m/s only (3 m/s left out, so nothing pooled): 30 discordant pairs, as the 7 m/s line above
    assert capsys.readouterr().out.splitlines()[:-1] == [
        "success    new/convnet - old/convnet, spheres, 7 m/s: +100 points [+77, +100], 30 pairs, McNemar p=1.9e-09"]


def test_a_study_results_json_gives_back_its_paired_findings(tmp_path, capsys):
    import json

    from vitfly.eval.paired import PairedDifference
    from vitfly.eval.paired_findings import PairedFinding

    spheres = (flights("vit_lstm", lambda k: 1) + flights("convnet", lambda k: 2) + flights("unet_lstm", lambda k: 0))
    findings = paired_findings(spheres, None, None, None)
    kept = json.loads(json.dumps({"paired_findings": [f.to_dict() for f in findings]}))  # as results.json keeps them
    back = [PairedFinding.from_dict(f) for f in kept["paired_findings"]]
    assert back == findings  # numbers, speeds (a tuple again) and verdicts
    with pytest.raises(VitflyError, match="results.json: comparison 0: not a paired difference"):
        PairedDifference.from_dict({"metric": "success"}, "results.json: comparison 0")

    script = load_script("paired_figure")
    (tmp_path / "results.json").write_text(json.dumps(kept))
    assert script.main([str(tmp_path / "results.json"), "--out", str(tmp_path / "paired.png")]) == 0
    assert (tmp_path / "paired.png").stat().st_size > 10_000
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "results.json").write_text("{}")
    assert script.main([str(tmp_path / "bad" / "results.json"), "--out", str(tmp_path / "bad.png")]) == 1
    assert "not a study's results.json with paired_findings (KeyError" in capsys.readouterr().err
