"""vitfly reproduce, the fast parts: configuration and recipes, the findings' rules and intervals, mean paths.

The whole command end to end (tiny preset, killed in every stage and resumed) is in
tests/test_reproduce_tiny.py (slow).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from vitfly.errors import VitflyError
from vitfly.eval.findings import findings_markdown, paper_findings, wilson
from vitfly.eval.records import TrialRecord
from vitfly.eval.repeats import RepeatPlan, mean_path
from vitfly.workflows.reproduce import _add_cost, _fit_seconds
from vitfly.workflows.reproduce_config import load_reproduce_config, recipe_fields, train_callbacks, train_stage

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "reproduce.yaml"


# -- configuration -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("preset", ["tiny", "laptop", "shipped", "paper", "paper_vitfly"])
def test_shipped_presets_load(preset):
    cfg = load_reproduce_config(CONFIG, preset)
    assert cfg.preset == preset
    for m in cfg.train.models:
        train_stage(cfg, m, True)  # every recipe reads and merges


def test_laptop_budget_merges_recipe_overrides_and_per_model(monkeypatch):
    monkeypatch.chdir(REPO)
    cfg = load_reproduce_config(CONFIG, "laptop")
    t = train_stage(cfg, "vit_lstm", False)
    # recipe configs/fit/vit_lstm.yaml, then overrides (cache), then per_model (epochs, warm-up, max_time)
    assert (t.model, t.use_state, t.max_epochs, t.batch_size, t.val_fraction, t.seed) == ("vit_lstm", False, 8, 4,
                                                                                        0.1, 0)
    assert t.policy_kwargs == {"lr": 1e-4, "warmup_epochs": 1, "warmup_start_factor": 0.1, "lr_decay": 1.0,
                               "avoid_weight": 10.0, "tbptt_steps": 32, "gradient_clip_val": 1.0, "compile": False,
                               "cpu_threads": "auto"}
    assert t.data_kwargs == {"max_length": None, "mirror_prob": 0.5, "num_workers": 1, "cache_mb": 1024,
                             "resident": True}
    assert t.trainer_kwargs == {"log_every_n_steps": 10, "precision": "bf16-mixed", "max_time": "00:01:00:00"}
    # every run of the laptop preset is capped below 2 hours
    for m in cfg.train.models:
        h, mi, s = map(int, train_stage(cfg, m, True).trainer_kwargs["max_time"].split(":")[1:])
        assert h * 60 + mi + s / 60 < 120


def test_paper_arm_trains_the_original_recipe_on_588_flights():
    cfg = load_reproduce_config(CONFIG, "paper")
    assert cfg.train.recipes == "configs/fit/paper" and cfg.collect["trajectories"] == 588
    assert cfg.train.models == cfg.train.nostate_models == ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm"]
    for m in cfg.train.models:
        t = train_stage(cfg, m, False)
        assert (t.batch_size, t.max_epochs, t.val_fraction) == (1, 100, 0.2)
        p = t.policy_kwargs
        assert (p["lr"], p["warmup_epochs"], p["warmup_start_factor"], p["lr_decay"]) == (1e-4, 5, 0.1, 1.0)
        assert (p["avoid_weight"], p["tbptt_steps"], p["gradient_clip_val"]) == (0.0, None, None)
        assert (t.data_kwargs["mirror_prob"], t.data_kwargs["max_length"]) == (0.0, None)
        # CUDA graphs of padded trajectories (eager on a CPU), except for the batch-norm networks not yet started
        # when the H100 measured them slower so: unpadded and eager, the same loss and gradients
        graphs = m not in ("lstmnet", "unet_lstm")
        assert (p["static_shapes"], p["compile"]) == ((True, "reduce-overhead") if graphs else (False, False))
        assert t.data_kwargs["time_bucket_steps"] == (64 if graphs else None)
        assert t.trainer_kwargs["precision"] == ("bf16-mixed" if m.startswith("vit") else "32-true")
        # a speed path, not the recipe: UNet+LSTM's convolutions channels-last on a CPU, and every CPU run
        # validates 4 trajectories a call
        assert p.get("channels_last", False) == ("cpu" if m == "unet_lstm" else False)
        assert t.data_kwargs["cpu_val_batch_size"] == 4


def test_paper_vitfly_arm_shares_the_dataset_and_scales_lr_by_the_square_root_of_the_batch():
    from vitfly.sim.collect import load_collect_config

    paper, arm = load_reproduce_config(CONFIG, "paper"), load_reproduce_config(CONFIG, "paper_vitfly")
    # same file, same collect settings: one collection (and one dataset hash) for both arms
    assert arm.data == paper.data and arm.collect_config == paper.collect_config
    key = load_collect_config(paper.collect_config, paper.collect).content_key()
    assert load_collect_config(arm.collect_config, arm.collect).content_key() == key
    assert arm.out != paper.out
    assert arm.train.models == ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18"]
    assert arm.train.nostate_models == [] and arm.train.recipes == "configs/fit"
    plain = load_reproduce_config(CONFIG, None)  # today's recipes, no preset
    for m in arm.train.models:
        recipe, t = train_stage(plain, m, True), train_stage(arm, m, True)
        assert (t.batch_size, t.max_epochs) == (64, 100)
        # lr = recipe lr * sqrt(64 / recipe batch); everything else of the recipe kept (chunks, loss, mirroring)
        expected = recipe.policy_kwargs["lr"] * math.sqrt(64 / recipe.batch_size)
        assert t.policy_kwargs["lr"] == pytest.approx(expected, rel=1e-3)
        for k in ("tbptt_steps", "warmup_epochs", "avoid_weight", "gradient_clip_val"):
            assert t.policy_kwargs.get(k) == recipe.policy_kwargs.get(k), k
        assert t.data_kwargs.get("mirror_prob") == recipe.data_kwargs.get("mirror_prob")
        assert t.trainer_kwargs["precision"] == ("bf16-mixed" if m.startswith("vit") else "32-true")


def test_existing_presets_train_as_before():
    """tiny and laptop runs keep their done.json settings: no new key enters their recipes."""
    for preset in ("tiny", "laptop"):
        cfg = load_reproduce_config(CONFIG, preset)
        for m in cfg.train.models:
            t = train_stage(cfg, m, True)
            assert "static_shapes" not in t.policy_kwargs and "time_bucket_steps" not in t.data_kwargs
            assert t.policy_kwargs["compile"] is False


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "r.yaml"
    path.write_text(f"train:\n  recipes: {REPO / 'configs/fit'}\n" + text)
    return path


@pytest.mark.parametrize("text,preset,message", [
    ("bogus: 1\n", None, r"r.yaml: unknown field 'bogus'; known fields: collect, collect_config"),
    ("evaluate:\n  spheres_trial: 3\n", None, r"r.yaml: evaluate: unknown field 'spheres_trial'"),
    ("presets:\n  tiny:\n    paths: {repeat: 2}\n", "tiny", r"r.yaml: paths: unknown field 'repeat'"),
    ("presets:\n  tiny: {}\n", "laptop", r"r.yaml: no preset 'laptop' under 'presets' \(known: tiny\)"),
    ("presets:\n  tiny:\n    train: {overrides: {max_epoch: 2}}\n", "tiny",
     r"train \(recipe .*convnet.yaml \+ overrides\) of convnet: unknown field 'max_epoch'"),
    ("presets:\n  tiny:\n    train: {models: [convnet, nope]}\n", "tiny", r"train.models has 'nope'; known: "),
    ("presets:\n  tiny:\n    train: {models: [convnet]}\n", "tiny",
     r"train.nostate_models has 'lstmnet', which train.models does not train"),
    ("evaluate:\n  baselines: [expert, oracle]\n", None, r"baselines have 'oracle'"),
    ("evaluate:\n  speeds: [0]\n", None, r"evaluate: field 'speeds' must be a non-empty list of positive m/s"),
    ("train:\n  closed_loop_check: {every: 2}\n", None, r"train.closed_loop_check: .*unexpected keyword"),
])
def test_bad_configs_are_one_line(tmp_path, text, preset, message):
    path = write(tmp_path, "") if text.startswith("train:") else write(tmp_path, text)
    if text.startswith("train:"):  # merge into the train section the helper wrote
        path.write_text(f"train:\n  recipes: {REPO / 'configs/fit'}\n" + text.split("\n", 1)[1])
    with pytest.raises(VitflyError, match=message) as err:
        load_reproduce_config(path, preset)
    assert "\n" not in str(err.value)


def test_recipe_sections_are_checked(tmp_path):
    recipes = tmp_path / "fit"
    recipes.mkdir()
    (recipes / "convnet.yaml").write_text("model:\n  class_path: vit\n")
    with pytest.raises(VitflyError, match=r"convnet.yaml: model.class_path is 'vit', but the file is the recipe"):
        recipe_fields(recipes / "convnet.yaml", "convnet")
    (recipes / "convnet.yaml").write_text("optimizer: adam\n")
    with pytest.raises(VitflyError, match=r"convnet.yaml: unknown section 'optimizer'"):
        recipe_fields(recipes / "convnet.yaml", "convnet")
    (recipes / "convnet.yaml").write_text(
        "seed_everything: 3\nmodel:\n  class_path: vitfly.zoo.policy.convnet\n  init_args: {lr: 0.001, use_state: "
        "false}\ndata: {data_path: x.h5, batch_size: 2, mirror_prob: 0.5, split_seed: 9}\n"
        "trainer: {max_epochs: 7, default_root_dir: runs/x, gradient_clip_val: 1.0}\n")
    assert recipe_fields(recipes / "convnet.yaml", "convnet") == {
        "seed": 3, "policy_kwargs": {"lr": 0.001}, "batch_size": 2, "data_kwargs": {"mirror_prob": 0.5},
        "max_epochs": 7, "trainer_kwargs": {"gradient_clip_val": 1.0}}


# -- findings ----------------------------------------------------------------------------------------------


def test_wilson_interval_by_hand():
    # Wilson: centre (p + z^2/2n) / (1 + z^2/n), half-width z / (1 + z^2/n) sqrt(p(1-p)/n + z^2/4n^2), z = 1.96
    lo, hi = wilson(7, 10)
    assert (lo, hi) == pytest.approx((0.3968, 0.8922), abs=2e-4)
    lo, hi = wilson(0, 1)
    assert lo == pytest.approx(0.0, abs=1e-12) and hi == pytest.approx(0.7935, abs=2e-4)


def row(policy, speed, env="spheres", trials=10, success=0.5, strict=None, collisions=1.0, energy=1.0, acc=5.0,
        tic=0.2):
    return {"policy": policy, "env": env, "speed": float(speed), "trials": trials, "success_paper_rate": success,
            "success_strict_rate": success if strict is None else strict, "reached_goal_rate": 1.0,
            "collisions_mean": collisions, "collisions_std": 0.5, "energy_cost_mean": energy, "energy_cost_std": 0.1,
            "cmd_acc_mean": acc, "cmd_acc_std": 1.0, "time_in_collision_mean": tic, "time_in_collision_std": 0.1}


def by_key(findings):
    return {f.key: f for f in findings}


def test_findings_reproduced_when_the_study_shows_the_papers_pattern():
    speeds = (3, 4, 5, 6, 7)
    spheres = [row("expert", s, collisions=0.1 * s, tic=1.0) for s in speeds]
    for m, base in (("convnet", 0.2), ("lstmnet", 0.3), ("vit", 0.25), ("resnet18", 0.22)):
        spheres += [row(m, s, collisions=base * s, energy=2.0, acc=8.0, success=0.5) for s in speeds]
    spheres += [row("vit_lstm", s, collisions=0.1 * s - 0.05 if s > 5 else 0.2 * s, energy=0.5, acc=4.0, tic=0.1)
                for s in speeds]
    trees = [row(m, s, env="trees", collisions=c, acc=8.0 if m == "vit" else 4.0)
             for m, c in (("convnet", 1.0), ("lstmnet", 0.8), ("vit", 0.2), ("vit_lstm", 0.3)) for s in speeds]
    at_7 = {"vit": 0.8, "vit_lstm": 0.7}  # the paper's trees success at 7 m/s, over 10 trials
    trees = [{**r, "success_paper_rate": at_7[r["policy"]]} if r["speed"] == 7.0 and r["policy"] in at_7 else r
             for r in trees]
    window = [row("convnet", 3, env="window", strict=0.0), row("lstmnet", 3, env="window", strict=0.0),
              row("vit", 3, env="window", strict=0.3), row("vit_lstm", 3, env="window", strict=0.6)]
    ablation = [row("vit_lstm", s, env=e, trials=11, success=8 / 11) for e in ("spheres", "trees") for s in (3, 5, 7)]
    ablation += [row("vit_lstm-nostate", s, env=e, trials=11, success=(5 if s != 5 else 8) / 11)
                 for e in ("spheres", "trees") for s in (3, 5, 7)]
    lateral = {"vit_lstm": 0.7, "convnet": 1.5, "expert": 0.2}
    f = by_key(paper_findings(spheres, trees, window, ablation, lateral))
    assert {k: v.verdict for k, v in f.items()} == {
        "lowest_collisions_6_7": "reproduced", "beats_expert_above_5": "reproduced", "time_in_collision": "reproduced",
        "most_direct_path": "reproduced", "vit_best_trees": "reproduced", "trees_success_7": "reproduced",
        "window_only_vit": "reproduced", "lowest_energy": "reproduced", "recurrence_acc": "reproduced",
        "state_helps_vit_lstm": "reproduced", "resnet_vs_convnet": "reproduced"}
    assert "8/10, CI 49-94 %" in f["trees_success_7"].ours  # Wilson of 8/10: 0.490-0.943
    text = findings_markdown(list(f.values()))
    assert "Verdicts: 11 reproduced, 0 partly, 0 not, 0 n/a." in text
    assert text.count("\n| ") == 11  # one row per finding


def test_findings_not_and_partly_and_missing_data():
    speeds = (3, 5, 6, 7)
    spheres = [row("expert", s, collisions=0.1) for s in speeds]
    spheres += [row("convnet", s, collisions=0.05, success=0.9, trials=50, energy=0.4) for s in speeds]
    spheres += [row("vit_lstm", s, collisions=0.2 if s == 6 else 0.04, energy=0.5) for s in speeds]
    spheres += [row("resnet18", s, success=1.0, trials=50) for s in speeds]
    spheres = [{**r, "success_paper_rate": 0.1} if r["policy"] == "convnet" else r for r in spheres]
    window = [row("convnet", 3, env="window", strict=0.5), row("vit_lstm", 3, env="window", strict=0.2)]
    f = by_key(paper_findings(spheres, None, window, None))
    assert f["lowest_collisions_6_7"].verdict == "partly"  # lowest at 7 m/s only
    assert f["beats_expert_above_5"].verdict == "partly"  # below the expert at 7, not at 6; ConvNet at both
    assert "ConvNet" in f["beats_expert_above_5"].why
    assert f["window_only_vit"].verdict == "not"
    assert f["lowest_energy"].verdict == "not"
    assert f["resnet_vs_convnet"].verdict == "not"  # 200/200 against 20/200: intervals far apart
    for key in ("vit_best_trees", "trees_success_7", "state_helps_vit_lstm", "most_direct_path", "recurrence_acc"):
        assert f[key].verdict == "n/a", key


# -- mean paths over repeats -------------------------------------------------------------------------------


def record(ys, zs, x_end=60.0) -> TrialRecord:
    x = np.linspace(0.0, x_end, len(ys))
    pos = np.stack([x, ys, zs], axis=1)
    path = {"time": list(range(len(x))), "position": pos.tolist(), "velocity": np.zeros_like(pos).tolist(),
            "command": np.zeros_like(pos).tolist(), "contact": [False] * len(x)}
    return TrialRecord("p", "spheres", 5.0, 0, 1, True, True, True, "goal", {}, path, {}, "s")


def test_mean_path_by_hand():
    n = 61
    a = record(np.full(n, 1.0), np.full(n, 3.0))
    b = record(np.full(n, -1.0), np.full(n, 5.0))
    c = record(np.full(31, 4.0), np.full(31, 4.0), x_end=30.0)  # stops at x = 30 m
    grid = np.array([0.0, 10.0, 29.0, 45.0, 60.0])
    mean, std, count = mean_path([a, b, c], grid)
    np.testing.assert_array_equal(count, [3, 3, 3, 2, 2])
    # up to 30 m: y = (1, -1, 4) -> mean 4/3, population std sqrt(((-1/3)^2 + (-7/3)^2 + (8/3)^2) / 3) = sqrt(38)/3
    np.testing.assert_allclose(mean[:3, 0], 4 / 3)
    np.testing.assert_allclose(std[:3, 0], math.sqrt(38) / 3)
    # beyond: y = (1, -1) -> mean 0, std 1; z = (3, 5) -> mean 4, std 1
    np.testing.assert_allclose(mean[3:], [[0.0, 4.0], [0.0, 4.0]])
    np.testing.assert_allclose(std[3:], [[1.0, 1.0], [1.0, 1.0]])


def test_repeat_offsets_are_bounded_and_fixed_by_the_seed():
    plan = RepeatPlan(repeats=20, jitter_m=0.1, seed=5)
    off = plan.offsets()
    assert off.shape == (20, 3) and np.all(off[:, 0] == 0) and np.all(np.abs(off[:, 1:]) <= 0.1)
    np.testing.assert_array_equal(off, RepeatPlan(repeats=20, jitter_m=0.1, seed=5).offsets())
    np.testing.assert_array_equal(off[:5], RepeatPlan(repeats=5, jitter_m=0.1, seed=5).offsets())
    assert len({tuple(o) for o in off}) == 20


def test_train_seed_retrains_every_run_with_another_seed_in_its_own_directory(monkeypatch, tmp_path):
    import argparse

    from vitfly.commands import reproduce as command

    monkeypatch.chdir(REPO)
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    default = command.config_from_args(parser.parse_args(["--preset", "laptop"]))
    args = ["--preset", "laptop", "--models", "convnet", "--train-seed", "3"]
    with pytest.raises(VitflyError, match=r"--train-seed 3: give --out too \(the preset's runs/reproduce-laptop"):
        command.config_from_args(parser.parse_args(args))
    cfg = command.config_from_args(parser.parse_args([*args, "--out", str(tmp_path / "s3")]))
    assert cfg.train.models == cfg.train.nostate_models == ["convnet"] and cfg.out == str(tmp_path / "s3")
    seeded, own = train_stage(cfg, "convnet", True), train_stage(default, "convnet", True)
    assert (own.seed, seeded.seed) == (0, 3)
    assert dataclasses.replace(seeded, seed=0) == own  # nothing else of the recipe moves (30 epochs, the cap, ...)


def test_threads_flag_sets_the_training_threads_and_refuses_negatives(monkeypatch):
    import argparse

    from vitfly.commands import reproduce as command

    monkeypatch.chdir(REPO)
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    assert command.config_from_args(parser.parse_args(["--preset", "paper"])).threads == 0  # the YAML's: all cores
    assert command.config_from_args(parser.parse_args(["--preset", "paper", "--threads", "1"])).threads == 1
    with pytest.raises(VitflyError, match=r"--threads -1: expected 0 \(all cores\) or more"):
        command.config_from_args(parser.parse_args(["--preset", "paper", "--threads", "-1"]))


def test_engine_flags_choose_the_sweeps_engine(monkeypatch):
    import argparse

    from vitfly.commands import reproduce as command
    from vitfly.workflows.reproduce_config import eval_stage

    monkeypatch.chdir(REPO)
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    cfg = command.config_from_args(parser.parse_args(["--preset", "paper", "--sim", "batched", "--sim-dtype",
                                                      "float32", "--sim-compile"]))
    stage = eval_stage(cfg, ["trees"], [3.0], 1)
    assert (stage.sim, stage.sim_device, stage.sim_dtype, stage.sim_compile) == ("batched", "cpu", "float32", True)
    assert cfg.collect == command.config_from_args(parser.parse_args(["--preset", "paper"])).collect  # data as is
    with pytest.raises(VitflyError, match="--sim: evaluate: field 'sim_dtype' is 'float32' but 'sim' is 'numpy'"):
        command.config_from_args(parser.parse_args(["--preset", "paper", "--sim-dtype", "float32"]))


# -- training cost over sessions ----------------------------------------------------------------------------


def _last_ckpt_with_timer(train_dir: Path, fit_s: float) -> None:
    """last.ckpt as Lightning leaves it, reduced to the Timer's state (seconds of fitting so far)."""
    (train_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    torch.save({"epoch": 0, "callbacks": {"Timer": {"time_elapsed": {"train": fit_s, "validate": 0.0}}}},
               train_dir / "checkpoints" / "last.ckpt")


def test_training_cost_counts_the_fitting_of_killed_sessions(tmp_path):
    assert _fit_seconds(tmp_path) == 0.0  # nothing trained yet
    # a first session, killed after its checkpoint at 300 s of fitting, left no cost.json
    _last_ckpt_with_timer(tmp_path, 300.0)
    before = _fit_seconds(tmp_path)
    _last_ckpt_with_timer(tmp_path, 480.0)  # the second fits 180 s more, in 200 s of wall time, and finishes
    assert _add_cost(tmp_path, 200.0, before) == {"wall_s": 500.0, "sessions": 1, "fit_s": 480.0, "killed_s": 300.0}
    # a third, with no kill between: only its own wall time
    before = _fit_seconds(tmp_path)
    _last_ckpt_with_timer(tmp_path, 530.0)
    assert _add_cost(tmp_path, 60.0, before) == {"wall_s": 560.0, "sessions": 2, "fit_s": 530.0, "killed_s": 300.0}
    # a cost.json written before the Timer was read says nothing of what was lost: nothing is added
    (tmp_path / "cost.json").write_text(json.dumps({"wall_s": 100.0, "sessions": 1}))
    assert _add_cost(tmp_path, 10.0, 530.0)["wall_s"] == 110.0


def test_every_run_has_a_stopwatch_and_max_time_keeps_its_own(monkeypatch):
    from lightning.pytorch.callbacks import Timer

    monkeypatch.chdir(REPO)
    for preset, expected in (("tiny", 1), ("paper", 1), ("laptop", 0)):  # laptop: max_time brings Lightning's
        cfg = load_reproduce_config(CONFIG, preset)
        stage, callbacks = train_callbacks(train_stage(cfg, "convnet", True), cfg, "test")
        timers = [c for c in callbacks if isinstance(c, Timer)]
        assert len(timers) == expected, preset
        assert all(t.time_remaining() is None for t in timers)  # a stopwatch: it never ends a run


# -- the results page from shipped weights (train.source: pretrained) ------------------------------------


def test_shipped_preset_flies_the_weights_without_data(monkeypatch):
    monkeypatch.chdir(REPO)
    cfg = load_reproduce_config(CONFIG, "shipped")
    assert cfg.train.source == "pretrained" and cfg.train.nostate_models == []
    assert cfg.train.models == ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm"]


@pytest.mark.parametrize("text,message", [
    ("train:\n  source: scratch\n", r"train.source: expected one of train, pretrained, got 'scratch'"),
    ("train:\n  source: pretrained\n", r"train.source pretrained .* set train.nostate_models: \[\]"),
    ("train:\n  source: pretrained\n  nostate_models: []\n  weights_dir: w\n", r"instead of train.weights_dir"),
])
def test_bad_train_source_is_one_line(tmp_path, text, message):
    path = tmp_path / "r.yaml"
    path.write_text(text)
    with pytest.raises(VitflyError, match=message) as err:
        load_reproduce_config(path)
    assert "\n" not in str(err.value)


def test_pretrained_source_evaluates_and_records_closed_loop(tmp_path, monkeypatch):
    from test_pretrained import random_checkpoint

    from vitfly.eval import records
    from vitfly.workflows.reproduce import run_reproduce
    from vitfly.zoo.pretrained import read_manifest, save_pretrained

    weights = tmp_path / "weights"
    monkeypatch.setenv("VITFLY_WEIGHTS_DIR", str(weights))
    _, ckpt = random_checkpoint(tmp_path, "convnet")
    save_pretrained(ckpt, "convnet", {"preset": "test", "steps": 7, "train_frames": 123}, weights)
    path = tmp_path / "r.yaml"
    path.write_text(
        f"out: {tmp_path / 'study'}\ndata: {tmp_path / 'never.h5'}\n"
        "train: {source: pretrained, models: [convnet], nostate_models: [], publish_models: [convnet]}\n"
        "evaluate: {speeds: [3.0], spheres_trials: 2, trees_trials: 1, window_trials: 1, baselines: [straight],"
        " num_envs: 2, timeout_s: 2.0}\n")
    cfg = load_reproduce_config(path)
    with pytest.raises(VitflyError, match=r"pretrained:lstmnet: not in .*manifest.json \(available: convnet\)"):
        run_reproduce(dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, models=["lstmnet"])),
                      ["evaluate"], progress=False)
    run_reproduce(cfg, ["data", "train", "evaluate", "report"], progress=False)
    assert not (tmp_path / "never.h5").exists()  # no data stage for shipped weights
    flown = records.read_sweep(tmp_path / "study" / "eval" / "spheres")
    assert sorted(r.policy for r in flown) == ["convnet", "convnet", "straight", "straight"]
    entry = read_manifest(weights)["models"]["convnet"]
    spheres = entry["closed_loop"]["spheres"]["3"]
    assert spheres["trials"] == 2
    assert spheres["success"] == sum(r.success_paper for r in flown if r.policy == "convnet") / 2  # a fraction
    assert entry["steps"] == 7  # the published entry otherwise unchanged
    results = (tmp_path / "study" / "results.md").read_text()
    assert "| pretrained:convnet | test | 7 | 123 |" in results
    # straight flight and the ConvNet flew the same two scenes: the paired section compares them
    assert "## Paired comparisons" in results and "ResNet-18 and ConvNet not flown on shared scenes" in results
    lines = results.splitlines()  # sections not flown (modular, paths) still leave every heading its blank line
    assert all(lines[i - 1] == "" for i, line in enumerate(lines) if line.startswith("## "))
    assert "## Modular baselines\n\n(not flown)\n\n## Latency" in results
