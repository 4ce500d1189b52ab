"""The report of `vitfly reproduce` from a study's published flights (``report.published``): the paper arm's
committed outcomes, reported in an empty run directory, and the rules of joining them to a run's own flights."""

from __future__ import annotations

import dataclasses
import gzip
import json
from pathlib import Path

import pytest
import yaml

from vitfly.errors import VitflyError
from vitfly.eval import records
from vitfly.workflows.reproduce_config import load_reproduce_config
from vitfly.workflows.reproduce_report import _summary, stage_report, study_label

ROOT = Path(__file__).resolve().parents[1]
PUBLISHED = ROOT / "docs/results/paper_budget"


def outcomes(folder: Path) -> list[dict]:
    with gzip.open(folder / records.OUTCOMES_FILE, "rt") as f:
        return [json.loads(line) for line in f]


def paper_config(out: Path, **published):
    cfg = load_reproduce_config(ROOT / "configs/reproduce.yaml", "paper", {"out": str(out)})
    given = {k: str(ROOT / v) for k, v in cfg.report.published.items() if k not in published}
    given.update(published)
    return dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, published=given))


def test_the_study_label_of_a_run_folder():
    assert study_label("convnet-state") == "convnet"
    assert study_label("lstmnet-state-s1") == "lstmnet-s1"
    assert study_label("unet_lstm-nostate") == "unet_lstm-nostate"
    assert [study_label(p) for p in ("convnet", "convnet-s2", "expert", "straight")] == \
        ["convnet", "convnet-s2", "expert", "straight"]


def test_the_paper_arm_reports_from_its_published_flights(tmp_path):
    """Nothing flown here: every number comes from the committed outcomes, which keep no paths."""
    cfg = paper_config(tmp_path / "study")
    result = stage_report(cfg)

    # the learned models' time in collision against the expert's, by each network's draws' mean, worked out from
    # the raw records: spheres, 3 and 7 m/s pooled
    spheres = outcomes(PUBLISHED / "evaluation_native/spheres")

    def mean_time(policy: str) -> float:
        v = [r["metrics"]["time_in_collision_s"] for r in spheres if r["policy"] == policy and r["speed"] in (3, 7)]
        assert len(v) == 200
        return sum(v) / len(v)

    finding = next(f for f in result["paired_findings"] if f["key"] == "time_in_collision")
    draws: dict[str, list[str]] = {}  # network -> its draws' labels (convnet, convnet-s1, ...), as flown so far
    for policy in sorted({r["policy"] for r in spheres} - {"expert", "straight"}):
        draws.setdefault(policy.split("-s")[0], []).append(policy)
    assert {"convnet", "lstmnet", "unet_lstm"} <= set(draws)  # the networks the CPU trained (the ViTs: GPU slots)
    assert {c["a"] for c in finding["comparisons"]} == set(draws)
    for c in finding["comparisons"]:
        by_hand = sum(mean_time(p) for p in draws[c["a"]]) / len(draws[c["a"]]) - mean_time("expert")
        assert c["diff"] == pytest.approx(by_hand, abs=1e-9)
        assert (c["pairs"], c["draws_a"], c["draws_b"]) == (200, len(draws[c["a"]]), 1)
        if c["a"] in ("convnet", "lstmnet", "unet_lstm"):  # results.md: -0.16 [-0.27, -0.06] ...
            assert c["low"] < c["diff"] < c["high"] < 0 and c["verdict"] == f"{c['a']} better"
    if set(draws) == {"convnet", "lstmnet", "unet_lstm"}:
        assert finding["verdict"] == "reproduced"  # each interval below 0

    # the ablation table reads the hand-flown labels (convnet-state) as the study's (convnet)
    ablation = outcomes(PUBLISHED / "ablation_native")
    cell = [r["outcome"]["success_paper"] for r in ablation
            if (r["policy"], r["env"], r["speed"]) == ("convnet-state", "spheres", 3.0)]
    assert len(cell) == 50
    row = next(line for line in (cfg.out_dir / "ablation.md").read_text().splitlines()
               if line.startswith("| spheres | ConvNet |"))
    assert row.split("|")[4].strip() == f"{round(100 * sum(cell) / 50)} (63)"  # 3 m/s with the state (paper)

    # a window without paths: its rates count, its path figure is not drawn
    assert "window_paths" not in result["files"]
    window = next(f for f in result["findings"] if f["key"] == "window_only_vit")
    if not {"vit", "vit_lstm"} & set(draws):
        assert window["verdict"] == "n/a"  # the finding needs a ViT model's flights
    assert (cfg.out_dir / "figures" / "spheres_collision_metrics.png").stat().st_size > 0


