"""Reading a dataset: ``open_trajectories(path)`` gives a ``TrajectoryFile`` of validated, streamed trajectories.

Nothing is preloaded but ``/traj_offsets`` and the per-trajectory table; a file whose writer was killed opens in
SWMR-read mode and shows exactly the committed trajectories (rows beyond ``off[-1]`` are ignored).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from vitfly.datamodules.readahead import ChunkReadahead
from vitfly.datamodules.schema.checks import (
    _as_str,
    _attr_str,
    _is_crash_flag_error,
    check_finite,
    optional_fields_of,
    read_sensor_attrs,
    validate_file,
)
from vitfly.datamodules.schema.layout import (
    OPTIONAL_ROW_FIELDS,
    OPTIONAL_TRAJ_FIELDS,
    ROW_FIELDS,
    TRAJ_FIELDS,
    TrajectoryRecord,
)
from vitfly.errors import VitflyError


def _open_for_reading(path: Path) -> h5py.File:
    """Open read-only; a file whose writer was killed is opened in SWMR-read mode instead."""
    if not path.exists():
        raise VitflyError(f"{path}: no such dataset file")
    if not h5py.is_hdf5(str(path)):
        raise VitflyError(f"{path}: not an HDF5 file (corrupt or wrong format); expected a vitfly dataset")
    try:
        return h5py.File(path, "r")
    except (OSError, RuntimeError) as err:
        if not _is_crash_flag_error(err) and "lock file" not in str(err):
            raise VitflyError(f"{path}: cannot open HDF5 file, corrupt or truncated ({err})") from None
        # left open for writing (a live or a killed SWMR writer): SWMR-read still sees every commit
        try:
            return h5py.File(path, "r", swmr=True)
        except (OSError, RuntimeError) as err2:
            raise VitflyError(f"{path}: cannot open HDF5 file, corrupt or truncated ({err2})") from None


class TrajectoryFile:
    """Read access to a validated dataset: ``len(tf)`` trajectories, ``tf[m]`` a TrajectoryRecord.

    Reads stream from disk; nothing is preloaded except ``/traj_offsets`` and the per-trajectory
    table. Use as a context manager or call ``close()``. Not shareable across processes: each
    DataLoader worker opens its own (see ``vitfly.datamodules.dataset``).
    """

    def __init__(self, path: str | os.PathLike, *, check_values: bool = True):
        self.path = Path(path)
        self._file = _open_for_reading(self.path)
        try:
            m = validate_file(self._file, self.path)
            self.offsets = self._file["traj_offsets"][...]
            if check_values:
                check_finite(self._file, self.path, int(self.offsets[-1]))
            self.optional_fields = optional_fields_of(self._file)
            table_fields = [*TRAJ_FIELDS, *(k for k in OPTIONAL_TRAJ_FIELDS if k in self.optional_fields)]
            self.table = {name: self._file[f"trajectories/{name}"][:m] for name in table_fields}
            # env as str whatever string type stored it (fixed-length bytes, variable-length str or bytes)
            self.table["env"] = np.array([_as_str(v) for v in self.table["env"]], dtype=object)
            self.sensor = read_sensor_attrs(self._file, self.path)
        except (OSError, RuntimeError, KeyError) as err:
            self._file.close()
            raise VitflyError(f"{self.path}: corrupt HDF5 file, a dataset cannot be read ({err})") from None
        except BaseException:
            self._file.close()
            raise
        self.depth_max_m = float(self._file.attrs["depth_max_m"])
        self._readahead: ChunkReadahead | None = None
        self.config = json.loads(_attr_str(self._file.attrs.get("config", "{}")) or "{}")
        self.vitfly_version = _attr_str(self._file.attrs.get("vitfly_version", ""))

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def lengths(self) -> np.ndarray:
        """(M,) number of steps in each trajectory."""
        return np.diff(self.offsets)

    @property
    def num_rows(self) -> int:
        return int(self.offsets[-1])

    def read(self, m: int, fields: Sequence[str] = tuple(ROW_FIELDS), start: int = 0, stop: int | None = None):
        """Rows [start, stop) of trajectory m as {field: array} in on-disk dtypes (depth stays uint8)."""
        if not 0 <= m < len(self):
            raise IndexError(f"trajectory {m} out of range [0, {len(self)})")
        lo, hi = int(self.offsets[m]), int(self.offsets[m + 1])
        stop = hi - lo if stop is None else stop
        return {name: self._file[name][lo + start : lo + stop] for name in fields}

    def prefetch(self, m: int, fields: Sequence[str] = tuple(ROW_FIELDS)) -> None:
        """Hint the kernel to start reading trajectory m's rows of ``fields`` in the background."""
        if self._readahead is None:
            self._readahead = ChunkReadahead(self._file, self.path)
        self._readahead.advise(fields, int(self.offsets[m]), int(self.offsets[m + 1]))

    @property
    def row_fields(self) -> tuple[str, ...]:
        """The per-row fields this file holds: the schema's, then the optional ones present."""
        return (*ROW_FIELDS, *(k for k in OPTIONAL_ROW_FIELDS if k in self.optional_fields))

    def meta(self, m: int) -> dict[str, Any]:
        """The /trajectories entry of trajectory m (env as str), optional fields included where the file has them."""
        row = {name: values[m] for name, values in self.table.items()}
        return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in row.items()}

    def __getitem__(self, m: int) -> TrajectoryRecord:
        meta = self.meta(m)
        del meta["desired_speed"]  # the per-row speeds are the record's
        return TrajectoryRecord(**self.read(m, self.row_fields), **meta)

    def __iter__(self) -> Iterator[TrajectoryRecord]:
        for m in range(len(self)):
            yield self[m]

    def close(self) -> None:
        if self._readahead is not None:
            self._readahead.close()
        self._file.close()

    def __enter__(self) -> TrajectoryFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_trajectories(path: str | os.PathLike, *, check_values: bool = True) -> TrajectoryFile:
    """Open and validate a vitfly dataset (schema, version, shapes, dtypes, NaN telemetry, non-empty).

    Bad files raise VitflyError with one line naming the file and the field.
    """
    return TrajectoryFile(path, check_values=check_values)
