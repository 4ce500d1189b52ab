"""Streaming dataset, padding collate, windows, seeded split, LRU cache and DataLoader workers.

``learnable_record`` / ``write_dataset`` are shared with the policy and fit tests: synthetic but real
trajectories (written through TrajectoryWriter) whose expert command is a function of the depth
image and the desired speed, so a network can learn it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from vitfly.datamodules.datamodule import LengthBucketBatchSampler, TrajectoryDataModule, split_trajectories
from vitfly.datamodules.dataset import TrajectoryCache, TrajectoryDataset, collate_trajectories, make_windows
from vitfly.datamodules.schema import TrajectoryRecord, TrajectoryWriter, decode_depth, open_trajectories
from vitfly.errors import VitflyError


def learnable_record(seed: int, length: int) -> TrajectoryRecord:
    """A sphere-like blob drifts across the view; the command steers away from it (y) and climbs (z)."""
    rng = np.random.default_rng(seed)
    speed = float(rng.choice([3.0, 5.0, 7.0]))
    cols = np.clip(45 + np.cumsum(rng.normal(0, 6, size=length)), 5, 84)
    rows = np.clip(30 + np.cumsum(rng.normal(0, 4, size=length)), 5, 54)
    yy, xx = np.mgrid[0:60, 0:90]
    depth = np.ones((length, 60, 90), np.float32)
    for t in range(length):
        blob = (yy - rows[t]) ** 2 + (xx - cols[t]) ** 2 < 12**2
        depth[t][blob] = 0.2
    direction = np.stack([np.ones(length), -(cols - 45) / 45, -(rows - 30) / 30], axis=1)
    cmd = speed * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (length, 1)) + rng.normal(0, 0.01, size=(length, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return TrajectoryRecord(
        depth=depth,
        desired_speed=speed,
        quat=quat,
        position=np.cumsum(cmd / 30.0, axis=0),
        velocity=cmd,
        velocity_cmd=cmd,
        time=np.arange(length) / 30.0,
        collision=np.zeros(length, bool),
        env="spheres",
        seed=seed,
        n_collisions=0,
        success=True,
    )


def write_dataset(path, lengths) -> str:
    with TrajectoryWriter(path, {"made_by": "tests"}) as writer:
        for seed, length in enumerate(lengths):
            writer.append(learnable_record(seed, length))
    return str(path)


@pytest.fixture
def data_path(tmp_path):
    return write_dataset(tmp_path / "data.h5", [7, 12, 5, 9, 16, 3])


def test_items_stream_the_file_rows(data_path):
    ds = TrajectoryDataset(data_path)
    assert len(ds) == 6
    with open_trajectories(data_path) as tf:
        for i in (0, 4):
            item = ds[i]
            rows = tf.read(i)
            assert item["traj_index"] == i and item["start"] == 0
            np.testing.assert_array_equal(item["depth"].numpy(), rows["depth"])
            np.testing.assert_array_equal(item["desired_speed"].numpy()[:, 0], rows["desired_speed"])
            np.testing.assert_array_equal(item["velocity_cmd"].numpy(), rows["velocity_cmd"])
            np.testing.assert_array_equal(item["quat"].numpy(), rows["quat"])


def test_collate_pads_and_masks(data_path):
    ds = TrajectoryDataset(data_path)
    batch = collate_trajectories([ds[2], ds[4], ds[0]])  # lengths 5, 16, 7
    assert batch["depth"].shape == (3, 16, 1, 60, 90) and batch["depth"].dtype == torch.float32
    assert batch["desired_speed"].shape == (3, 16, 1)
    assert batch["quat"].shape == (3, 16, 4) and batch["velocity_cmd"].shape == (3, 16, 3)
    assert batch["mask"].sum(dim=1).tolist() == [5, 16, 7]
    assert not batch["mask"][0, 5:].any() and batch["mask"][0, :5].all()
    assert batch["traj_index"].tolist() == [2, 4, 0]
    expected = decode_depth(ds[2]["depth"].numpy())
    np.testing.assert_allclose(batch["depth"][0, :5, 0].numpy(), expected, atol=1e-7)
    assert float(batch["depth"].max()) <= 1.0
    assert float(batch["depth"][0, 5:].abs().sum()) == 0.0


def test_windows_cut_long_trajectories(data_path):
    assert make_windows([10, 3], [0, 1], 4) == [(0, 0, 4), (0, 4, 8), (0, 8, 10), (1, 0, 3)]
    ds = TrajectoryDataset(data_path, indices=[4], max_length=6)  # trajectory of 16 steps
    assert [(item["start"], item["depth"].shape[0]) for item in ds] == [(0, 6), (6, 6), (12, 4)]
    with open_trajectories(data_path) as tf:
        np.testing.assert_array_equal(ds[1]["velocity_cmd"].numpy(), tf.read(4)["velocity_cmd"][6:12])
    with pytest.raises(VitflyError, match="max_length"):
        TrajectoryDataset(data_path, max_length=0)


def test_split_is_seeded_disjoint_and_recorded(data_path, tmp_path):
    train, val = split_trajectories(10, 0.2, seed=3)
    assert (train, val) == split_trajectories(10, 0.2, seed=3)
    assert sorted(train + val) == list(range(10)) and len(val) == 2
    assert split_trajectories(10, 0.2, seed=4) != (train, val)
    dm = TrajectoryDataModule(data_path, batch_size=2, val_fraction=0.34, split_seed=1, use_state=False)
    dm.setup("fit")
    out = dm.save_split(tmp_path / "run")
    record = json.loads(out.read_text())
    assert record["train"] == dm.train_indices and record["val"] == dm.val_indices
    assert len(record["val"]) == 2 and not set(record["train"]) & set(record["val"])
    assert record["val_seeds"] == record["val"]  # the file's seeds are 0..5 in order
    assert record["use_state"] is False
    # an earlier run's split is reused as recorded
    again = TrajectoryDataModule(data_path, split_file=str(out), split_seed=99)
    again.setup("fit")
    assert again.val_indices == dm.val_indices


def test_batches_hold_whole_trajectories_once_per_epoch(data_path):
    dm = TrajectoryDataModule(data_path, batch_size=2, val_fraction=0.0)
    dm.setup("fit")
    seen = []
    for batch in dm.train_dataloader():
        lengths = batch["mask"].sum(dim=1)
        assert batch["mask"].shape[1] == int(lengths.max())
        seen += batch["traj_index"].tolist()
    assert sorted(seen) == list(range(6))
    assert dm.val_dataloader() == []


def test_length_buckets_reduce_padding_and_are_reproducible():
    lengths = np.random.default_rng(0).integers(10, 500, size=200)
    sampler = LengthBucketBatchSampler(lengths, batch_size=8, shuffle=True, seed=5)
    first = list(sampler)
    assert sorted(i for b in first for i in b) == list(range(200))
    padding = sum(8 * lengths[b].max() - lengths[b].sum() for b in first if len(b) == 8)
    random_batches = np.random.default_rng(1).permutation(200).reshape(-1, 8)
    random_padding = sum(8 * lengths[b].max() - lengths[b].sum() for b in random_batches)
    assert padding < 0.2 * random_padding
    sampler.set_epoch(0)
    assert list(sampler) == first
    assert list(sampler) != first  # the next epoch reshuffles


def test_dataloader_workers_match_the_main_process(data_path):
    kwargs = dict(batch_size=3, val_fraction=0.0, bucket_by_length=False)
    single = TrajectoryDataModule(data_path, num_workers=0, **kwargs)
    multi = TrajectoryDataModule(data_path, num_workers=2, **kwargs)
    for dm in (single, multi):
        dm.setup("fit")
    ds_single, ds_multi = single._datasets["train"], multi._datasets["train"]
    loader = torch.utils.data.DataLoader(ds_multi, batch_size=3, num_workers=2, collate_fn=collate_trajectories)
    for batch in loader:
        expected = collate_trajectories([ds_single[int(i)] for i in batch["traj_index"]])
        for key in expected:
            torch.testing.assert_close(batch[key], expected[key])


def test_lru_cache_is_bounded_and_evicts_least_recent():
    item = {"a": np.zeros(100, np.uint8)}
    cache = TrajectoryCache(max_bytes=250)
    cache.put(0, item)
    cache.put(1, item)
    assert cache.get(0) is item  # 0 is now the most recent
    cache.put(2, item)
    assert cache.get(1) is None and cache.get(0) is item and cache.get(2) is item
    assert cache.bytes == 200 and len(cache) == 2
    cache.put(3, {"a": np.zeros(300, np.uint8)})  # larger than the whole cache: not kept
    assert cache.get(3) is None and cache.bytes == 200


def test_dataset_cache_serves_repeated_reads(data_path):
    ds = TrajectoryDataset(data_path, cache_mb=1)
    first = ds.read_arrays(1)
    assert ds.read_arrays(1) is first
    uncached = TrajectoryDataset(data_path, cache_mb=0)
    assert uncached.read_arrays(1) is not uncached.read_arrays(1)


def test_bad_files_fail_at_setup_with_one_line(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"\x89HDF\r\n\x1a\n" + b"garbage" * 50)
    dm = TrajectoryDataModule(str(bad))
    with pytest.raises(VitflyError, match="bad.h5: cannot open HDF5 file, corrupt"):
        dm.setup("fit")
    truncated = tmp_path / "truncated.h5"
    whole = open(write_dataset(tmp_path / "whole.h5", [20, 20]), "rb").read()
    truncated.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(VitflyError, match="truncated.h5: .*corrupt"):
        TrajectoryDataModule(str(truncated)).setup("fit")
    with pytest.raises(VitflyError, match="no such dataset file"):
        TrajectoryDataModule(str(tmp_path / "missing.h5")).setup("fit")


def test_loader_hands_over_uint8_depth_that_the_transfer_hook_makes_the_contract_float(data_path):
    dm = TrajectoryDataModule(data_path, batch_size=3, val_fraction=0.0, bucket_by_length=False)
    dm.setup("fit")
    ds = dm._datasets["train"]
    for batch in dm.train_dataloader():
        assert batch["depth"].dtype == torch.uint8
        expected = collate_trajectories([ds[int(i)] for i in batch["traj_index"]])
        converted = dm.on_after_batch_transfer(batch, 0)
        assert converted["depth"].dtype == torch.float32
        torch.testing.assert_close(converted["depth"], expected["depth"], rtol=0, atol=0)
        assert float(converted["depth"].max()) <= 1.0


def test_worker_batches_built_in_shared_memory_equal_the_in_process_ones(data_path):
    epochs = []
    for workers in (0, 2):
        dm = TrajectoryDataModule(data_path, batch_size=2, val_fraction=0.0, num_workers=workers)
        dm.setup("fit")
        epochs.append(list(dm.train_dataloader()))
    assert len(epochs[0]) == 3
    for a, b in zip(*epochs, strict=True):
        assert b["depth"].dtype == torch.uint8 and b["depth"].is_shared()
        for key in a:
            assert torch.equal(a[key], b[key]), key
