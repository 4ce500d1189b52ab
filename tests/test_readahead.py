"""Read-ahead: the chunk byte ranges it hints are the rows' real bytes; hints come one batch early and
never change what the loader returns."""

from __future__ import annotations

import zlib

import h5py
import numpy as np
import torch
from test_datamodule import learnable_record

from vitfly.datamodules.datamodule import LengthBucketBatchSampler, TrajectoryDataModule
from vitfly.datamodules.readahead import ChunkReadahead
from vitfly.datamodules.schema import DEPTH_STORAGE, TrajectoryWriter, open_trajectories

LENGTHS = [70, 12, 100, 5, 64, 33]  # trajectories straddle the 64-frame depth chunks


def write(path, storage: str) -> str:
    with TrajectoryWriter(path, {}, depth_compression=storage) as writer:
        for seed, length in enumerate(LENGTHS):
            writer.append(learnable_record(seed, length))
    return str(path)


def test_uncompressed_ranges_hold_exactly_the_rows_chunks(tmp_path):
    path = write(tmp_path / "none.h5", "none")
    raw = (tmp_path / "none.h5").read_bytes()
    rows_per_chunk = DEPTH_STORAGE["none"]["chunks"][0]
    frame = 60 * 90
    with open_trajectories(path) as tf, h5py.File(path, "r") as f:
        ra = ChunkReadahead(f, path)
        for m in range(len(tf)):
            lo, hi = int(tf.offsets[m]), int(tf.offsets[m + 1])
            ranges = ra.byte_ranges("depth", lo, hi)
            data = np.frombuffer(b"".join(raw[a:b] for a, b in ranges), np.uint8)
            first = lo // rows_per_chunk * rows_per_chunk  # the ranges cover whole chunks
            got = data[(lo - first) * frame : (hi - first) * frame].reshape(-1, 60, 90)
            np.testing.assert_array_equal(got, tf.read(m, ["depth"])["depth"])
            quat = ra.byte_ranges("quat", lo, hi)  # telemetry: one 4096-row chunk here
            assert len(quat) == 1 and quat[0][1] - quat[0][0] == f["quat"].chunks[0] * 4 * 4
        assert ra.byte_ranges("depth", 5, 5) == []
        ra.advise(("depth", "quat"), 0, tf.num_rows)
        assert ra.enabled  # the hints went through (Linux has posix_fadvise; this HDF5 has chunk_iter)
        ra.close()


def test_gzip_chunk_ranges_inflate_to_their_frames(tmp_path):
    path = write(tmp_path / "gzip.h5", "gzip")
    raw = (tmp_path / "gzip.h5").read_bytes()
    with open_trajectories(path) as tf, h5py.File(path, "r") as f:
        ra = ChunkReadahead(f, path)
        depth = tf.read(2, ["depth"])["depth"]
        lo = int(tf.offsets[2])
        for t in (0, 1, 57, len(depth) - 1):  # one frame per chunk
            ((a, b),) = ra.byte_ranges("depth", lo + t, lo + t + 1)
            np.testing.assert_array_equal(np.frombuffer(zlib.decompress(raw[a:b]), np.uint8), depth[t].ravel())
        whole = ra.byte_ranges("depth", lo, lo + len(depth))  # adjacent chunks merge
        assert len(whole) < len(depth)


def test_sampler_announces_each_batch_before_handing_it_out():
    calls, handed_out = [], []
    sampler = LengthBucketBatchSampler(list(range(1, 23)), 4, shuffle=True, seed=3, prefetch=calls.append)
    for k, batch in enumerate(sampler):
        handed_out.append(batch)
        assert len(calls) == min(k + 2, len(sampler))  # this batch and the next one are announced
    assert calls == handed_out  # each batch exactly once, in order
    assert sorted(sum(handed_out, [])) == list(range(22))


def test_readahead_does_not_change_the_batches(tmp_path):
    path = write(tmp_path / "none.h5", "none")
    epochs = []
    for readahead in (True, False):
        dm = TrajectoryDataModule(path, batch_size=2, val_fraction=0.0, cache_mb=0, readahead=readahead)
        dm.setup("fit")
        epochs.append(list(dm.train_dataloader()))
    assert len(epochs[0]) == 3
    for a, b in zip(*epochs, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            assert torch.equal(a[key], b[key]), key
