"""Training draws in ``vitfly reproduce`` (``train.draws``): each run trained again with other seeds, flown beside
it on the same scenes, and the paired findings comparing a run by its draws' mean."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import yaml
from helpers import load_script

from vitfly.errors import VitflyError
from vitfly.workflows.reproduce import evaluation_plan
from vitfly.workflows.reproduce_config import Run, draw_groups, load_reproduce_config, runs, train_stage

REPO = Path(__file__).resolve().parents[1]


def config(tmp_path: Path, draws: dict, **train) -> Path:
    """configs/reproduce.yaml with the tiny preset's train section given ``draws`` (and ``train``)."""
    cfg = yaml.safe_load((REPO / "configs" / "reproduce.yaml").read_text())
    cfg["presets"]["tiny"]["train"].update(draws=draws, **train)
    path = tmp_path / "reproduce.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_draws_are_runs_with_their_own_seed_folder_and_label(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    cfg = load_reproduce_config(config(tmp_path, {"convnet": [3, 1], "convnet-nostate": [2]}), "tiny")
    assert runs(cfg) == [Run("convnet", True), Run("vit_lstm", True), Run("convnet", False),
                         Run("convnet", True, 3), Run("convnet", True, 1), Run("convnet", False, 2)]
    assert [r.label for r in runs(cfg)][3:] == ["convnet-s3", "convnet-s1", "convnet-nostate-s2"]
    assert cfg.train_dir("convnet", False, 2) == Path(cfg.out) / "train" / "convnet-nostate-s2"
    assert Run.parse("convnet-nostate-s2") == Run("convnet", False, 2)
    assert Run.parse("vit_lstm-state") == Run("vit_lstm", True)
    with pytest.raises(VitflyError, match="expected MODEL-state or MODEL-nostate"):
        Run.parse("convnet-s2")
    # every trained run is listed once any has draws (a run trained once borrows the others' spread)
    assert draw_groups(cfg) == {"convnet": ["convnet", "convnet-s3", "convnet-s1"], "vit_lstm": ["vit_lstm"],
                                "convnet-nostate": ["convnet-nostate", "convnet-nostate-s2"]}
    # a draw is the run's recipe with another seed, nothing else
    own, drawn = train_stage(cfg, "convnet", True), train_stage(cfg, "convnet", True, seed=3)
    assert (own.seed, drawn.seed) == (0, 3) and dataclasses.replace(drawn, seed=0) == own
    # every sweep of a run flies its draws, after the study's own runs
    plan = evaluation_plan(cfg, {r.label: f"{r.label}.ckpt" for r in runs(cfg)})
    assert [label for _, label in plan["spheres"][1]] == ["convnet", "vit_lstm", "convnet-s3", "convnet-s1",
                                                          None, None]  # then expert and straight
    assert [label for _, label in plan["ablation"][1]] == ["convnet", "convnet-nostate", "convnet-s3", "convnet-s1",
                                                           "convnet-nostate-s2"]


@pytest.mark.parametrize("draws,message", [
    ({"lstmnet": [1]}, r"train.draws has 'lstmnet', which the study does not train; its runs are convnet, vit_lstm, "
                       r"convnet-nostate"),
    ({"vit_lstm-nostate": [1]}, r"train.draws has 'vit_lstm-nostate', which the study does not train"),
    ({"convnet": [0, 1]}, r"train.draws.convnet has the run's own seed 0: that draw is the run itself"),
    ({"convnet": [1, 1]}, r"train.draws.convnet must be a list of distinct seeds >= 0, got \[1, 1\]"),
    ({"convnet": [-1]}, r"must be a list of distinct seeds >= 0"),
    ({"convnet": 2}, r"must be a list of distinct seeds >= 0, got 2"),
    ({"convnet": []}, r"must be a list of distinct seeds >= 0, got \[\]"),
])
def test_bad_draws_are_one_line(tmp_path, monkeypatch, draws, message):
    monkeypatch.chdir(REPO)
    with pytest.raises(VitflyError, match=message) as err:
        load_reproduce_config(config(tmp_path, draws), "tiny")
    assert "\n" not in str(err.value)


