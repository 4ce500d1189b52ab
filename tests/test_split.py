"""A run's train/validation split is frozen: a resumed run on a grown dataset never moves a trained-on
trajectory into validation, and a split that does not fit the dataset is one clear line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from test_datamodule import learnable_record, write_dataset
from test_fit_cli import fit_args, run_dir_of

from vitfly.cli import main
from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.schema import TrajectoryWriter, open_trajectories
from vitfly.datamodules.split import TrajectoryIds, reuse_split, split_trajectories
from vitfly.errors import VitflyError
from vitfly.training import train_policy

FAST = dict(batch_size=2, progress_bar=False, policy_kwargs={"tbptt_steps": 8})


def grow(path, lengths, first_seed: int) -> None:
    """Append trajectories to an existing dataset, as a resumed `vitfly collect` does."""
    with TrajectoryWriter(path, {"made_by": "tests"}) as writer:
        for k, length in enumerate(lengths):
            writer.append(learnable_record(first_seed + k, length))


def ids_of(path) -> TrajectoryIds:
    with open_trajectories(path) as tf:
        return TrajectoryIds.of(tf)


def test_resumed_run_on_a_grown_dataset_keeps_its_validation_trajectories(tmp_path):
    data = write_dataset(tmp_path / "d.h5", [6, 5, 7, 4, 6, 5])
    out = tmp_path / "run"
    train_policy(data, "convnet", out, max_epochs=1, val_fraction=0.34, **FAST)
    first = json.loads((out / "split.json").read_text())
    assert len(first["val"]) == 2 and len(first["train"]) == 4
    grow(data, [5, 6, 4], first_seed=6)
    # the old behaviour, a fresh draw over the 9 trajectories, would validate on trained-on ones:
    # the test is only meaningful if it does
    redrawn_val = split_trajectories(9, 0.34, 0)[1]
    assert set(redrawn_val) & set(first["train"])
    train_policy(data, "convnet", out, max_epochs=2, val_fraction=0.34, **FAST)  # resumes last.ckpt
    second = json.loads((out / "split.json").read_text())
    assert second["val"] == first["val"]  # nothing moved from train to validation
    assert second["train"] == sorted(first["train"] + [6, 7, 8])  # the new trajectories train
    assert second["added_to_train"] == [6, 7, 8] and second["num_trajectories"] == 9
    last = torch.load(out / "checkpoints/last.ckpt", weights_only=True)
    assert last["epoch"] == 1
    stored = last["TrajectoryDataModule"]["split"]  # the split travels with the checkpoint
    assert (stored["train"], stored["val"]) == (second["train"], second["val"])


def test_resume_in_another_directory_reuses_the_checkpoints_split_over_new_settings(tmp_path):
    data = write_dataset(tmp_path / "d.h5", [6, 5, 7, 4, 6])
    assert main(fit_args(data, tmp_path / "a", epochs=1)) == 0
    run_a = run_dir_of(tmp_path / "a")
    split_a = json.loads((run_a / "split.json").read_text())
    grow(data, [5, 4], first_seed=5)
    # another val_fraction and seed would draw another split: the checkpoint's stands
    args = fit_args(data, tmp_path / "b", "--ckpt_path", str(run_a / "checkpoints/last.ckpt"),
                    "--data.val_fraction", "0.5", "--data.split_seed", "7", epochs=2)  # fmt: skip
    assert main(args) == 0
    split_b = json.loads((run_dir_of(tmp_path / "b") / "split.json").read_text())
    assert split_b["val"] == split_a["val"]
    assert split_b["train"] == sorted(split_a["train"] + [5, 6])


def test_reuse_split_extends_training_and_checks_the_dataset(tmp_path):
    data = write_dataset(tmp_path / "d.h5", [5, 6, 7, 8])
    ids = ids_of(data)
    record = {"num_trajectories": 3, "fingerprint": ids.fingerprint(3), "train": [0, 2], "val": [1]}
    split = reuse_split(record, ids, data, "split.json")
    assert (split.train, split.val, split.added) == ([0, 2, 3], [1], (3,))
    # records written before fingerprints: the seeds (0..3 here) must match instead
    old = {"num_trajectories": 4, "train": [0, 1, 3], "val": [2], "train_seeds": [0, 1, 3], "val_seeds": [2]}
    assert reuse_split(old, ids, data, "old.json").val == [2]
    with pytest.raises(VitflyError, match="'val_seeds' does not match"):
        reuse_split({**old, "val_seeds": [9]}, ids, data, "old.json")
    # another dataset: same count, other seeds and lengths
    other = ids_of(write_dataset(tmp_path / "other.h5", [9, 9, 9, 9]))
    foreign = {"num_trajectories": 4, "fingerprint": other.fingerprint(), "train": [0, 1, 2], "val": [3]}
    with pytest.raises(VitflyError, match="split.json: made for another dataset"):
        reuse_split(foreign, ids, data, "split.json")
    bad = [
        ({**record, "val": [4]}, "field 'val' holds trajectory 4, but .* holds 4 trajectories"),
        ({**record, "num_trajectories": 5}, "made for 5 trajectories, but .* holds 4"),
        ({**record, "val": [0]}, "trajectory 0 is in both"),
        ({**record, "train": [0, 0, 2]}, "lists a trajectory twice"),
        ({**record, "train": "0,2"}, "field 'train' must be a list"),
        ({**record, "num_trajectories": 2}, "field 'num_trajectories' is 2"),
    ]
    for rec, message in bad:
        with pytest.raises(VitflyError, match=message):
            reuse_split(rec, ids, data, "split.json")


def write_split(path: Path, record: dict) -> str:
    path.write_text(json.dumps(record))
    return str(path)


@pytest.mark.parametrize("problem", ["index beyond the count", "another dataset", "not json"])
def test_split_file_that_does_not_fit_is_one_line(tmp_path, capsys, problem):
    data = write_dataset(tmp_path / "d.h5", [5, 6, 4])
    ids = ids_of(data)
    record = {"num_trajectories": 3, "fingerprint": ids.fingerprint(), "train": [0, 1], "val": [2]}
    if problem == "index beyond the count":
        record = {**record, "num_trajectories": 6, "val": [5]}
        message = "field 'val' holds trajectory 5, but"
    elif problem == "another dataset":
        record = {**record, "fingerprint": ids_of(write_dataset(tmp_path / "o.h5", [5, 6, 5])).fingerprint()}
        message = "made for another dataset"
    split = tmp_path / "split.json"
    if problem == "not json":
        split.write_text("{train: [0")
        message = "not a readable split file"
    else:
        write_split(split, record)
    assert main(fit_args(data, tmp_path / "run", "--data.split_file", str(split), epochs=1)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("vitfly: error: ") and str(split) in err[-1] and message in err[-1]
    assert not list(tmp_path.glob("run/version_*/checkpoints/*.ckpt"))


def test_resuming_with_a_split_file_other_than_the_checkpoints_is_refused(tmp_path):
    data = write_dataset(tmp_path / "d.h5", [5, 6, 4, 5])
    out = tmp_path / "run"
    train_policy(data, "convnet", out, max_epochs=1, val_fraction=0.25, **FAST)
    trained = json.loads((out / "split.json").read_text())
    swapped = {**trained, "train": sorted(trained["val"] + trained["train"][1:]), "val": trained["train"][:1]}
    other = write_split(tmp_path / "other_split.json", {k: v for k, v in swapped.items() if "seeds" not in k})
    with pytest.raises(VitflyError, match="other_split.json: its train/validation split differs"):
        train_policy(data, "convnet", out, max_epochs=2, data_kwargs={"split_file": other}, **FAST)
    assert json.loads((out / "split.json").read_text()) == trained  # the run's record is left as it was


def test_datamodule_without_a_run_directory_draws_and_records(tmp_path):
    data = write_dataset(tmp_path / "d.h5", [5, 6, 4, 5, 3])
    dm = TrajectoryDataModule(data, val_fraction=0.4, split_seed=2)
    dm.setup("fit")
    assert (dm.train_indices, dm.val_indices) == split_trajectories(5, 0.4, 2)
    record = dm.split_record()
    assert record["fingerprint"] == ids_of(data).fingerprint() and "added_to_train" not in record