def test_a_published_label_flown_with_another_setup_is_refused(tmp_path):
    """A run directory whose `convnet` is not the published `convnet` (another policy) cannot be reported beside it."""
    cfg = paper_config(tmp_path / "study")
    mine = next(r for r in records.read_report_records(PUBLISHED / "evaluation_native/window") if r.policy == "convnet")
    other = dataclasses.replace(mine, setup_id="0" * 16, setup={**mine.setup, "policy_id": "f" * 16})
    records.append_record(cfg.eval_dir("window") / records.TRIALS_FILE, other)
    with pytest.raises(VitflyError, match="policy label 'convnet' holds trials flown with different setups"):
        stage_report(cfg)
    assert not (cfg.out_dir / "results.md").exists()


def test_the_run_directory_s_own_flight_of_a_trial_wins(tmp_path):
    """The same trial (label, setup, env, speed, index) in both: the run directory's record is reported."""
    cfg = paper_config(tmp_path / "study")
    published = [r for r in records.read_report_records(PUBLISHED / "evaluation_native/window")
                 if r.policy == "expert"]
    flown = next(r for r in published if r.success_paper)
    crashed = dataclasses.replace(flown, success_paper=False, success_strict=False,
                                  metrics={**flown.metrics, "success_paper": False, "collisions": 1})
    records.append_record(cfg.eval_dir("window") / records.TRIALS_FILE, crashed)
    rows, _ = _summary(cfg.eval_dir("window"), cfg.report.published["window"])
    expert = next(r for r in rows if r["policy"] == "expert")
    successes = sum(r.success_paper for r in published)
    assert expert["trials"] == len(published) == 50
    assert expert["success_paper_rate"] == pytest.approx((successes - 1) / 50)


def test_a_missing_published_folder_is_one_line(tmp_path):
    cfg = paper_config(tmp_path / "study", window=str(tmp_path / "nowhere"))
    with pytest.raises(VitflyError, match=r"report.published.window: .*nowhere holds no outcomes.jsonl.gz"):
        stage_report(cfg)


def test_an_unknown_published_sweep_is_one_line(tmp_path):
    data = yaml.safe_load((ROOT / "configs/reproduce.yaml").read_text())
    data["report"] = {"published": {"forest": "docs/results"}}
    path = tmp_path / "reproduce.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(VitflyError, match="report.published has 'forest'; expected sweeps: spheres, trees"):
        load_reproduce_config(path, "tiny")


def test_a_restored_run_s_training_row_reads_the_checkpoint_it_flies(tmp_path):
    """`gpu.py restore` brings a finished run back with the weights it flies and no last.ckpt: its epochs and
    optimiser steps come from that checkpoint (the paper arm's 100 epochs of 470 one-trajectory steps)."""
    import torch

    from vitfly.workflows.reproduce_report import _training_table

    cfg = paper_config(tmp_path / "study")
    run = cfg.train_dir("convnet", True)
    (run / "checkpoints").mkdir(parents=True)
    torch.save({"epoch": 99, "global_step": 47_000, "state_dict": {}}, run / "checkpoints" / "best.ckpt")
    (run / "done.json").write_text(json.dumps({"checkpoint": str(run / "checkpoints" / "best.ckpt")}))
    (run / "cost.json").write_text(json.dumps({"wall_s": 1590.0}))
    rows = {line.split("|")[1].strip(): line for line in _training_table(cfg).splitlines()[2:]}
    assert rows["convnet"].startswith("| convnet | 100 | 47000 | - | 26.5 |")
    assert rows["lstmnet"] == "| lstmnet | - | - | - | - | not trained |"
