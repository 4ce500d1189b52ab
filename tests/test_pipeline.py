"""`vitfly pipeline`: the quick-start config, bad configs, and a tiny run end to end with resume."""

import json

import pytest
import torch

from vitfly.cli import main
from vitfly.workflows.pipeline import TrainStage, load_pipeline_config, same_settings, success_by_policy, train_settings

TINY = """
out: {out}
data: {data}
collect:
  trajectories: 6
  speeds: [3.0, 4.0]
  workers: 1
train:
  model: convnet
  max_epochs: 1
  batch_size: 4
  policy_kwargs: {{lr: 1.0e-3, warmup_epochs: 0, tbptt_steps: 128}}
evaluate:
  speeds: [4.0]
  trials: 3
  num_envs: 3
  timeout_s: 4.0
baselines: [expert, straight]
"""


def test_quickstart_config_loads():
    cfg = load_pipeline_config("configs/quickstart.yaml")
    assert cfg.train.model == "convnet" and cfg.baselines == ["expert", "straight"]
    assert cfg.evaluate.seed != cfg.collect["seed"]  # evaluation scenes are not the training scenes
    assert cfg.collect["trajectories"] >= 100


@pytest.mark.parametrize(("text", "message"), [
    ("train: {model: convnett}", "train.model 'convnett' unknown"),
    ("evaluate: {speeds: [0]}", "speeds"),
    ("baselines: [oracle]", "baselines"),
    ("trian: {}", "unknown field 'trian'"),
    ("train: {max_epochs: many}", "max_epochs"),
])
def test_bad_config_is_one_line(tmp_path, capsys, text, message):
    f = tmp_path / "p.yaml"
    f.write_text(text)
    assert main(["pipeline", "--config", str(f), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and str(f) in err[0]
    assert not (tmp_path / "run").exists()


def test_success_by_policy_weights_cells_by_trials():
    rows = [{"policy": "a", "success_paper_rate": 0.5, "success_strict_rate": 0.5, "trials": 2},
            {"policy": "a", "success_paper_rate": 1.0, "success_strict_rate": 0.5, "trials": 6},
            {"policy": "b", "success_paper_rate": 0.0, "success_strict_rate": 0.0, "trials": 4}]
    # (0.5 * 2 + 1.0 * 6) / 8 = 7/8 by the paper's definition; (0.5 * 2 + 0.5 * 6) / 8 = 1/2 strict
    assert success_by_policy(rows) == {"a": pytest.approx(7 / 8), "b": 0.0}
    assert success_by_policy(rows, "success_strict_rate") == {"a": pytest.approx(0.5), "b": 0.0}


def test_evaluate_stage_flies_a_retrained_model_again(tmp_path, capsys):
    from vitfly.eval import records
    from vitfly.workflows.pipeline import EvalStage, stage_evaluate
    from vitfly.zoo import create_model, save_checkpoint

    ckpt, out = tmp_path / "train" / "best.ckpt", tmp_path / "eval"
    ckpt.parent.mkdir()
    stage = EvalStage(speeds=[4.0], trials=2, num_envs=2, timeout_s=1.0)
    policies = [(str(ckpt), "convnet"), ("straight", None)]
    ids = []
    for seed in (0, 0, 1):  # trained, the same checkpoint again, then retrained (other weights, same path)
        torch.manual_seed(seed)
        save_checkpoint(create_model("convnet"), "convnet", True, ckpt)
        stage_evaluate(stage, out, policies, progress=False, gif_for=0)
        ids.append({r.setup["policy_id"] for r in records.read_sweep(out) if r.policy == "convnet"})
    text = capsys.readouterr().out.splitlines()
    assert text == ["[evaluate] convnet: 2 trials flown, 0 done before",
                    "[evaluate] straight: 2 trials flown, 0 done before",
                    "[evaluate] convnet: 0 trials flown, 2 done before",
                    "[evaluate] straight: 0 trials flown, 2 done before",
                    "[evaluate] convnet: 2 trials flown, 0 done before, 2 stale trials (another setup) replaced",
                    "[evaluate] straight: 0 trials flown, 2 done before"]
    assert len(ids[0]) == len(ids[2]) == 1 and ids[0] == ids[1] != ids[2]
    assert len(records.read_sweep(out)) == 4
    # the depth GIF shows the retrained model too
    about = json.loads((out / "depth_convnet_spheres.json").read_text())
    assert about["setup"]["policy_id"] == next(iter(ids[2]))


def test_tiny_pipeline_end_to_end_and_resume(tmp_path, capsys):
    out, data = tmp_path / "run", tmp_path / "data" / "d.h5"
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY.format(out=out, data=data))
    assert main(["pipeline", "--config", str(cfg), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "[collect]" in text and "[train]" in text and "success over all trials" in text
    result = json.loads((out / "pipeline.json").read_text())
    assert set(result["success_paper"]) == set(result["success_strict"]) == {"convnet", "expert", "straight"}
    assert isinstance(result["beats_straight"], bool) and isinstance(result["beats_straight_strict"], bool)
    ev = out / "eval"
    for name in ("summary.csv", "summary.md", "rates_vs_speed.png", "energy_vs_speed.png", "paths_spheres.png",
                 "time_in_collision_vs_speed.png", "depth_convnet_spheres.gif"):
        assert (ev / name).stat().st_size > 0, name
    trials = [json.loads(x) for x in (ev / "trials.jsonl").read_text().splitlines()]
    assert len(trials) == 9
    # every policy flew the same scenes
    seeds = {p: sorted(t["scene_seed"] for t in trials if t["policy"] == p) for p in ("convnet", "expert", "straight")}
    assert seeds["convnet"] == seeds["expert"] == seeds["straight"]

    # rerun: every stage is skipped
    assert main(["pipeline", "--config", str(cfg), "--no-progress"]) == 0
    again = capsys.readouterr().out
    assert "(0 new)" in again and "[train] done before" in again
    assert again.count("0 trials flown, 3 done before") == 3


def test_a_field_added_to_train_stage_keeps_finished_runs_done():
    """A done.json recorded before TrainStage had ``select`` still matches the default; a run of other settings
    does not."""
    wanted = train_settings(TrainStage(model="convnet"), "d.h5")
    recorded = {k: v for k, v in wanted.items() if k != "select"}
    assert same_settings(recorded, wanted)
    assert not same_settings(recorded, train_settings(TrainStage(model="convnet", select="last"), "d.h5"))
    assert not same_settings({**recorded, "max_epochs": 7}, wanted) and not same_settings(None, wanted)


def test_how_often_a_run_validated_counts_only_where_validation_chooses_the_epoch():
    """A run flown from its last epoch (``select: last``, the paper preset) trained the same weights however often
    it validated, so a finished run recorded without ``check_val_every_n_epoch`` stays done when the preset adds
    it; a run flown from its best-validation epoch would have chosen among other epochs, so it does not."""
    every5 = {"trainer_kwargs": {"check_val_every_n_epoch": 5, "precision": "32-true"}}
    for select, same in (("last", True), ("best", False)):
        recorded = train_settings(TrainStage(model="lstmnet", select=select, trainer_kwargs={"precision": "32-true"}),
                                  "d.h5")
        assert same_settings(recorded, train_settings(TrainStage(model="lstmnet", select=select, **every5), "d.h5")) \
            is same
    # any other trainer argument still counts
    last = train_settings(TrainStage(model="lstmnet", select="last", **every5), "d.h5")
    other = train_settings(TrainStage(model="lstmnet", select="last",
                                      trainer_kwargs={"check_val_every_n_epoch": 5, "precision": "bf16-mixed"}), "d.h5")
    assert not same_settings(last, other)


def test_how_a_run_batched_its_validation_never_makes_it_stale():
    """``val_batch_size`` and ``cpu_val_batch_size`` change how many trajectories a validation call takes, not its
    metrics, so a run finished without them stays done when a preset adds them, whichever epoch it flies (with
    ``select: best`` the validation losses it chose by are the same numbers); any other data argument counts."""
    batched = {"time_bucket_steps": 64, "val_batch_size": 16, "cpu_val_batch_size": 4}
    for select in ("last", "best"):
        recorded = train_settings(TrainStage(model="unet_lstm", select=select,
                                             data_kwargs={"time_bucket_steps": 64}), "d.h5")
        wanted = train_settings(TrainStage(model="unet_lstm", select=select, data_kwargs=batched), "d.h5")
        assert same_settings(recorded, wanted)
        other = train_settings(TrainStage(model="unet_lstm", select=select,
                                          data_kwargs={**batched, "time_bucket_steps": 32}), "d.h5")
        assert not same_settings(recorded, other)
