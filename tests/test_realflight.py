"""The paper's real-flight half in simulation: the avoidance onset, the paired map study, the paired verdict and
the onboard budget script, each on worked cases."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest
from helpers import load_benchmark, load_script

from vitfly.cli import main
from vitfly.errors import VitflyError
from vitfly.eval.avoidance_onset import Onset, avoidance_onset, distance_to_surface_m, paired_onset
from vitfly.eval.explain.frames import TrialFrames
from vitfly.eval.explain.study import map_finding, paired_map_difference, ticks_before_passing
from vitfly.eval.paired import claim_side, claims_verdict
from vitfly.sim.scenes import Scene

CYLINDER = np.array([10.0, 0.0, 0.0, 8.0, 0.5])  # x, y, z_bottom, z_top, radius: near face at x = 9.5


def _straight_path(xs, vy, speed=3.0):
    """Positions on the line (y 0, z 3.5) at ``xs``, commands (speed, vy, 0), one tick per 0.1 s."""
    xs = np.asarray(xs, dtype=float)
    position = np.stack([xs, np.zeros_like(xs), np.full_like(xs, 3.5)], axis=1)
    command = np.stack([np.full_like(xs, speed), np.asarray(vy, dtype=float), np.zeros_like(xs)], axis=1)
    return 0.1 * np.arange(len(xs)), position, command


def test_distance_to_surface_by_hand():
    # cylinder: beside it (radial 2 - 0.5), above it (vertical 1), diagonal (radial 3 - 0.5 = 2.5, vertical 1)
    d = distance_to_surface_m(np.array([[10.0, 2.0, 3.5], [10.0, 0.0, 9.0], [7.0, 0.0, 9.0], [10.2, 0.0, 1.0]]),
                              "cylinder", CYLINDER)
    np.testing.assert_allclose(d, [1.5, 1.0, math.hypot(2.5, 1.0), 0.0])
    # box x 8..9, y -0.5..0.5, z 0..8: from (5, 1, 3.5) the excess is (3, 0.5, 0)
    box = np.array([8.0, -0.5, 0.0, 9.0, 0.5, 8.0])
    np.testing.assert_allclose(distance_to_surface_m(np.array([[5.0, 1.0, 3.5]]), "box", box), [math.sqrt(9.25)])


def test_onset_is_the_first_tick_over_a_tenth_of_the_speed():
    # x 0..9 m; at 3 m/s the threshold is 0.3 m/s: 0.25 at x = 4 stays below it, -0.5 at x = 6 crosses it
    vy = [0, 0, 0, 0, 0.25, 0, -0.5, -1.0, -1.0, -1.0]
    t, pos, cmd = _straight_path(np.arange(10.0), vy)
    onset = avoidance_onset(t, pos, cmd, 3.0, "cylinder", CYLINDER)
    assert onset == Onset(distance_m=3.5, departed=True, tick=6, time_s=pytest.approx(0.6), command_y_mps=-0.5,
                          window_ticks=10)
    # a stricter threshold (0.2 x 3 = 0.6 m/s) moves it to x = 7: 2.5 m from the surface
    assert avoidance_onset(t, pos, cmd, 3.0, "cylinder", CYLINDER, threshold_fraction=0.2).distance_m == 2.5


def test_onset_ignores_departures_out_of_range_or_past_the_near_face():
    # obstacle near face at 9.5 m: a turn at x = 0 (9.5 m away, in range) counts; with range 5 m only the ticks
    # within 5 m (x >= 4.5) do, and the first turn there is at x = 8 (1.5 m)
    xs = np.array([0.0, 2.0, 4.0, 6.0, 8.0, 9.6, 11.0])
    t, pos, cmd = _straight_path(xs, [1.0, 0, 0, 0, 1.0, 1.0, 1.0])
    assert avoidance_onset(t, pos, cmd, 3.0, "cylinder", CYLINDER).distance_m == 9.5
    assert avoidance_onset(t, pos, cmd, 3.0, "cylinder", CYLINDER, range_m=5.0).distance_m == 1.5
    # never turning before the near face (the turns at 9.6 and 11 m come after it): distance 0, not departed
    t, pos, cmd = _straight_path(xs, [0, 0, 0, 0, 0, 1.0, 1.0])
    onset = avoidance_onset(t, pos, cmd, 3.0, "cylinder", CYLINDER)
    assert (onset.distance_m, onset.departed, onset.tick, onset.window_ticks) == (0.0, False, None, 5)


def test_claim_sides_and_the_verdict_rule():
    assert [claim_side(*ci) for ci in ((0.1, 0.5), (-0.5, -0.1), (-0.1, 0.2), (math.nan, 1.0))] == [
        "for", "against", "undecided", "undecided"]
    assert claims_verdict(["for", "for"]) == ("reproduced", "2 of 2 claims decided for, 0 against")
    assert claims_verdict(["for", "undecided"])[0] == "partly"
    assert claims_verdict(["for", "against"])[0] == "not"
    assert claims_verdict(["undecided", "undecided"])[0] == "cannot tell"
    assert claims_verdict([])[0] == "n/a"


def _onset(d):
    return Onset(d, d > 0, None, math.nan, math.nan, 1)


def test_paired_onset_on_hand_made_distances():
    # a avoids 1 m earlier than b in each of three scenes: the difference is exactly +1 with a point interval
    onsets = {}
    for seed, (da, db) in enumerate([(3.0, 2.0), (4.0, 3.0), (2.5, 1.5)]):
        onsets[("a", 3.0, seed)], onsets[("b", 3.0, seed)] = _onset(da), _onset(db)
    d = paired_onset(onsets, "a", "b")
    assert (d.pairs, d.scenes, d.diff_m, d.low_m, d.high_m, d.side) == (3, 3, 1.0, 1.0, 1.0, "for")
    assert d.mean_a_m == pytest.approx(9.5 / 3) and d.mean_b_m == pytest.approx(6.5 / 3)
    # differences +2, -2, +1, -1 over four scenes: mean 0, an interval around it, undecided
    onsets = {}
    for seed, (da, db) in enumerate([(3.0, 1.0), (1.0, 3.0), (2.0, 1.0), (1.0, 2.0)]):
        onsets[("a", 5.0, seed)], onsets[("b", 5.0, seed)] = _onset(da), _onset(db)
    d = paired_onset(onsets, "a", "b", speeds=[5.0])
    assert d.diff_m == 0.0 and d.low_m < 0 < d.high_m and d.side == "undecided"
    assert paired_onset(onsets, "a", "b", speeds=[7.0]) is None
    with pytest.raises(VitflyError, match="twice"):
        paired_onset(onsets, "a", "a")


def test_paired_map_difference_and_finding_on_hand_made_rows():
    rows = []
    for seed, (ca, cb, la, lb) in enumerate([(0.9, 0.7, 2.0, 1.0), (0.8, 0.6, 1.5, 1.5), (0.95, 0.75, 1.0, 2.0)]):
        rows += [{"seed": seed, "model": "vit", "map": "command", "consistency": ca, "edge_lift": la},
                 {"seed": seed, "model": "conv", "map": "command", "consistency": cb, "edge_lift": lb},
                 {"seed": seed, "model": "vit", "map": "attention", "consistency": 1.0, "edge_lift": 9.0}]
    d = paired_map_difference(rows, "vit", "conv", "consistency")
    assert d.trials == 3 and d.diff == pytest.approx(0.2) and d.side == "for"  # +0.2 in every trial
    f = map_finding(rows, "vit", "conv")
    # edge lift: +1, 0, -1: mean 0, undecided -> one claim for, one undecided: partly
    assert [c["side"] for c in f["comparisons"]] == ["for", "undecided"] and f["verdict"] == "partly"


def test_frames_stop_once_the_drone_has_passed_every_obstacle():
    scene = Scene("course", "easy", 0, np.zeros((0, 4)), CYLINDER[None], np.zeros((0, 6)))  # far face x = 10.5
    xs = np.array([9.0, 10.0, 10.5, 10.6, 12.0])
    frames = TrialFrames(np.zeros((5, 60, 90), np.float32), np.full(5, 3.0), np.tile([1.0, 0, 0, 0], (5, 1)),
                         0.1 * np.arange(5), np.stack([xs, np.zeros(5), np.full(5, 3.5)], axis=1))
    assert ticks_before_passing(frames, scene) == 3


def test_explain_trials_pairs_every_model_with_the_first(tmp_path, capsys, one_torch_thread):
    # two copies of the same random network: every difference is exactly 0, so nothing is decided
    out = tmp_path / "study"
    assert main(["explain", "--policy", "random:convnet", "random:convnet", "--name", "A", "B", "--env", "course",
                 "--preset", "easy", "--seed", "4", "--speed", "7", "--trials", "2", "--max-ticks", "3",
                 "--no-gif", "--frames", "2", "--out", str(out)]) == 0  # fmt: skip
    with open(out / "trials.csv") as f:
        rows = list(csv.DictReader(f))
    assert {(r["seed"], r["model"]) for r in rows} == {(s, m) for s in ("4", "5") for m in ("A", "B")}
    finding = json.loads((out / "paired.json").read_text())["findings"][0]
    assert (finding["a"], finding["b"], finding["verdict"]) == ("B", "A", "cannot tell")
    assert all(c["diff"] == 0.0 and c["trials"] == 2 for c in finding["comparisons"])
    assert "B vs A: **cannot tell**" in capsys.readouterr().out


def test_onboard_budget_script_on_a_tiny_setting(tmp_path, capsys, one_torch_thread):
    bench = load_benchmark("onboard_budget")
    out = tmp_path / "budget.json"
    assert bench.main(["--models", "convnet", "--ticks", "3", "--warmup", "1", "--frames", "2",
                       "--out", str(out)]) == 0  # fmt: skip
    payload = json.loads(out.read_text())
    assert payload["budget_ms"] == pytest.approx(1000 / 30) and payload["frames"] == 2
    (result,) = payload["results"]
    s = result["summary"]
    assert result["model"] == "convnet" and set(s) == {"sensor", "network", "total"}
    # the total of each tick is its sensor part plus its network part, so the means add up
    wall = {part: s[part]["wall"]["mean_ms"] for part in s}
    assert wall["total"] == pytest.approx(wall["sensor"] + wall["network"])
    assert s["total"]["wall"]["mean_share"] == pytest.approx(s["total"]["wall"]["mean_ms"] / (1000 / 30))
    assert "| convnet | total |" in capsys.readouterr().out
    assert bench.main(["--models", "resnet18", "--ticks", "1"]) == 2
    assert "'resnet18' is not shipped" in capsys.readouterr().err


def test_explain_trials_refuses_a_map_a_policy_cannot_make(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["explain", "--policy", "random:convnet", "random:convnet", "--trials", "2", "--compare-map",
                 "attention", "--out", str(out)]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--compare-map attention: convnet (random weights) has no such map" in err[0]
    assert not out.exists()


def test_flown_frames_through_the_d435_model_keep_exact_edges():
    from vitfly.eval.explain import fly_trial
    from vitfly.sim.policies import ExpertPolicy
    from vitfly.sim.rollout import RolloutConfig, TaskConfig
    from vitfly.sim.scenes import make_scene
    from vitfly.sim.sensor_models import StereoDepthConfig

    cfg = RolloutConfig(sensor=StereoDepthConfig(), task=TaskConfig(timeout_s=0.2, timeout_speed_factor=0.0))
    frames = fly_trial(make_scene("course", "easy", 2), 5.0, ExpertPolicy(), "expert", cfg)  # a column 6 m ahead
    # the top-left corner looks at the sky (the column is in the middle): no reading, which the deployment sets to
    # 0.8 (the clean render reads 1.0 there)
    np.testing.assert_array_equal(frames.depth[:, 0, :10], np.float32(0.8))
    assert frames.edge_source == "scene" and frames.info["sensor"] == "d435" and frames.edges[0].any()


def test_explain_bad_sensor_field_is_one_line(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["explain", "--policy", "random:convnet", "--sensor", "d435", "baseline_m=-1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sensor.baseline_m" in err[0] and not out.exists()


def test_map_finding_decides_the_claims_of_both_depths_together(tmp_path, capsys):
    def paired(path, sides):
        comparisons = [{"a": "ViT+LSTM", "b": "ConvNet", "metric": m, "map_kind": "command", "diff": 0.1,
                        "low": lo, "high": hi, "trials": 20, "side": side}
                       for m, (lo, hi, side) in zip(("consistency", "edge_lift"), sides, strict=True)]
        path.write_text(json.dumps({"findings": [{"a": "ViT+LSTM", "b": "ConvNet", "comparisons": comparisons}]}))
        return str(path)

    exact = paired(tmp_path / "e.json", [(-0.1, 0.2, "undecided"), (0.1, 0.5, "for")])
    d435 = paired(tmp_path / "d.json", [(0.05, 0.1, "for"), (-0.2, 0.3, "undecided")])
    out = tmp_path / "finding.json"
    map_finding = load_script("map_finding")
    assert map_finding.main(["--paired", "exact", exact, "--paired", "d435", d435, "--out", str(out)]) == 0
    assert json.loads(out.read_text())["verdict"] == "partly"  # 2 of 4 for, none against
    assert "verdict: partly (2 of 4 claims decided for, 0 against)" in capsys.readouterr().out


def test_avoidance_onset_script_names_a_missing_sweep(tmp_path, capsys):
    assert load_script("avoidance_onset").main(["--sweep", "exact", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope/trials.jsonl: missing" in err[0]


def test_onset_finding_from_records_on_a_course_box():
    from vitfly.eval.avoidance_onset import onset_finding, onset_markdown
    from vitfly.eval.records import TrialRecord, round_path

    # course/easy seed 3 is one box, x 14.287..15.282 m, y -0.645..0.350 m, z 0..8 m: on the line at z 3.5 m the
    # distance to it is 14.287 - x. "a" turns at x = 10 m (4.287 m), "b" at x = 12 m (2.287 m): a - b = 2 m exactly
    xs = np.concatenate([np.arange(0.0, 15.0), [21.0]])  # x = 21 m: more than 5 m past the far face (floor tick)

    def record(policy, turn_x):
        t, pos, cmd = _straight_path(xs, np.where((xs >= turn_x) & (xs < 15), 1.0, 0.0))
        cmd[-1, 1] = 0.03  # empty space: 0.01 x the speed
        return TrialRecord(policy, "course", 3.0, 0, 3, True, True, True, "goal", {},
                           round_path(t, pos, cmd, cmd, np.zeros(len(xs), bool)), {}, "x", preset="easy")

    f = onset_finding({"exact": [record("a", 10.0), record("b", 12.0)]}, "a", "b")
    s = f["sensors"]["exact"]
    assert s["mean_onset_m"]["a"]["3"] == pytest.approx(14.28709738 - 10) and s["pooled"]["pairs"] == 1
    assert s["pooled"]["diff_m"] == pytest.approx(2.0) and s["straight_floor"]["a"] == {"p99": 0.01, "ticks": 1}
    assert f["verdict"] == "reproduced" and "| exact | 3 m/s | 4.29 | 2.29 | +2.00 [+2.00, +2.00], 1 |" in \
        onset_markdown(f)
    with pytest.raises(VitflyError, match="has 6 obstacles"):
        onset_finding({"exact": [dataclasses.replace(record("a", 10.0), preset="hard", scene_seed=2)]}, "a", "b")