def test_a_tiny_study_with_draws_trains_flies_and_reports_them(tmp_path, monkeypatch):
    from vitfly.eval import records
    from vitfly.workflows.reproduce import run_reproduce

    monkeypatch.chdir(REPO)
    path = config(tmp_path, {"convnet": [1]}, models=["convnet"], nostate_models=[], publish_models=["convnet"])
    cfg = load_reproduce_config(path, "tiny", {"out": str(tmp_path / "study"), "data": str(tmp_path / "d.h5")})
    cfg = dataclasses.replace(cfg, evaluate=dataclasses.replace(cfg.evaluate, speeds=[7.0], spheres_trials=3,
                                                                baselines=["straight"]))
    run_reproduce(cfg, ["data", "train", "evaluate", "report"], progress=False)
    done = json.loads((tmp_path / "study" / "train" / "convnet-state-s1" / "done.json").read_text())
    assert done["train"]["seed"] == 1
    flown = records.read_sweep(tmp_path / "study" / "eval" / "spheres")
    by_policy = {p: sorted(r.scene_seed for r in flown if r.policy == p) for p in ("convnet", "convnet-s1", "straight")}
    assert len(by_policy["convnet"]) == 3 and by_policy["convnet"] == by_policy["convnet-s1"] == by_policy["straight"]
    results = (tmp_path / "study" / "results.md").read_text()
    # the draws table: both seeds, with the success each flew in spheres
    rate = {p: 100 * sum(r.success_paper for r in flown if r.policy == p) / 3 for p in ("convnet", "convnet-s1")}
    assert "## Training draws" in results
    assert f"| ConvNet | 0 | {rate['convnet']:.0f} % |" in results
    assert f"| ConvNet | 1 | {rate['convnet-s1']:.0f} % |" in results
    assert "| convnet-s1 | 1 |" in results  # the training table lists the draw as a run
    saved = json.loads((tmp_path / "study" / "results.json").read_text())
    assert saved["config"]["train"]["draws"] == {"convnet": [1]}


def test_gpu_slots_know_draws_as_runs(tmp_path, monkeypatch):
    import argparse

    monkeypatch.chdir(REPO)
    gpu, slots = load_script("gpu"), load_script("gpu_reproduce")
    path = config(tmp_path, {"convnet-nostate": [5]})
    where = {"config": str(path), "preset": "tiny", "run_dir": str(tmp_path / "run"), "data": str(tmp_path / "d.h5")}
    cfg = slots.load_cfg(argparse.Namespace(**where))
    assert [(r.label, r.state) for r in slots.run_states(cfg)][-1] == ("convnet-nostate-s5", "not started")
    assert slots.parse_label("convnet-nostate-s5") == Run("convnet", False, 5)
    with pytest.raises(SystemExit, match="expected MODEL-state or MODEL-nostate"):
        slots.parse_label("convnet-s5")
    # a draw the preset does not have is refused before anything is collected or trained
    flags = [f"--{k.replace('_', '-')}={v}" for k, v in where.items()]
    with pytest.raises(SystemExit, match="convnet-state-s9 is not a run of the tiny preset"):
        gpu.main(["train", *flags, "--out", str(tmp_path / "back"), "--work", str(tmp_path / "work"),
                  "--runs", "convnet-state-s9"])
    assert not (tmp_path / "d.h5").exists()


def test_command_line_narrows_the_draws(monkeypatch, tmp_path):
    import argparse

    from vitfly.commands import reproduce as command

    monkeypatch.chdir(REPO)
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    laptop = command.config_from_args(parser.parse_args(["--preset", "laptop"]))
    assert laptop.train.draws == {"convnet": [1, 2, 3, 4], "convnet-nostate": [1, 2, 3, 4], "lstmnet": [1, 2],
                                  "lstmnet-nostate": [1, 2], "vit": [1, 2], "vit_lstm": [1, 2],
                                  "vit_lstm-nostate": [1, 2]}
    one = command.config_from_args(parser.parse_args(["--preset", "laptop", "--models", "vit_lstm"]))
    assert one.train.draws == {"vit_lstm": [1, 2], "vit_lstm-nostate": [1, 2]}
    # the slot plan narrows alike (the paper preset: LSTMnet trains on a CPU, the others in GPU slots)
    lstmnet = command.config_from_args(parser.parse_args(["--preset", "paper", "--models", "lstmnet"]))
    assert (lstmnet.train.slot_order, lstmnet.train.cpu_models) == (["lstmnet"], ["lstmnet"])
    # another copy of the study (--train-seed) has no draws: seed 3 would be one of ConvNet's
    copy = command.config_from_args(parser.parse_args(["--preset", "laptop", "--train-seed", "3", "--out",
                                                       str(tmp_path / "s3")]))
    assert copy.train.draws == {} and train_stage(copy, "convnet", True).seed == 3
