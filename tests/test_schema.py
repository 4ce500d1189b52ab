"""HDF5 schema v1: round trip, resume, SIGKILL safety of the writer, and the validator's one-liners."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import h5py
import numpy as np
import pytest

from vitfly.datamodules.schema import (
    TrajectoryRecord,
    TrajectoryWriter,
    decode_depth,
    encode_depth,
    open_trajectories,
)
from vitfly.errors import VitflyError


def make_record(seed: int, length: int | None = None) -> TrajectoryRecord:
    """A deterministic, seed-dependent trajectory (values differ per seed so mix-ups show)."""
    rng = np.random.default_rng(seed)
    t = length if length is not None else int(rng.integers(5, 40))
    quat = rng.normal(size=(t, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    collision = rng.random(t) < 0.2
    return TrajectoryRecord(
        depth=rng.integers(0, 256, size=(t, 60, 90), dtype=np.uint8),
        desired_speed=float(3 + seed % 5),
        quat=quat,
        position=rng.normal(size=(t, 3)),
        velocity=rng.normal(size=(t, 3)),
        velocity_cmd=rng.normal(size=(t, 3)),
        time=np.arange(t) / 30.0,
        collision=collision,
        env="spheres",
        seed=seed,
        n_collisions=int(collision.sum()),
        success=bool(seed % 2),
    )


def assert_same(a: TrajectoryRecord, b: TrajectoryRecord) -> None:
    ra, rb = a.row_arrays(), b.row_arrays()
    for name in ra:
        np.testing.assert_array_equal(ra[name], rb[name], err_msg=name)
    assert (a.env, a.seed, a.n_collisions, a.success) == (b.env, b.seed, b.n_collisions, b.success)


def test_depth_encoding_rounds_to_nearest_level():
    depth = np.array([0.0, 0.5, 1.0, 1.7, -0.2, 0.3])
    enc = encode_depth(depth)
    np.testing.assert_array_equal(enc, [0, 128, 255, 255, 0, 76])
    assert np.abs(decode_depth(enc)[:4] - np.clip(depth[:4], 0, 1)).max() <= 0.5 / 255 + 1e-7


@pytest.mark.parametrize(("storage", "chunk_frames"), [("none", 64), ("gzip", 1)])
def test_round_trip_and_resume(tmp_path, storage, chunk_frames):
    path = tmp_path / "d.h5"
    records = [make_record(s) for s in range(5)]
    with TrajectoryWriter(path, {"env": "spheres", "n": 5}, depth_max_m=10.0, depth_compression=storage) as w:
        for rec in records[:3]:
            w.append(rec)
        assert w.num_trajectories == 3
    other = "gzip" if storage == "none" else "none"
    with TrajectoryWriter(path, {"ignored": True}, depth_compression=other) as w:  # reopen to append: layout kept
        assert w.seeds() == [0, 1, 2]
        for rec in records[3:]:
            w.append(rec)
    with open_trajectories(path) as tf:
        assert len(tf) == 5
        assert tf.config == {"env": "spheres", "n": 5}
        assert tf.depth_max_m == 10.0
        np.testing.assert_array_equal(tf.lengths, [r.length for r in records])
        for m, rec in enumerate(records):
            assert_same(tf[m], rec)
        part = tf.read(2, ("velocity_cmd",), start=1, stop=3)
        np.testing.assert_allclose(part["velocity_cmd"], records[2].velocity_cmd[1:3].astype(np.float32))
    with h5py.File(path, "r") as f:
        assert f["depth"].compression == (None if storage == "none" else "gzip")
        assert f["depth"].chunks == (chunk_frames, 60, 90)


def test_unknown_depth_compression_is_one_line(tmp_path):
    with pytest.raises(VitflyError, match="depth_compression is 'lz4'; expected one of none, gzip"):
        TrajectoryWriter(tmp_path / "d.h5", {}, depth_compression="lz4")
    assert not (tmp_path / "d.h5").exists()


def test_float_depth_is_encoded_and_scalar_speed_broadcast(tmp_path):
    rec = make_record(7, length=4)
    rec.depth = decode_depth(rec.depth)
    with TrajectoryWriter(tmp_path / "d.h5", {}) as w:
        w.append(rec)
    with open_trajectories(tmp_path / "d.h5") as tf:
        got = tf[0]
        np.testing.assert_array_equal(got.depth, encode_depth(rec.depth))
        np.testing.assert_array_equal(got.desired_speed, np.full(4, rec.desired_speed, np.float32))


def test_writer_rejects_bad_record_and_other_depth_range(tmp_path):
    path = tmp_path / "d.h5"
    bad = make_record(1, length=6)
    bad.quat = bad.quat[:, :3]
    with TrajectoryWriter(path, {}) as w:
        with pytest.raises(VitflyError, match=r"TrajectoryRecord.quat: expected shape \(6, 4\)"):
            w.append(bad)
        nan = make_record(2, length=6)
        nan.velocity_cmd[3, 1] = np.nan
        with pytest.raises(VitflyError, match="velocity_cmd: contains NaN"):
            w.append(nan)
        w.append(make_record(3))
    with pytest.raises(VitflyError, match="depth_max_m"):
        TrajectoryWriter(path, {}, depth_max_m=20.0)


WRITER_SCRIPT = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {tests!r})
    from test_schema import make_record
    from vitfly.datamodules.schema import TrajectoryWriter
    with TrajectoryWriter({path!r}, {{"kill": "test"}}, depth_compression={storage!r}) as w:
        seed = w.num_trajectories
        while True:
            w.append(make_record(seed, length=30 + seed % 7))
            print(seed, flush=True)
            seed += 1
    """
)


