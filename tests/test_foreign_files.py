"""Schema-v1 files written by other tools, with plain h5py: any string type for /trajectories/env, any storage
layout (contiguous, chunked, compressed) for any dataset. They load, read back, and train with `vitfly fit`."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch
from test_datamodule import learnable_record
from test_fit_cli import fit_args, run_dir_of

from vitfly.cli import main
from vitfly.datamodules.dataset import TrajectoryDataset
from vitfly.datamodules.readahead import ChunkReadahead
from vitfly.datamodules.schema import ROW_FIELDS, TrajectoryWriter, open_trajectories
from vitfly.errors import VitflyError

LENGTHS = [7, 5, 9, 6]
ENVS = ["spheres", "trees", "window", "spheres"]

# env string type, storage of the per-row datasets, of depth, of the per-trajectory table
LAYOUTS = {
    # what plain h5py makes of Python lists and arrays: variable-length UTF-8 str, contiguous everything
    "vlen-str-contiguous": (None, {}, {}, {}),
    # fixed-length UTF-8, chunked + gzip telemetry, lzf depth, chunked table
    "fixed-utf8-compressed": (
        h5py.string_dtype("utf-8", 12),
        {"chunks": True, "compression": "gzip", "shuffle": True},
        {"chunks": (3, 60, 90), "compression": "lzf"},
        {"chunks": True},
    ),
    # variable-length ASCII bytes, chunked uncompressed telemetry with checksums, contiguous depth
    "vlen-bytes-chunked": (h5py.string_dtype("ascii"), {"chunks": (4,), "fletcher32": True}, {}, {}),
}


def write_foreign(path, layout: str) -> list:
    """A schema-v1 file written the way another tool would, with plain h5py (not vitfly's writer)."""
    env_dtype, rows, depth_storage, table = LAYOUTS[layout]
    recs = [learnable_record(seed, n) for seed, n in enumerate(LENGTHS)]
    arrays = [r.row_arrays() for r in recs]
    with h5py.File(path, "w") as f:
        f.attrs.update(schema="vitfly.trajectories", schema_version=1, image_shape=[60, 90], depth_max_m=10.0)
        for name in ROW_FIELDS:
            data = np.concatenate([a[name] for a in arrays])
            storage = depth_storage if name == "depth" else dict(rows)
            if storage.get("chunks") not in (None, True):  # per-row chunks, whatever the trailing shape
                storage["chunks"] = (storage["chunks"][0], *data.shape[1:])
            f.create_dataset(name, data=data, **storage)
        f["traj_offsets"] = np.concatenate([[0], np.cumsum(LENGTHS)]).astype(np.int64)
        g = f.create_group("trajectories")
        if env_dtype is None:
            g["env"] = ENVS  # h5py stores a list of str as variable-length UTF-8 strings
        else:
            g.create_dataset("env", data=[e.encode() for e in ENVS], dtype=env_dtype, **table)
        g.create_dataset("seed", data=np.arange(len(LENGTHS), dtype=np.int32), **table)  # another int type
        g.create_dataset("desired_speed", data=np.array([r.traj_row()["desired_speed"] for r in recs], np.float32))
        g.create_dataset("n_collisions", data=np.zeros(len(LENGTHS), np.int64), **table)
        g.create_dataset("success", data=np.ones(len(LENGTHS), bool), **table)
    return recs


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_foreign_file_reads_back_every_value(tmp_path, layout):
    path = tmp_path / "foreign.h5"
    recs = write_foreign(path, layout)
    with h5py.File(path, "r") as f:
        if layout == "vlen-str-contiguous":
            assert h5py.check_string_dtype(f["trajectories/env"].dtype).length is None  # really variable-length
            assert f["depth"].chunks is None and f["quat"].chunks is None  # really contiguous
    with open_trajectories(path) as tf:
        assert len(tf) == 4 and tf.lengths.tolist() == LENGTHS
        assert [tf.meta(m)["env"] for m in range(4)] == ENVS and tf.meta(2)["seed"] == 2
        for m, rec in enumerate(recs):
            got, want = tf[m].row_arrays(), rec.row_arrays()
            for name in ROW_FIELDS:
                np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    # read-ahead hints whatever can be hinted and skips the rest, without changing what is read
    dataset = TrajectoryDataset(path)
    dataset.prefetch(range(len(dataset)))
    np.testing.assert_array_equal(dataset[1]["velocity_cmd"].numpy(), recs[1].velocity_cmd.astype(np.float32))
    with h5py.File(path, "r") as f:
        ra = ChunkReadahead(f, path)
        for name in ("depth", "quat"):
            ranges = ra.byte_ranges(name, 0, 12)
            assert (ranges == []) == (f[name].chunks is None)  # contiguous: nothing to look up, no hint
        ra.close()


def test_vitfly_fit_trains_on_a_file_written_with_plain_h5py(tmp_path):
    path = tmp_path / "foreign.h5"
    write_foreign(path, "vlen-str-contiguous")
    args = fit_args(str(path), tmp_path / "run", "--trainer.limit_train_batches", "2",
                    "--data.readahead", "true", epochs=1)  # fmt: skip
    assert main(args) == 0
    ckpt = torch.load(run_dir_of(tmp_path / "run") / "checkpoints/last.ckpt", weights_only=True)
    assert ckpt["global_step"] >= 2  # two batches of chunked TBPTT steps were taken


def test_foreign_file_is_readable_but_not_appendable(tmp_path):
    path = tmp_path / "foreign.h5"
    write_foreign(path, "vlen-str-contiguous")
    with pytest.raises(VitflyError, match="dataset '/depth' has a fixed size .* cannot append"):
        TrajectoryWriter(path)
    # resizable datasets, but variable-length names (a SWMR writer cannot grow their heap safely)
    vitfly_written = tmp_path / "ours.h5"
    with TrajectoryWriter(vitfly_written) as writer:
        writer.append(learnable_record(0, 5))
    with h5py.File(vitfly_written, "r+") as f:
        del f["trajectories/env"]
        f["trajectories"].create_dataset("env", data=["spheres"], dtype=h5py.string_dtype(), maxshape=(None,))
    with open_trajectories(vitfly_written) as tf:
        assert tf.meta(0)["env"] == "spheres"
    with pytest.raises(VitflyError, match="'/trajectories/env' holds variable-length strings .* cannot append|appends"):
        TrajectoryWriter(vitfly_written)


def test_env_that_is_not_a_string_is_one_line(tmp_path):
    path = tmp_path / "foreign.h5"
    write_foreign(path, "vlen-str-contiguous")
    with h5py.File(path, "r+") as f:
        del f["trajectories/env"]
        f["trajectories/env"] = np.zeros(4, np.int64)
    with pytest.raises(VitflyError, match="dataset '/trajectories/env' must be a string type with at least 4"):
        open_trajectories(path)
