"""checkpoints/last.ckpt holds the latest epoch, best.ckpt the lowest val/loss, and resuming from last.ckpt
continues where training stopped: through `train_policy` and `vitfly fit`.

The runs train at lr 0: the weights stay, only ConvNet's BatchNorm statistics move, and the validation loss
never improves on epoch 0's. best.ckpt stays at epoch 0 while last.ckpt must move on (Lightning 2.6's own
``save_last`` left it at epoch 0 as well).
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

import pytest
import torch
from lightning.pytorch.callbacks import Callback
from test_datamodule import write_dataset
from test_fit_cli import fit_args, run_dir_of

from vitfly.cli import main
from vitfly.errors import VitflyError
from vitfly.training import train_policy

FROZEN = dict(batch_size=2, progress_bar=False, policy_kwargs={"tbptt_steps": 8, "lr": 0.0, "cpu_threads": 1})
FROZEN_CLI = ("--model.init_args.tbptt_steps", "8", "--model.init_args.lr", "0.0",
              "--model.init_args.cpu_threads", "1")  # fmt: skip


class Record(Callback):
    """The epochs this fit trained, the step count at each epoch end and where training ended."""

    def __init__(self, sleep_s: float = 0.0):
        self.sleep_s, self.epochs, self.epoch_end_steps, self.end = sleep_s, [], [], None

    def on_train_epoch_start(self, trainer, pl_module):
        self.epochs.append(trainer.current_epoch)

    def on_train_batch_end(self, *args):
        time.sleep(self.sleep_s)  # makes a max_time stop fall inside an epoch

    def on_train_epoch_end(self, trainer, pl_module):
        self.epoch_end_steps.append(trainer.global_step)

    def on_train_end(self, trainer, pl_module):
        self.end = trainer.global_step


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("data") / "d.h5", [12, 9, 15, 7, 11])


def load(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def epoch_column(metrics: Path, column: str) -> dict[int, str]:
    """{epoch: value} of the rows of a CSVLogger metrics.csv that hold ``column``."""
    with open(metrics) as fh:
        return {int(r["epoch"]): r[column] for r in csv.DictReader(fh) if r[column]}


def test_train_policy_last_holds_the_latest_epoch_and_resumes_there(data_path, tmp_path):
    out = tmp_path / "run"
    first = Record()
    best_path = train_policy(data_path, "convnet", out, max_epochs=3, callbacks=[first], **FROZEN)
    val_loss = epoch_column(out / "metrics.csv", "val/loss")
    assert sorted(val_loss) == [0, 1, 2] and min(val_loss, key=val_loss.get) == 0  # no later epoch improves
    best, last = load(out / "checkpoints/best.ckpt"), load(out / "checkpoints/last.ckpt")
    assert best_path == out / "checkpoints/best.ckpt"
    assert (best["epoch"], last["epoch"]) == (0, 2)
    steps = first.epoch_end_steps  # every epoch trains the same batches
    assert best["global_step"] == steps[0] and last["global_step"] == steps[2] == 3 * steps[0]
    # both callbacks' states travel, under distinct keys; the best one's is the state after epoch 2
    best_state = [v for k, v in last["callbacks"].items() if k.startswith("ModelCheckpoint{'monitor': 'val/loss'")]
    assert len(last["callbacks"]) >= 2 and len(best_state) == 1
    assert Path(best_state[0]["best_model_path"]) == out / "checkpoints/best.ckpt"
    assert float(best_state[0]["best_model_score"]) == pytest.approx(float(val_loss[0]))

    # a killed session's row of an epoch it did not finish (epoch 3; last.ckpt holds epoch 2)
    with open(out / "metrics.csv", "a", newline="") as fh:
        header = next(csv.reader(open(out / "metrics.csv")))
        csv.DictWriter(fh, fieldnames=header).writerow({"epoch": 3, "step": 999, "val/loss": -1.0})

    # called again with one more epoch: it trains epoch 3 only, from epoch 2's state
    again = Record()
    assert train_policy(data_path, "convnet", out, max_epochs=4, callbacks=[again], **FROZEN) == best_path
    assert again.epochs == [3]
    last = load(out / "checkpoints/last.ckpt")
    assert (last["epoch"], last["global_step"]) == (3, 4 * steps[0])
    # Lightning's CSVLogger empties metrics.csv on a resume; the curve stays whole: epochs 0-2 as they were, the
    # killed session's epoch-3 row gone, epoch 3 as this session trained it
    curve = epoch_column(out / "metrics.csv", "val/loss")
    assert sorted(curve) == [0, 1, 2, 3] and all(curve[e] == val_loss[e] for e in (0, 1, 2))
    assert float(curve[3]) >= float(val_loss[0]) and not (out / "metrics.earlier.csv").exists()
    assert load(out / "checkpoints/best.ckpt")["epoch"] == 0


def test_select_last_hands_on_the_final_epoch_and_keeps_no_best(data_path, tmp_path):
    """``select="last"`` (the paper preset, as the original code): the validation loss never improves on epoch
    0's here, yet the checkpoint handed on is epoch 2's, and no best.ckpt is written."""
    out = tmp_path / "run"
    handed_on = train_policy(data_path, "convnet", out, max_epochs=3, select="last", **FROZEN)
    assert handed_on == out / "checkpoints/last.ckpt"
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["last.ckpt"]
    last = load(out / "checkpoints/last.ckpt")
    assert last["epoch"] == 2
    assert not any(k.startswith("ModelCheckpoint{'monitor': 'val/loss'") for k in last["callbacks"])
    with pytest.raises(VitflyError, match="select: expected one of best, last, got 'median'"):
        train_policy(data_path, "convnet", tmp_path / "other", max_epochs=1, select="median", **FROZEN)
    assert not (tmp_path / "other").exists()  # refused before anything is written


class SlowValidation(Callback):
    """Every validation batch of a fit takes ``sleep_s`` longer (the sanity check's too)."""

    def __init__(self, sleep_s: float) -> None:
        self.sleep_s, self.batches = sleep_s, 0

    def on_validation_batch_end(self, trainer, *args, **kwargs) -> None:
        time.sleep(self.sleep_s)
        self.batches += not trainer.sanity_checking


def test_every_epoch_says_how_long_it_trained_and_validated(data_path, tmp_path):
    """metrics.csv's ``time/val_s``: the seconds of the epoch's validation loop (here at least the 0.3 s slept
    in each of its batches; the sanity check's not counted); ``time/train_s``: the rest of the epoch."""
    slow = SlowValidation(0.3)
    started = time.monotonic()
    train_policy(data_path, "convnet", tmp_path / "run", max_epochs=2, callbacks=[slow], **FROZEN)
    wall_s = time.monotonic() - started
    val_s = {e: float(v) for e, v in epoch_column(tmp_path / "run" / "metrics.csv", "time/val_s").items()}
    train_s = {e: float(v) for e, v in epoch_column(tmp_path / "run" / "metrics.csv", "time/train_s").items()}
    assert sorted(val_s) == sorted(train_s) == [0, 1] and slow.batches == 2  # one validation batch an epoch
    for epoch in (0, 1):
        assert 0.3 <= val_s[epoch] < 0.3 + 5.0 and 0 < train_s[epoch]
    assert sum(val_s.values()) + sum(train_s.values()) < wall_s - 0.3  # the sanity check's sleep is outside


@pytest.mark.parametrize(
    "trainer_kwargs, sleep_s",
    [({"max_steps": 6}, 0.0), ({"max_time": {"seconds": 2}}, 0.8)],
    ids=["max_steps", "max_time"],
)
def test_last_holds_the_final_state_when_training_stops_inside_an_epoch(data_path, tmp_path, trainer_kwargs, sleep_s):
    record = Record(sleep_s)
    train_policy(data_path, "convnet", tmp_path / "run", max_epochs=3, callbacks=[record],
                 trainer_kwargs=trainer_kwargs, **FROZEN)  # fmt: skip
    last = load(tmp_path / "run/checkpoints/last.ckpt")
    assert last["global_step"] == record.end
    # 4 training trajectories of 7 to 15 steps in 2 batches, each ceil(longest / 8) = 2 chunks: 4 steps an epoch
    assert record.end < 3 * 4  # it stopped before the 3 epochs were done
    if "max_steps" in trainer_kwargs:
        assert (last["epoch"], last["global_step"]) == (1, 6)  # two steps into epoch 1


def test_fit_cli_last_holds_the_latest_epoch_and_resumes_by_path_and_by_last(data_path, tmp_path):
    assert main(fit_args(data_path, tmp_path / "a", *FROZEN_CLI, epochs=3)) == 0
    run_a = run_dir_of(tmp_path / "a")
    assert load(run_a / "checkpoints/best.ckpt")["epoch"] == 0
    last_a = load(run_a / "checkpoints/last.ckpt")
    assert last_a["epoch"] == 2

    # resume by path into a new run whose checkpoints go to a chosen directory (a --checkpoint.* override)
    ckpts = tmp_path / "ckpts"
    args = fit_args(data_path, tmp_path / "b", *FROZEN_CLI, "--checkpoint.dirpath", str(ckpts),
                    "--ckpt_path", str(run_a / "checkpoints/last.ckpt"), epochs=4)  # fmt: skip
    assert main(args) == 0
    assert sorted(epoch_column(run_dir_of(tmp_path / "b") / "metrics.csv", "val/loss")) == [3]  # epoch 3 only
    last_b = load(ckpts / "last.ckpt")
    assert (last_b["epoch"], last_b["global_step"]) == (3, last_a["global_step"] * 4 // 3)
    assert (ckpts / "best.ckpt").exists() and not list((run_dir_of(tmp_path / "b") / "checkpoints").glob("*"))

    # `--ckpt_path last` finds ckpts/last.ckpt and goes on from epoch 4
    args = fit_args(data_path, tmp_path / "c", *FROZEN_CLI, "--checkpoint.dirpath", str(ckpts),
                    "--ckpt_path", "last", epochs=5)  # fmt: skip
    assert main(args) == 0
    assert sorted(epoch_column(run_dir_of(tmp_path / "c") / "metrics.csv", "val/loss")) == [4]
    assert load(ckpts / "last.ckpt")["epoch"] == 4


def test_how_often_a_run_validates_never_changes_the_weights(data_path, tmp_path):
    """LSTMnet draws dropout masks from the global generator; validating every epoch or only after the third
    trains the same weights and optimiser moments, bit for bit (before, each validation's data loader drew its
    worker seed from that generator and shifted every later mask), so the paper preset may validate every 5th
    epoch. The run that validates less logs ``val/loss`` at epoch 2 only."""
    kwargs = dict(batch_size=2, progress_bar=False, select="last",
                  policy_kwargs={"tbptt_steps": 8, "lr": 1e-3, "cpu_threads": 1})
    states = {}
    for every in (1, 3):
        out = tmp_path / f"every{every}"
        train_policy(data_path, "lstmnet", out, max_epochs=3, trainer_kwargs={"check_val_every_n_epoch": every},
                     **kwargs)
        states[every] = load(out / "checkpoints/last.ckpt")
        assert sorted(epoch_column(out / "metrics.csv", "val/loss")) == ([0, 1, 2] if every == 1 else [2])
    one, three = states[1], states[3]
    assert one["global_step"] == three["global_step"] > 0
    assert all(torch.equal(one["state_dict"][k], three["state_dict"][k]) for k in one["state_dict"])
    moments = [[t for s in c["optimizer_states"][0]["state"].values() for t in s.values()] for c in (one, three)]
    assert len(moments[0]) > 0 and all(torch.equal(a, b) for a, b in zip(*moments, strict=True))
    assert one["state_dict"].keys() == three["state_dict"].keys()
    # the weights moved: lr 1e-3, not a frozen run
    start = train_policy(data_path, "lstmnet", tmp_path / "zero", max_epochs=1, **{**kwargs, "policy_kwargs":
                         {**kwargs["policy_kwargs"], "lr": 0.0}})
    untrained = load(start)["state_dict"]
    assert any(not torch.equal(untrained[k], one["state_dict"][k]) for k in untrained if "weight" in k)
