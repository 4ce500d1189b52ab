"""`vitfly fit | validate | test | predict` end to end through LightningCLI on a small HDF5 the test writes."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import pytest
import torch
from test_datamodule import write_dataset

from vitfly.cli import main
from vitfly.datamodules.schema import decode_depth, open_trajectories
from vitfly.zoo import load_network
from vitfly.zoo.policy import PolicyModule

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("data") / "d.h5", [12, 9, 15, 7, 11])


def fit_args(data_path, run_dir, *extra, model="convnet", epochs=2):
    return [
        "fit",
        "--config", str(REPO / "configs/fit" / f"{model}.yaml"),
        "--data.data_path", data_path,
        "--data.num_workers", "0",
        "--data.batch_size", "2",
        "--trainer.max_epochs", str(epochs),
        "--trainer.default_root_dir", str(run_dir),
        "--trainer.enable_progress_bar", "false",
        "--trainer.enable_model_summary", "false",
        *extra,
    ]  # fmt: skip


def run_dir_of(root: Path) -> Path:
    (version,) = sorted(root.glob("version_*"))
    return version


def test_fit_writes_checkpoints_split_and_metrics_then_resumes(data_path, tmp_path):
    root = tmp_path / "run"
    assert main(fit_args(data_path, root, "--model.init_args.tbptt_steps", "4")) == 0
    run = run_dir_of(root)
    best, last = run / "checkpoints/best.ckpt", run / "checkpoints/last.ckpt"
    assert best.exists() and last.exists()
    ckpt = torch.load(last, weights_only=True)  # contract 2: no pickled objects
    assert ckpt["hyper_parameters"]["model"] == "convnet" and ckpt["hyper_parameters"]["use_state"] is True
    assert ckpt["hyper_parameters"]["model_kwargs"] == {}
    assert ckpt["state_dict"] and all(k.startswith("net.") for k in ckpt["state_dict"])
    assert ckpt["epoch"] == 1
    steps = ckpt["global_step"]
    # 4 training trajectories (one held out), batches of 2, chunks of 4 steps: several optimiser steps per batch
    assert steps > 2 * 2
    net = load_network(best)  # the zoo's loader reads fit checkpoints by path alone
    assert type(net).__name__ == "ConvNet" and not net.training
    assert PolicyModule.load_from_checkpoint(best).hparams.model == "convnet"
    split = json.loads((run / "split.json").read_text())
    assert len(split["val"]) == 1 and len(split["train"]) == 4
    with open(run / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {"train/loss_epoch", "val/loss", "val/cosine"} <= set(rows[0])
    assert any(r["val/loss"] for r in rows)

    # resume: the step count continues from the checkpoint
    assert main(fit_args(data_path, tmp_path / "resumed", "--model.init_args.tbptt_steps", "4",
                         "--ckpt_path", str(last), epochs=3)) == 0  # fmt: skip
    resumed = torch.load(run_dir_of(tmp_path / "resumed") / "checkpoints/last.ckpt", weights_only=True)
    assert resumed["epoch"] == 2
    assert resumed["global_step"] == steps + steps // 2

    # validate / test / predict from the checkpoint
    for sub in ("validate", "test", "predict"):
        args = fit_args(data_path, tmp_path / sub, "--ckpt_path", str(best))
        args[0] = sub
        assert main(args) == 0, sub


def test_model_short_name_use_state_link_and_recurrent_model(data_path, tmp_path):
    root = tmp_path / "lstm"
    args = fit_args(data_path, root, "--model", "lstmnet", "--model.init_args.use_state", "false",
                    "--model.init_args.tbptt_steps", "5", "--trainer.limit_train_batches", "1",
                    "--trainer.limit_val_batches", "1", epochs=1)  # fmt: skip
    assert main(args) == 0
    run = run_dir_of(root)
    ckpt = torch.load(run / "checkpoints/last.ckpt", weights_only=True)
    assert ckpt["hyper_parameters"]["model"] == "lstmnet"
    assert ckpt["hyper_parameters"]["use_state"] is False
    assert json.loads((run / "split.json").read_text())["use_state"] is False  # linked into the datamodule
    assert load_network(run / "checkpoints/last.ckpt").use_state is False


def test_tensorboard_logger_composes_as_a_second_config(data_path, tmp_path):
    args = fit_args(data_path, tmp_path / "tb", "--config", str(REPO / "configs/fit/logger/tensorboard.yaml"),
                    epochs=1)  # fmt: skip
    assert main(args) == 0
    assert list((tmp_path / "tb").rglob("events.out.tfevents.*"))


def test_wandb_logger_runs_offline(data_path, tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_DIR", str(tmp_path))
    monkeypatch.setenv("WANDB_SILENT", "true")
    args = fit_args(data_path, tmp_path / "wb", "--config", str(REPO / "configs/fit/logger/wandb.yaml"),
                    epochs=1)  # fmt: skip
    assert main(args) == 0
    assert list((tmp_path / "wb").rglob("offline-run-*"))
    import wandb

    assert wandb.run is None  # finished between runs


def test_print_config_shows_the_recipe(capsys):
    assert main(["fit", "--config", str(REPO / "configs/fit/vit_lstm.yaml"), "--print_config"]) == 0
    out = capsys.readouterr().out
    assert "class_path: vitfly.zoo.policy.vit_lstm" in out
    assert "lr: 0.0001" in out and "warmup_epochs: 1" in out and "warmup_start_factor: 0.1" in out
    assert "avoid_weight: 10.0" in out and "tbptt_steps: 32" in out and "mirror_prob: 0.5" in out


PAPER_MODELS = ("convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm")


def test_all_model_configs_parse():
    for name in ("convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18"):
        assert main(["fit", "--config", str(REPO / "configs/fit" / f"{name}.yaml"), "--print_config"]) == 0
    for name in PAPER_MODELS:  # the paper-recipe arm
        assert main(["fit", "--config", str(REPO / "configs/fit/paper" / f"{name}.yaml"), "--print_config"]) == 0


@pytest.mark.parametrize("name", PAPER_MODELS)
def test_paper_recipes_are_the_original_training_config(name, capsys):
    assert main(["fit", "--config", str(REPO / "configs/fit/paper" / f"{name}.yaml"), "--print_config"]) == 0
    out = capsys.readouterr().out
    for line in ("lr: 0.0001", "warmup_epochs: 5", "warmup_start_factor: 0.1", "lr_decay: 1.0", "avoid_weight: 0.0",
                 "tbptt_steps: null", "batch_size: 1", "val_fraction: 0.2", "mirror_prob: 0.0", "max_length: null",
                 "max_epochs: 100", f"class_path: vitfly.zoo.policy.{name}"):
        assert line in out, line
    precision = "bf16-mixed" if name.startswith("vit") else "32-true"
    assert f"precision: {precision}" in out


def test_paper_recipe_fits_with_static_shapes_and_buckets(data_path, tmp_path):
    args = fit_args(data_path, tmp_path / "paper", "--data.batch_size", "1", "--model.init_args.static_shapes", "true",
                    "--model.init_args.compile", "reduce-overhead", "--data.time_bucket_steps", "8", epochs=1)
    args[2] = str(REPO / "configs/fit/paper/lstmnet.yaml")
    assert main(args) == 0
    run = run_dir_of(tmp_path / "paper")
    assert (run / "checkpoints" / "last.ckpt").exists() and (run / "split.json").exists()
    hparams = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["hyper_parameters"]
    assert (hparams["static_shapes"], hparams["compile"], hparams["tbptt_steps"]) == (True, "reduce-overhead", None)


@pytest.mark.parametrize("flag,value,message", [
    ("--data.time_bucket_steps", "0", "data.time_bucket_steps: expected a positive number of time steps"),
    ("--model.init_args.compile", "graphs", "model.compile: expected false, true (default mode) or reduce-overhead"),
])
def test_bad_static_shape_options_fail_with_one_line(data_path, tmp_path, capsys, flag, value, message):
    assert main(fit_args(data_path, tmp_path / "run", flag, value, epochs=1)) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1]


def set_schema_version(path, version):
    write_dataset(path, [5, 6])
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = version


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: p.write_bytes(b"not an hdf5 file at all" * 10), "not an HDF5 file"),
        (lambda p: set_schema_version(p, 7), "attribute 'schema_version' is 7"),
        (lambda p: None, "no such dataset file"),
    ],
)
def test_bad_dataset_fails_with_one_line(tmp_path, capsys, make, message):
    bad = tmp_path / "bad.h5"
    make(bad)
    assert main(fit_args(str(bad), tmp_path / "run", epochs=1)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("vitfly: error: ") and message in err[-1] and str(bad) in err[-1]
    assert not list(tmp_path.glob("run/version_*/checkpoints/*.ckpt"))


def test_unknown_model_name_fails_cleanly(data_path, tmp_path, capsys):
    assert main(fit_args(data_path, tmp_path / "run", "--model", "no_such_net", epochs=1)) != 0
    assert "no_such_net" in capsys.readouterr().err


def test_train_policy_from_python_writes_and_then_reuses_checkpoints(data_path, tmp_path):
    from vitfly.training import train_policy

    out = tmp_path / "prog"
    kwargs = dict(max_epochs=1, batch_size=2, progress_bar=False, policy_kwargs={"tbptt_steps": 8})
    best = train_policy(data_path, "convnet", out, **kwargs)
    assert best == out / "checkpoints/best.ckpt" and (out / "checkpoints/last.ckpt").exists()
    assert (out / "split.json").exists() and (out / "metrics.csv").exists()
    assert type(load_network(best)).__name__ == "ConvNet"
    step = torch.load(out / "checkpoints/last.ckpt", weights_only=True)["global_step"]
    # a second call with the same arguments finds the finished run and trains no further
    assert train_policy(data_path, "convnet", out, **kwargs) == best
    assert torch.load(out / "checkpoints/last.ckpt", weights_only=True)["global_step"] == step


def test_train_policy_refuses_to_resume_another_model(data_path, tmp_path):
    from vitfly.errors import VitflyError
    from vitfly.training import train_policy

    out = tmp_path / "prog"
    train_policy(data_path, "convnet", out, max_epochs=1, batch_size=2, progress_bar=False)
    with pytest.raises(VitflyError, match="holds a run of model 'convnet' .* not 'lstmnet'"):
        train_policy(data_path, "lstmnet", out, max_epochs=2, batch_size=2, progress_bar=False)


def direct_val_loss(net, data_path, val_indices) -> float:
    """Paper eq. 1 worked out without the loader or the policy module: the mean over every step and axis of the
    held-out trajectories of (output - velocity_cmd / desired_speed)^2, one whole trajectory at a time."""
    squared, count = 0.0, 0
    with open_trajectories(data_path) as tf, torch.no_grad():
        for m in val_indices:
            rows = tf.read(m, ["depth", "desired_speed", "quat", "velocity_cmd"])
            depth = torch.from_numpy(decode_depth(rows["depth"]))[None, :, None]
            speed = torch.from_numpy(rows["desired_speed"])[None, :, None]
            prediction, _ = net(depth, speed, torch.from_numpy(rows["quat"])[None])
            target = torch.from_numpy(rows["velocity_cmd"]) / speed[0]
            squared += float(((prediction[0] - target) ** 2).sum())
            count += target.numel()
    return squared / count


def test_validate_takes_the_network_from_a_no_state_checkpoint(data_path, tmp_path, capsys):
    from vitfly.training import train_policy
    from vitfly.training.cli import build_cli
    from vitfly.zoo import create_model

    ckpt = train_policy(data_path, "lstmnet", tmp_path / "nostate", use_state=False, max_epochs=1, batch_size=2,
                        progress_bar=False)  # fmt: skip
    # the config: convnet WITH state; fp32 so the loss compares with the direct fp32 computation to 1e-5
    args = fit_args(data_path, tmp_path / "val", "--ckpt_path", str(ckpt), "--trainer.precision", "32-true")
    args[0] = "validate"
    cli = build_cli(args)
    assert f"{ckpt} holds lstmnet (use_state=False" in capsys.readouterr().err
    assert type(cli.model.net).__name__ == "LSTMNet" and cli.model.net.use_state is False
    got = float(cli.trainer.callback_metrics["val/loss"])
    val = json.loads((tmp_path / "nostate/split.json").read_text())["val"]
    assert json.loads((run_dir_of(tmp_path / "val") / "split.json").read_text())["val"] == val  # the ckpt's split
    net = load_network(ckpt)
    assert got == pytest.approx(direct_val_loss(net, data_path, val), rel=1e-5)
    # the same weights fed the state give another loss: validating with state inputs would show
    with_state = create_model("lstmnet", use_state=True).eval()
    with_state.load_state_dict(net.state_dict())
    assert abs(direct_val_loss(with_state, data_path, val) - got) > 1e-4 * got


def test_ckpt_path_that_is_not_a_vitfly_checkpoint_is_one_line(data_path, tmp_path, capsys):
    from vitfly.zoo import create_model

    plain = tmp_path / "plain.pth"
    torch.save(create_model("convnet").state_dict(), plain)  # an original-project style state dict
    args = fit_args(data_path, tmp_path / "val", "--ckpt_path", str(plain))
    args[0] = "validate"
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("vitfly: error: ") and "plain.pth: checkpoint has no hyper_parameters.model" in err[-1]


def test_init_weights_starts_a_fit_from_the_shipped_weights(data_path, tmp_path, capsys):
    from vitfly.zoo import load_pretrained

    shipped = load_pretrained("convnet")
    # lr 1e-12: Adam moves each weight by about lr per step, so the trained weights stay the shipped ones
    assert main(fit_args(data_path, tmp_path / "ft", "--init_weights", "pretrained:convnet",
                         "--model.init_args.lr", "1e-12", epochs=1)) == 0  # fmt: skip
    state = torch.load(run_dir_of(tmp_path / "ft") / "checkpoints/last.ckpt", weights_only=True)["state_dict"]
    for name, param in shipped.named_parameters():
        torch.testing.assert_close(state[f"net.{name}"], param, rtol=0, atol=1e-6)
    # without it the network starts from its random initialisation, far from the shipped weights
    assert main(fit_args(data_path, tmp_path / "fresh", "--model.init_args.lr", "1e-12", epochs=1)) == 0
    fresh = torch.load(run_dir_of(tmp_path / "fresh") / "checkpoints/last.ckpt", weights_only=True)["state_dict"]
    with torch.no_grad():
        assert max(float((fresh[f"net.{n}"] - p).abs().max()) for n, p in shipped.named_parameters()) > 0.01
    # weights of another network: one line, non-zero exit
    capsys.readouterr()
    assert main(fit_args(data_path, tmp_path / "bad", "--init_weights", "pretrained:lstmnet", epochs=1)) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["vitfly: error: pretrained:lstmnet: init_weights holds model 'lstmnet' (use_state=True), "
                   "not 'convnet' (use_state=True)"]  # fmt: skip
    assert not list((tmp_path / "bad").rglob("*.ckpt"))


def test_train_policy_says_nothing_about_its_own_run_folder(data_path, tmp_path):
    """The run folder holds vitfly's own files (data.json from the pipeline, split.json) before Lightning's
    logger starts, and a resume finds checkpoints there: Lightning's 'exists and is not empty ... will be
    deleted' warnings are wrong about such a folder (the earlier metrics are joined back), so they stay quiet,
    and the resumed run's metrics.csv holds both epochs."""
    import warnings

    from vitfly.training import train_policy

    out = tmp_path / "prog"
    out.mkdir()
    (out / "data.json").write_text('{"hash": "0"}')  # what vitfly pipeline records before training
    kwargs = dict(batch_size=2, progress_bar=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        train_policy(data_path, "convnet", out, max_epochs=1, **kwargs)
        train_policy(data_path, "convnet", out, max_epochs=2, **kwargs)  # resumes from last.ckpt
    assert not [w for w in caught if "exists and is not empty" in str(w.message)]
    with open(out / "metrics.csv") as f:
        epochs = {row["epoch"] for row in csv.DictReader(f) if row.get("val/loss")}
    assert epochs == {"0", "1"}