def _run_and_kill(path, min_commits: int, extra_delay: float, storage: str) -> int:
    """Start a real writer process, SIGKILL it mid-run; return how many appends it reported."""
    script = WRITER_SCRIPT.format(tests=os.path.dirname(__file__), path=str(path), storage=storage)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    reported = 0
    try:
        while reported < min_commits:
            line = proc.stdout.readline()
            assert line, "writer process died on its own"
            reported += 1
        time.sleep(extra_delay)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    reported += sum(1 for _ in proc.stdout)  # lines printed before the kill
    proc.stdout.close()
    return reported


# "none" shares 64-frame depth chunks between trajectories; "gzip" has one compressed chunk per frame
@pytest.mark.parametrize("storage", ["none", "gzip"])
def test_sigkill_mid_write_keeps_exactly_the_committed_trajectories(tmp_path, storage):
    path = tmp_path / "killed.h5"
    rng = np.random.default_rng(0)
    total_reported = 0
    for round_ in range(4):
        reported = _run_and_kill(path, min_commits=2, extra_delay=float(rng.uniform(0.0, 0.05)), storage=storage)
        total_reported += reported
        with open_trajectories(path) as tf:  # opens a crashed file without any repair step
            committed = len(tf)
            # append() returned for every printed seed; at most one more returned just before the kill
            assert total_reported <= committed <= total_reported + 1 + round_, (round_, committed, total_reported)
            for m in range(committed):
                assert_same(tf[m], make_record(m, length=30 + m % 7))
        total_reported = committed
    # a writer reopening the crashed file drops the half-written rows and appends after the commits
    with TrajectoryWriter(path, {}) as w:
        assert w.seeds() == list(range(committed))
        w.append(make_record(committed, length=30 + committed % 7))
    with open_trajectories(path) as tf:
        assert len(tf) == committed + 1
        assert_same(tf[committed], make_record(committed, length=30 + committed % 7))
        with h5py.File(path, "r") as f:  # the rebuilt file opens normally again, with the same storage
            assert f["depth"].shape[0] == tf.num_rows
            assert f["depth"].compression == (None if storage == "none" else "gzip")


# ---- validation: one line naming file and field -------------------------------------------------


@pytest.fixture
def good_file(tmp_path):
    path = tmp_path / "good.h5"
    with TrajectoryWriter(path, {}) as w:
        w.append(make_record(0, length=8))
        w.append(make_record(1, length=5))
    return path


def _edit(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f)


def test_missing_and_non_hdf5_files(tmp_path):
    with pytest.raises(VitflyError, match="no such dataset file"):
        open_trajectories(tmp_path / "nope.h5")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"this is not hdf5" * 100)
    with pytest.raises(VitflyError, match=r"junk.h5: not an HDF5 file"):
        open_trajectories(junk)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda f: f.attrs.__setitem__("schema", "something.else"), "attribute 'schema' is"),
        (lambda f: f.attrs.__setitem__("schema_version", 2), "attribute 'schema_version' is 2"),
        (lambda f: f.attrs.__setitem__("image_shape", [64, 64]), r"'image_shape' is \[64, 64\], expected \[60, 90\]"),
        (lambda f: f.__delitem__("quat"), "dataset '/quat' is missing"),
        (
            lambda f: (f.__delitem__("time"), f.create_dataset("time", data=np.zeros(13, np.float32))),
            "dataset '/time' has dtype float32, expected float64",
        ),
        (lambda f: f["velocity_cmd"].__setitem__((3, 0), np.nan), r"'/velocity_cmd' holds NaN .* row 3"),
    ],
)
def test_validator_names_file_and_field(good_file, edit, message):
    _edit(good_file, edit)
    with pytest.raises(VitflyError, match=message) as info:
        open_trajectories(good_file)
    assert str(good_file) in str(info.value)
    assert "\n" not in str(info.value)


def test_empty_dataset_is_an_error(tmp_path):
    path = tmp_path / "empty.h5"
    TrajectoryWriter(path, {}).close()
    with pytest.raises(VitflyError, match="dataset is empty"):
        open_trajectories(path)
