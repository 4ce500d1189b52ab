"""The HDF5 trajectory dataset, schema version 1: constants, writer, reader and validator.

This module is the single owner of the on-disk format (DESIGN.md "Datasets")::

    / attrs: schema="vitfly.trajectories", schema_version=1, image_shape=[60, 90],
             depth_max_m=10.0, vitfly_version, config (JSON of how it was made),
             optional: camera (JSON of the camera's settings), control_hz (control and camera rate, Hz)
    /depth          uint8   (N, 60, 90)  round(255 * normalised depth); chunked, see DEPTH_STORAGE
    /desired_speed  float32 (N,)         m/s
    /quat           float32 (N, 4)       attitude, body to world, (w, x, y, z)
    /position       float32 (N, 3)       m, world frame
    /velocity       float32 (N, 3)       measured, m/s, world frame
    /velocity_cmd   float32 (N, 3)       expert command (the label), m/s, world frame
    /time           float64 (N,)         s since the trajectory's start
    /collision      bool    (N,)         drone in contact with an obstacle
    /traj_offsets   int64   (M+1,)       trajectory m is rows [off[m], off[m+1])
    /trajectories/{env, seed, desired_speed, n_collisions, success}   (M,) each

Optional fields (version 1 still; files without them stay valid, a writer creates them only when asked):

    /velocity_cmd_executed       float32 (N, 3)  the command actually flown, m/s, world frame; differs from
                                                 /velocity_cmd where another policy flew (DAgger: the student)
    /trajectories/dagger_round   int64   (M,)    DAgger round that flew the trajectory (0: the expert's own data)
    /trajectories/dagger_beta    float32 (M,)    probability that the expert's command was flown at a tick

A file holds each optional field for all of its trajectories or not at all: a writer that reopens a file
with them needs every appended record to carry them, and refuses records that carry fields the file lacks.

Readers accept files written by other tools: ``/trajectories/env`` may be any HDF5 string type
(fixed or variable length, ASCII or UTF-8), integer fields any signed or unsigned integer type, and
every dataset any storage layout (contiguous, chunked, compressed or not). Appending needs the
resizable (chunked) layout this writer creates.

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
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from vitfly import __version__
from vitfly.datamodules.readahead import ChunkReadahead
from vitfly.errors import VitflyError

SCHEMA_NAME = "vitfly.trajectories"
SCHEMA_VERSION = 1
IMAGE_SHAPE = (60, 90)
DEFAULT_DEPTH_MAX_M = 10.0
ENV_NAME_BYTES = 32  # fixed-length env names: SWMR writers cannot grow variable-length heaps safely

# per-row datasets: name -> (dtype, trailing shape)
ROW_FIELDS: dict[str, tuple[np.dtype, tuple[int, ...]]] = {
    "depth": (np.dtype(np.uint8), IMAGE_SHAPE),
    "desired_speed": (np.dtype(np.float32), ()),
    "quat": (np.dtype(np.float32), (4,)),
    "position": (np.dtype(np.float32), (3,)),
    "velocity": (np.dtype(np.float32), (3,)),
    "velocity_cmd": (np.dtype(np.float32), (3,)),
    "time": (np.dtype(np.float64), ()),
    "collision": (np.dtype(np.bool_), ()),
}
# per-trajectory table under /trajectories: name -> dtype
TRAJ_FIELDS: dict[str, np.dtype] = {
    "env": np.dtype(f"S{ENV_NAME_BYTES}"),
    "seed": np.dtype(np.int64),
    "desired_speed": np.dtype(np.float32),
    "n_collisions": np.dtype(np.int64),
    "success": np.dtype(np.bool_),
}
# optional fields (see the module docstring): absent from older files, written only when a writer asks for them
OPTIONAL_ROW_FIELDS: dict[str, tuple[np.dtype, tuple[int, ...]]] = {
    "velocity_cmd_executed": (np.dtype(np.float32), (3,)),
}
OPTIONAL_TRAJ_FIELDS: dict[str, np.dtype] = {
    "dagger_round": np.dtype(np.int64),
    "dagger_beta": np.dtype(np.float32),
}
OPTIONAL_FIELDS = (*OPTIONAL_ROW_FIELDS, *OPTIONAL_TRAJ_FIELDS)
FLOAT_ROW_FIELDS = tuple(k for k, (dt, _) in {**ROW_FIELDS, **OPTIONAL_ROW_FIELDS}.items() if dt.kind == "f")
TELEMETRY_CHUNK_ROWS = 4096
DEPTH_CHUNK_FRAMES = 64
# How /depth is stored (the reader handles both). "none" streams several times faster than "gzip" (gzip
# inflation bounds the reader; benchmarks/loader_headroom.py) for about 2.8x the file size.
CAMERA_ATTR = "camera"  # optional root attr: JSON of the camera geometry (vitfly.sim.CameraConfig fields)
CONTROL_HZ_ATTR = "control_hz"  # optional root attr: float, the rate of the logged ticks (Hz)
DEPTH_STORAGE: dict[str, dict[str, Any]] = {
    # uncompressed chunks are rewritten in place, so an append may share a chunk with committed rows
    "none": {"chunks": (DEPTH_CHUNK_FRAMES, *IMAGE_SHAPE)},
    # a rewritten compressed chunk moves: one frame per chunk keeps committed chunks untouched
    "gzip": {"chunks": (1, *IMAGE_SHAPE), "compression": "gzip", "compression_opts": 4, "shuffle": False},
}


def depth_storage_of(f: h5py.File) -> str:
    """The DEPTH_STORAGE key an existing file's /depth was written with."""
    return "gzip" if f["depth"].compression == "gzip" else "none"


