"""Writing a dataset: ``TrajectoryWriter`` creates a file or reopens one to append trajectories to it.

Crash safety (a writer killed with SIGKILL at any moment leaves a file holding exactly the
trajectories whose ``append`` returned): the file is written in HDF5 SWMR mode, whose ordered
metadata flushes keep the on-disk file consistent at every instant. ``append`` writes the rows and
the per-trajectory table first, flushes, and only then extends ``/traj_offsets`` and flushes again:
``/traj_offsets`` is the commit record, and rows beyond ``off[-1]`` are ignored by readers and
dropped when a writer reopens the file. No compressed chunk of a committed trajectory is ever
rewritten (a rewritten compressed chunk moves, and its old space could be reused before the index
points elsewhere): telemetry and, by default, depth are stored uncompressed, whose chunks are
rewritten in place, and gzip-compressed depth (``depth_compression="gzip"``) has one frame per chunk.
After a crash HDF5 refuses a plain open ("file is already open for write"); readers then open in
SWMR-read mode, and a writer rebuilds the committed part into a fresh file and renames it over the
old one (the old file stays untouched until the rename).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from vitfly.datamodules.schema.checks import _attr_str, _is_crash_flag_error, _show, optional_fields_of, validate_file
from vitfly.datamodules.schema.layout import (
    DEFAULT_DEPTH_MAX_M,
    OPTIONAL_FIELDS,
    OPTIONAL_ROW_FIELDS,
    OPTIONAL_TRAJ_FIELDS,
    ROW_FIELDS,
    TRAJ_FIELDS,
    TrajectoryRecord,
    _create_layout,
    check_depth_compression,
    sensor_attrs,
)
from vitfly.datamodules.schema.rebuild import _rebuild_committed
from vitfly.errors import VitflyError


def _check_not_locked(path: Path) -> None:
    """Fail if another live process holds the file (HDF5 takes an flock while writing)."""
    with open(path, "rb") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise VitflyError(f"{path}: the dataset is being written by another process") from None
        fcntl.flock(fh, fcntl.LOCK_UN)


def _tmp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


class TrajectoryWriter:
    """Create a dataset, or reopen one to append to it (resume after an interruption).

    ``append(rec)`` is atomic with respect to SIGKILL: after a crash, reopening gives a readable
    file holding exactly the trajectories whose ``append`` returned. ``config`` (a JSON-able dict
    of how the data was made) is stored on creation; on reopen the stored one is kept, and
    ``depth_max_m`` must match the file's. ``depth_compression`` ("none" or "gzip", see
    DEPTH_STORAGE) applies to a new file; a reopened file keeps the storage it was created with.
    ``camera`` (a JSON-able dict of the camera's settings) and ``control_hz`` (Hz), when known, are
    stored as root attributes of a new file; a reopened file that records them must record the same.
    ``optional_fields`` (names from ``OPTIONAL_FIELDS``) are created in a new file; a reopened file must
    hold them. Every appended record must carry exactly the optional fields the file holds.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        config: dict | None = None,
        depth_max_m: float = DEFAULT_DEPTH_MAX_M,
        depth_compression: str = "none",
        camera: dict | None = None,
        control_hz: float | None = None,
        optional_fields: Sequence[str] = (),
    ):
        self.path = Path(path)
        self.depth_max_m = float(depth_max_m)
        check_depth_compression(depth_compression)
        unknown = [name for name in optional_fields if name not in OPTIONAL_FIELDS]
        if unknown:
            raise VitflyError(f"optional_fields: unknown field {unknown[0]!r}; expected some of "
                              f"{', '.join(OPTIONAL_FIELDS)}")
        self._sensor = sensor_attrs(camera, control_hz)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for stale in self.path.parent.glob(f".{self.path.name}.tmp-*"):
            with contextlib.suppress(OSError):
                pid = int(stale.name.rsplit("-", 1)[1])
                if pid == os.getpid() or not _pid_alive(pid):
                    stale.unlink()
        if self.path.exists():
            self._reopen()
        else:
            tmp = _tmp_path(self.path)
            try:
                with h5py.File(tmp, "w", libver="latest") as f:
                    _create_layout(f, config or {}, self.depth_max_m, depth_compression, self._sensor,
                                   optional=optional_fields)
                os.replace(tmp, self.path)
            finally:
                tmp.unlink(missing_ok=True)
        self._file = h5py.File(self.path, "r+", libver="latest")
        self._file.swmr_mode = True
        off = self._file["traj_offsets"]
        self._num = off.shape[0] - 1
        self._rows = int(off[-1])
        self._seeds = [int(s) for s in self._file["trajectories/seed"][: self._num]]
        self.config = json.loads(_attr_str(self._file.attrs.get("config", "{}")) or "{}")
        self.optional_fields = optional_fields_of(self._file)
        missing = [name for name in optional_fields if name not in self.optional_fields]
        if missing:
            self.close()
            where = f"/trajectories/{missing[0]}" if missing[0] in OPTIONAL_TRAJ_FIELDS else f"/{missing[0]}"
            raise VitflyError(f"{self.path}: dataset '{where}' is missing (the file was made without it); "
                              "write to another --out")

    def _reopen(self) -> None:
        if not h5py.is_hdf5(str(self.path)):
            raise VitflyError(f"{self.path}: exists but is not an HDF5 file; move it away or choose another --out")
        _check_not_locked(self.path)
        try:
            f = h5py.File(self.path, "r+", libver="latest")
        except OSError as err:
            if not _is_crash_flag_error(err):
                raise VitflyError(f"{self.path}: cannot open HDF5 file for appending ({err})") from None
            # the previous writer was killed: rebuild its committed part, then swap files atomically
            tmp = _tmp_path(self.path)
            try:
                _rebuild_committed(self.path, tmp)
                os.replace(tmp, self.path)
            finally:
                tmp.unlink(missing_ok=True)
            f = h5py.File(self.path, "r+", libver="latest")
        with f:
            validate_file(f, self.path, allow_empty=True)
            stored = float(f.attrs["depth_max_m"])
            if not np.isclose(stored, self.depth_max_m):
                raise VitflyError(
                    f"{self.path}: attribute 'depth_max_m' is {stored} m but this writer uses {self.depth_max_m} m"
                )
            for key, value in self._sensor.items():
                if key in f.attrs and _attr_str(f.attrs[key]) != _attr_str(value):
                    raise VitflyError(
                        f"{self.path}: attribute {key!r} is {_show(f.attrs[key])} but this writer records {value!r}"
                    )
            _check_appendable(f, self.path)
            # rows beyond the last commit belong to an interrupted append: drop them
            off = f["traj_offsets"]
            m, n = off.shape[0] - 1, int(off[-1])
            optional = optional_fields_of(f)
            for name in (*ROW_FIELDS, *(k for k in OPTIONAL_ROW_FIELDS if k in optional)):
                if f[name].shape[0] != n:
                    f[name].resize(n, axis=0)
            for name in (*TRAJ_FIELDS, *(k for k in OPTIONAL_TRAJ_FIELDS if k in optional)):
                if f[f"trajectories/{name}"].shape[0] != m:
                    f[f"trajectories/{name}"].resize(m, axis=0)

    @property
    def num_trajectories(self) -> int:
        """Trajectories committed so far."""
        return self._num

    def seeds(self) -> list[int]:
        """Seeds of the committed trajectories, in order (to skip them on resume)."""
        return list(self._seeds)

    def append(self, rec: TrajectoryRecord) -> None:
        """Write one trajectory and commit it; returns only once it is durable against SIGKILL."""
        if self._file is None:
            raise VitflyError(f"{self.path}: writer is closed")
        carried = rec.optional_fields()
        if set(carried) != set(self.optional_fields):
            extra = sorted(set(carried) - set(self.optional_fields))
            lacking = sorted(set(self.optional_fields) - set(carried))
            if extra:
                raise VitflyError(f"{self.path}: the record carries {extra[0]}, which this file does not hold "
                                  "(create the file with it: TrajectoryWriter(optional_fields=...))")
            raise VitflyError(f"{self.path}: the file holds {lacking[0]} for every trajectory; the record lacks it")
        rows = rec.row_arrays()
        meta = rec.traj_row()
        t = rec.length
        lo, hi = self._rows, self._rows + t
        f = self._file
        for name, arr in rows.items():
            ds = f[name]
            if ds.shape[0] < hi:
                ds.resize(hi, axis=0)
            ds[lo:hi] = arr
        m = self._num
        for name, value in meta.items():
            ds = f[f"trajectories/{name}"]
            if ds.shape[0] < m + 1:
                ds.resize(m + 1, axis=0)
            ds[m] = value
        f.flush()
        # the commit: readers see trajectory m only once traj_offsets has grown
        off = f["traj_offsets"]
        off.resize(m + 2, axis=0)
        off[m + 1] = hi
        f.flush()
        self._num, self._rows = m + 1, hi
        self._seeds.append(int(meta["seed"]))

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> TrajectoryWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        with contextlib.suppress(Exception):
            self.close()


def _check_appendable(f: h5py.File, path: Path) -> None:
    """Appending needs this writer's layout: resizable datasets and fixed-length env names (SWMR writers cannot
    grow variable-length heaps safely). Files written by other tools may have neither; they stay readable."""
    optional = optional_fields_of(f)
    names = [*ROW_FIELDS, *(k for k in OPTIONAL_ROW_FIELDS if k in optional), "traj_offsets",
             *(f"trajectories/{n}" for n in (*TRAJ_FIELDS, *(k for k in OPTIONAL_TRAJ_FIELDS if k in optional)))]
    for name in names:
        if f[name].maxshape[0] is not None:
            raise VitflyError(
                f"{path}: dataset '/{name}' has a fixed size (written by another tool?); vitfly reads such files "
                "but cannot append to them: write to another --out"
            )
    env = f["trajectories/env"].dtype
    if env.kind != "S":
        raise VitflyError(
            f"{path}: dataset '/trajectories/env' holds variable-length strings ({env}); vitfly reads such files "
            "but appends only to fixed-length |S32 names: write to another --out"
        )


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
