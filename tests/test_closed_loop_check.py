"""ClosedLoopCheck: the network in training flown in held-out scenes every N epochs, logged beside val/loss."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch
from test_datamodule import write_dataset

from vitfly.cli import main
from vitfly.errors import VitflyError
from vitfly.training import train_policy
from vitfly.workflows.closed_loop_check import ClosedLoopCheck
from vitfly.zoo import load_network

REPO = Path(__file__).resolve().parents[1]
torch.set_num_threads(1)


def rows(csv_path: Path) -> list[dict]:
    with open(csv_path) as f:
        return list(csv.DictReader(f))


def test_check_flies_every_n_epochs_and_logs_what_the_network_does(tmp_path):
    data = write_dataset(tmp_path / "d.h5", [9, 12, 7, 10, 8])
    check = ClosedLoopCheck(every_n_epochs=2, trials=1, speeds=[7.0], timeout_s=1.5)
    ckpt = train_policy(data, "convnet", tmp_path / "run", max_epochs=2, batch_size=2, progress_bar=False,
                        policy_kwargs={"warmup_epochs": 0, "tbptt_steps": None}, data_kwargs={"cache_mb": 8},
                        callbacks=[check])
    assert [h["epoch"] for h in check.history] == [1]  # after the 2nd epoch only
    # the logged numbers are the ones the network of that epoch flies: fly last.ckpt again (deterministic sim)
    again = check.fly(load_network(ckpt.parent / "last.ckpt"))
    assert {k: check.history[0][k] for k in again} == again
    logged = [r for r in rows(tmp_path / "run" / "metrics.csv") if r.get("closed_loop/success")]
    assert len(logged) == 1 and logged[0]["epoch"] == "1"
    assert float(logged[0]["closed_loop/success"]) == again["success"]
    assert float(logged[0]["closed_loop/collisions"]) == again["collisions"]
    # and val/r2_* sit in the same log
    assert any(r.get("val/r2_lateral") for r in rows(tmp_path / "run" / "metrics.csv"))


def test_check_is_a_fit_config_callback(tmp_path):
    data = write_dataset(tmp_path / "d.h5", [9, 12, 7, 10])
    config = tmp_path / "callbacks.yaml"
    config.write_text(
        "trainer:\n  callbacks:\n    - class_path: vitfly.workflows.closed_loop_check.ClosedLoopCheck\n"
        "      init_args: {every_n_epochs: 1, trials: 1, speeds: [7.0], timeout_s: 1.0}\n")
    code = main(["fit", "--config", str(REPO / "configs/fit/convnet.yaml"), "--config", str(config),
                 "--data.data_path", data, "--data.num_workers", "0", "--data.batch_size", "2",
                 "--trainer.max_epochs", "1", "--trainer.default_root_dir", str(tmp_path / "fit"),
                 "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"])
    assert code == 0
    (metrics,) = (tmp_path / "fit").glob("version_*/metrics.csv")
    assert any(r.get("closed_loop/success") for r in rows(metrics))


def test_bad_arguments_are_one_line():
    with pytest.raises(VitflyError, match="every_n_epochs, trials and threads must be >= 1"):
        ClosedLoopCheck(every_n_epochs=0)