def check_depth_compression(value: str, source: str = "depth_compression") -> None:
    """Raise VitflyError unless ``value`` is a DEPTH_STORAGE key."""
    if value not in DEPTH_STORAGE:
        raise VitflyError(f"{source} is {value!r}; expected one of {', '.join(DEPTH_STORAGE)}")


def encode_depth(depth: np.ndarray) -> np.ndarray:
    """Normalised depth in [0, 1] (float) -> uint8 round(255 * depth), clipped to [0, 255]."""
    return np.clip(np.rint(np.asarray(depth, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)


def decode_depth(depth_u8: np.ndarray) -> np.ndarray:
    """uint8 stored depth -> float32 normalised depth in [0, 1] (metric depth / depth_max_m)."""
    return np.asarray(depth_u8, dtype=np.float32) * np.float32(1.0 / 255.0)


@dataclass
class TrajectoryRecord:
    """One flown trajectory of T control ticks, as written to and read from the dataset.

    depth: uint8 (T, 60, 90) = round(255 * normalised depth); a float array in [0, 1] is encoded.
    desired_speed: m/s, a scalar (constant over the flight) or (T,).
    quat: (T, 4) attitude (w, x, y, z), body to world. position (T, 3) m, velocity (T, 3) m/s and
    velocity_cmd (T, 3) m/s are world frame. time: (T,) s since the start. collision: bool (T,).
    Optional (None: not recorded): velocity_cmd_executed (T, 3) m/s, the command flown when it is not the
    label; dagger_round and dagger_beta, the DAgger round and mixing probability that flew the trajectory.
    """

    depth: np.ndarray
    desired_speed: float | np.ndarray
    quat: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    velocity_cmd: np.ndarray
    time: np.ndarray
    collision: np.ndarray
    env: str = "spheres"
    seed: int = 0
    n_collisions: int = 0
    success: bool = False
    velocity_cmd_executed: np.ndarray | None = None
    dagger_round: int | None = None
    dagger_beta: float | None = None

    def optional_fields(self) -> tuple[str, ...]:
        """The optional schema fields this record carries."""
        return tuple(name for name in OPTIONAL_FIELDS if getattr(self, name) is not None)

    @property
    def length(self) -> int:
        return int(np.asarray(self.depth).shape[0])

    def row_arrays(self) -> dict[str, np.ndarray]:
        """Validated per-row arrays in the on-disk dtypes; raises VitflyError naming the bad field."""
        t = self.length
        depth = np.asarray(self.depth)
        if depth.dtype != np.uint8:
            if depth.dtype.kind != "f":
                raise VitflyError(f"TrajectoryRecord.depth: expected uint8 or float in [0, 1], got {depth.dtype}")
            depth = encode_depth(depth)
        speed = np.asarray(self.desired_speed, dtype=np.float32)
        if speed.ndim == 0:
            speed = np.full((t,), speed, dtype=np.float32)
        arrays = {
            "depth": depth,
            "desired_speed": speed,
            "quat": self.quat,
            "position": self.position,
            "velocity": self.velocity,
            "velocity_cmd": self.velocity_cmd,
            "time": self.time,
            "collision": self.collision,
        }
        fields = dict(ROW_FIELDS)
        if self.velocity_cmd_executed is not None:
            arrays["velocity_cmd_executed"] = self.velocity_cmd_executed
            fields.update(OPTIONAL_ROW_FIELDS)
        out = {}
        for name, (dtype, tail) in fields.items():
            arr = np.asarray(arrays[name])
            if arr.shape != (t, *tail):
                raise VitflyError(f"TrajectoryRecord.{name}: expected shape {(t, *tail)}, got {arr.shape}")
            arr = arr.astype(dtype, copy=False)
            if dtype.kind == "f" and not np.isfinite(arr).all():
                raise VitflyError(f"TrajectoryRecord.{name}: contains NaN or infinite values")
            out[name] = arr
        if t == 0:
            raise VitflyError("TrajectoryRecord: a trajectory needs at least one step (depth has 0 frames)")
        if len(self.env.encode()) > ENV_NAME_BYTES:
            raise VitflyError(f"TrajectoryRecord.env: at most {ENV_NAME_BYTES} bytes, got {self.env!r}")
        return out

    def traj_row(self) -> dict[str, Any]:
        """The /trajectories entry for this record."""
        speed = np.asarray(self.desired_speed, dtype=np.float32)
        row = {
            "env": self.env.encode(),
            "seed": int(self.seed),
            # float64 mean: a constant float32 speed read back from a file is written back unchanged
            "desired_speed": float(speed if speed.ndim == 0 else speed.mean(dtype=np.float64)),
            "n_collisions": int(self.n_collisions),
            "success": bool(self.success),
        }
        if self.dagger_round is not None:
            row["dagger_round"] = int(self.dagger_round)
        if self.dagger_beta is not None:
            beta = float(self.dagger_beta)
            if not 0.0 <= beta <= 1.0:
                raise VitflyError(f"TrajectoryRecord.dagger_beta: expected a probability in [0, 1], got {beta}")
            row["dagger_beta"] = beta
        return row


# ---------------------------------------------------------------------------------------------
# opening files (including ones left behind by a killed SWMR writer)


def _is_crash_flag_error(err: OSError) -> bool:
    return "already open for write" in str(err) or "consistency flags" in str(err)


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


# ---------------------------------------------------------------------------------------------
# validation


def _attr_str(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _show(value: Any) -> str:
    """An attribute value as a user reads it (no numpy reprs)."""
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    return repr(_attr_str(value) if isinstance(value, bytes) else value)


def _table_dtype_ok(found: np.dtype, expected: np.dtype) -> bool:
    """Whether a /trajectories dataset's dtype reads as the schema's: any HDF5 string type for strings (fixed or
    variable length, as other tools write them), any integer type for integers."""
    if expected.kind == "S":
        return h5py.check_string_dtype(found) is not None
    if expected.kind in "iu":
        return found.kind in "iu"
    return found.kind == expected.kind


def _as_str(value: Any) -> str:
    return value.decode("utf-8", errors="replace") if isinstance(value, bytes | np.bytes_) else str(value)


def read_sensor_attrs(f: h5py.File, path: Path) -> dict[str, Any]:
    """The sensor a dataset was recorded with: ``depth_max_m`` (m), ``camera`` (dict of the camera's settings, or
    None when the file does not say) and ``control_hz`` (Hz, or None). Plain values; raises VitflyError on a
    malformed attribute."""
    camera = f.attrs.get(CAMERA_ATTR)
    if camera is not None:
        try:
            camera = json.loads(_attr_str(camera))
        except ValueError:
            camera = None  # reported below
        if not isinstance(camera, dict):
            raise VitflyError(f"{path}: attribute 'camera' must be a JSON object of the camera's settings")
    rate = f.attrs.get(CONTROL_HZ_ATTR)
    if rate is not None:
        rate = np.asarray(rate)
        if rate.shape != () or rate.dtype.kind not in "iuf" or not np.isfinite(rate) or float(rate) <= 0:
            raise VitflyError(f"{path}: attribute 'control_hz' is {_show(rate)}, expected a positive number of Hz")
        rate = float(rate)
    return {"depth_max_m": float(f.attrs["depth_max_m"]), "camera": camera, "control_hz": rate}


def validate_file(f: h5py.File, path: Path, *, allow_empty: bool = False) -> int:
    """Check schema, version, image shape, dataset dtypes/shapes and commit records.

    Returns the number of committed trajectories M. Raises VitflyError with one line naming the
    file and the field. NaN checks over the telemetry are done by ``check_finite``.
    """
    schema = f.attrs.get("schema")
    if schema is None or _attr_str(schema) != SCHEMA_NAME:
        raise VitflyError(
            f"{path}: attribute 'schema' is {_show(schema)}, expected {SCHEMA_NAME!r} (not a vitfly dataset)"
        )
    version = f.attrs.get("schema_version")
    if version is None or int(version) != SCHEMA_VERSION:
        raise VitflyError(
            f"{path}: attribute 'schema_version' is {_show(version)}, this vitfly reads version {SCHEMA_VERSION}"
        )
    shape = tuple(int(v) for v in np.atleast_1d(f.attrs.get("image_shape", [])))
    if shape != IMAGE_SHAPE:
        raise VitflyError(f"{path}: attribute 'image_shape' is {list(shape)}, expected {list(IMAGE_SHAPE)}")
    depth_max = f.attrs.get("depth_max_m")
    if depth_max is None or not np.isfinite(depth_max) or float(depth_max) <= 0:
        raise VitflyError(
            f"{path}: attribute 'depth_max_m' is {_show(depth_max)}, expected a positive number of metres"
        )
    if "traj_offsets" not in f:
        raise VitflyError(f"{path}: dataset '/traj_offsets' is missing")
    offsets = f["traj_offsets"]
    if offsets.dtype != np.int64 or offsets.ndim != 1 or offsets.shape[0] < 1:
        raise VitflyError(f"{path}: dataset '/traj_offsets' must be int64 (M+1,), got {offsets.dtype} {offsets.shape}")
    off = offsets[...]
    m = off.shape[0] - 1
    n_rows = None
    optional = optional_fields_of(f)
    row_fields = {**ROW_FIELDS, **{k: v for k, v in OPTIONAL_ROW_FIELDS.items() if k in optional}}
    for name, (dtype, tail) in row_fields.items():
        if name not in f:
            raise VitflyError(f"{path}: dataset '/{name}' is missing")
        ds = f[name]
        if ds.dtype != dtype:
            raise VitflyError(f"{path}: dataset '/{name}' has dtype {ds.dtype}, expected {dtype}")
        if ds.shape[1:] != tail:
            expected = "(N, " + ", ".join(map(str, tail)) + ")" if tail else "(N,)"
            raise VitflyError(f"{path}: dataset '/{name}' has shape {ds.shape}, expected {expected}")
        n_rows = ds.shape[0] if n_rows is None else min(n_rows, ds.shape[0])
    if off[0] != 0 or np.any(np.diff(off) <= 0) or off[-1] > n_rows:
        raise VitflyError(
            f"{path}: dataset '/traj_offsets' is not an increasing list of row offsets from 0 to <= {n_rows}"
        )
    traj_fields = {**TRAJ_FIELDS, **{k: v for k, v in OPTIONAL_TRAJ_FIELDS.items() if k in optional}}
    for name, dtype in traj_fields.items():
        key = f"trajectories/{name}"
        if key not in f:
            raise VitflyError(f"{path}: dataset '/{key}' is missing")
        ds = f[key]
        if not _table_dtype_ok(ds.dtype, dtype) or ds.ndim != 1 or ds.shape[0] < m:
            expected = "a string type" if name == "env" else str(dtype)
            raise VitflyError(
                f"{path}: dataset '/{key}' must be {expected} with at least {m} entries, got {ds.dtype} {ds.shape}"
            )
    if m == 0 and not allow_empty:
        raise VitflyError(f"{path}: dataset is empty ('/traj_offsets' holds no trajectory)")
    return m


def optional_fields_of(f: h5py.File) -> tuple[str, ...]:
    """The optional schema fields (``OPTIONAL_FIELDS``) an open file holds, in schema order."""
    rows = [name for name in OPTIONAL_ROW_FIELDS if name in f]
    table = [name for name in OPTIONAL_TRAJ_FIELDS if f"trajectories/{name}" in f]
    return (*rows, *table)


def check_finite(f: h5py.File, path: Path, n_rows: int, block: int = 1 << 18) -> None:
    """Raise VitflyError naming the first float telemetry field (and row) that holds NaN or inf."""
    for name in FLOAT_ROW_FIELDS:
        if name not in f:  # an optional field the file does not hold
            continue
        ds = f[name]
        for start in range(0, n_rows, block):
            values = ds[start : min(start + block, n_rows)]
            bad = ~np.isfinite(values)
            if bad.any():
                row = start + int(np.argwhere(bad.reshape(bad.shape[0], -1).any(axis=1))[0, 0])
                raise VitflyError(f"{path}: dataset '/{name}' holds NaN or infinite values (first at row {row})")


# ---------------------------------------------------------------------------------------------
# reader


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


# ---------------------------------------------------------------------------------------------
# writer


def sensor_attrs(camera: dict | None, control_hz: float | None) -> dict[str, Any]:
    """The optional sensor attributes as stored: ``camera`` as a JSON string, ``control_hz`` as a float (Hz)."""
    attrs: dict[str, Any] = {}
    if camera is not None:
        attrs[CAMERA_ATTR] = json.dumps(camera, sort_keys=True)
    if control_hz is not None:
        if not np.isfinite(control_hz) or control_hz <= 0:
            raise VitflyError(f"control_hz: expected a positive number of Hz, got {control_hz}")
        attrs[CONTROL_HZ_ATTR] = float(control_hz)
    return attrs


def _create_layout(
    f: h5py.File,
    config: dict,
    depth_max_m: float,
    depth_compression: str = "none",
    sensor: dict | None = None,
    optional: Sequence[str] = (),
) -> None:
    f.attrs["schema"] = SCHEMA_NAME
    f.attrs["schema_version"] = SCHEMA_VERSION
    f.attrs["image_shape"] = np.asarray(IMAGE_SHAPE, dtype=np.int64)
    f.attrs["depth_max_m"] = float(depth_max_m)
    f.attrs["vitfly_version"] = __version__
    f.attrs["config"] = json.dumps(config, sort_keys=True, default=str)
    for key, value in (sensor or {}).items():
        f.attrs[key] = value
    rows = {**ROW_FIELDS, **{k: v for k, v in OPTIONAL_ROW_FIELDS.items() if k in optional}}
    for name, (dtype, tail) in rows.items():
        if name == "depth":
            f.create_dataset(name, (0, *tail), maxshape=(None, *tail), dtype=dtype, **DEPTH_STORAGE[depth_compression])
        else:
            f.create_dataset(
                name, (0, *tail), maxshape=(None, *tail), dtype=dtype, chunks=(TELEMETRY_CHUNK_ROWS, *tail)
            )
    f.create_dataset("traj_offsets", data=np.zeros(1, dtype=np.int64), maxshape=(None,), chunks=(1024,))
    group = f.create_group("trajectories")
    table = {**TRAJ_FIELDS, **{k: v for k, v in OPTIONAL_TRAJ_FIELDS.items() if k in optional}}
    for name, dtype in table.items():
        group.create_dataset(name, (0,), maxshape=(None,), dtype=dtype, chunks=(1024,))


def _rebuild_committed(src_path: Path, dst_path: Path) -> None:
    """Copy the committed trajectories of a crashed file into a fresh file with the same depth storage."""
    with h5py.File(src_path, "r", swmr=True) as src:
        validate_file(src, src_path, allow_empty=True)
        off = src["traj_offsets"][...]
        m, n = len(off) - 1, int(off[-1])
        config = json.loads(_attr_str(src.attrs.get("config", "{}")) or "{}")
        optional = optional_fields_of(src)
        rows = [*ROW_FIELDS, *(k for k in OPTIONAL_ROW_FIELDS if k in optional)]
        table = [*TRAJ_FIELDS, *(k for k in OPTIONAL_TRAJ_FIELDS if k in optional)]
        with h5py.File(dst_path, "w", libver="latest") as dst:
            storage = depth_storage_of(src)
            _create_layout(dst, config, float(src.attrs["depth_max_m"]), storage, optional=optional)
            for key, value in src.attrs.items():  # schema, version, sensor attributes, ... as they were
                dst.attrs[key] = value
            for name in rows:
                dst[name].resize(n, axis=0)
            copied = set()
            if storage == "gzip":  # one frame per chunk: copy the compressed bytes, no re-compression
                src_depth, dst_depth = src["depth"].id, dst["depth"].id
                for i in range(n):
                    mask, chunk = src_depth.read_direct_chunk((i, 0, 0))
                    dst_depth.write_direct_chunk((i, 0, 0), chunk, mask)
                copied.add("depth")
            for name in rows:
                if name not in copied:
                    for start in range(0, n, 1 << 14):
                        stop = min(start + (1 << 14), n)
                        dst[name][start:stop] = src[name][start:stop]
            for name in table:
                key = f"trajectories/{name}"
                dst[key].resize(m, axis=0)
                dst[key][:] = src[key][:m]
            dst["traj_offsets"].resize(m + 1, axis=0)
            dst["traj_offsets"][:] = off


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


__all__ = [
    "DEFAULT_DEPTH_MAX_M",
    "DEPTH_STORAGE",
    "IMAGE_SHAPE",
    "OPTIONAL_FIELDS",
    "OPTIONAL_ROW_FIELDS",
    "OPTIONAL_TRAJ_FIELDS",
    "ROW_FIELDS",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "TRAJ_FIELDS",
    "TrajectoryFile",
    "TrajectoryRecord",
    "TrajectoryWriter",
    "check_depth_compression",
    "check_finite",
    "decode_depth",
    "depth_storage_of",
    "encode_depth",
    "open_trajectories",
    "optional_fields_of",
    "read_sensor_attrs",
    "sensor_attrs",
    "validate_file",
]
