"""benchmarks/sim_agreement.py's pairing and counting, on hand-made records (no flight), and benchmarks/sim_scale.py
end to end (slow)."""

import json

import pytest
from helpers import load_benchmark

from vitfly.eval.records import TrialRecord


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("sim_agreement")


def rec(label, trial, success=True, goal=True, collisions=0, speed=3.0):
    return TrialRecord(policy=label, env="spheres", speed=speed, trial=trial, scene_seed=trial,
                       success_paper=success, success_strict=success and goal, reached_goal=goal,
                       end_reason="goal" if goal else "timeout", metrics={"collisions": collisions}, path={},
                       setup={}, setup_id="s")


def test_agreement_counts_outcomes_pair_by_pair(bench):
    f64 = [rec("expert-float64", 0), rec("expert-float64", 1, success=False, collisions=1),
           rec("expert-float64", 2, success=False, collisions=1), rec("expert-float64", 3),
           rec("expert-float64", 4, speed=5.0)]
    # trial 1: same outcome; trial 2: two collisions instead of one (disagrees, success alike);
    # trial 3: float32 collides (a success flip); trial 4 at 5 m/s: goal missed (disagrees); trial 9 unpaired
    f32 = [rec("expert-float32", 0), rec("expert-float32", 1, success=False, collisions=1),
           rec("expert-float32", 2, success=False, collisions=2), rec("expert-float32", 3, success=False, collisions=1),
           rec("expert-float32", 4, goal=False, speed=5.0), rec("expert-float32", 9)]
    row = bench.agreement(f64 + f32, "expert")
    assert (row["pairs"], row["agree"]) == (5, 2)
    assert row["agreement"] == pytest.approx(0.4)
    assert row["success_flips"] == {"float64 succeeds, float32 not": 1}
    assert row["success_float64"] == pytest.approx(3 / 5) and row["success_float32"] == pytest.approx(2 / 5)
    # Clopper-Pearson for 2 of 5 (from beta quantiles): 0.0527 .. 0.8534
    assert row["ci95"] == pytest.approx([0.05274, 0.85337], abs=1e-4)
    # endings (success, end reason): trials 0, 1 and 2 alike (2's extra collision aside); 3 flips success, 4 ends
    # in a timeout instead of the goal: 3 of 5; Clopper-Pearson 0.1466 .. 0.9473
    assert (row["agree_end"], row["agreement_end"]) == (3, pytest.approx(0.6))
    assert row["ci95_end"] == pytest.approx([0.14663, 0.94726], abs=1e-4)


@pytest.mark.slow
def test_sim_scale_flies_the_same_trials_with_both_engines(tmp_path, monkeypatch):
    # benchmarks/sim_scale.py end to end, tiny and eager: in float64 both engines fly the same trials (exact
    # engines, the same scenes; 3 s each) and collect the same frames (no --warm: eager, a rerun adds nothing)
    scale = load_benchmark("sim_scale")
    out = tmp_path / "scale.json"
    monkeypatch.setattr("sys.argv", ["sim_scale", "--eager", "--dtype", "float64", "--trials", "3",
                                     "--numpy-trials", "3", "--num-envs", "3", "--flights", "2",
                                     "--numpy-flights", "2", "--timeout", "3", "--json", str(out)])
    scale.main()
    got = json.loads(out.read_text())
    ev, co = got["evaluation"], got["collection"]
    assert ev["batched"]["trials"] == ev["numpy"]["trials"] == 3
    assert ev["batched"]["success"] == ev["numpy"]["success"]
    assert co["batched"]["frames"] == co["numpy"]["frames"] > 0
    assert ev["ratio"] == pytest.approx(ev["batched"]["trials_per_min"] / ev["numpy"]["trials_per_min"])
    assert co["ratio"] == pytest.approx(co["batched"]["frames_per_s"] / co["numpy"]["frames_per_s"])
    assert "batched_warm" not in ev and "batched_warm" not in co  # the second run only with --warm
