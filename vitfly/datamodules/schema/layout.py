"""The HDF5 trajectory dataset, schema version 1: names, fields, depth storage, the record and the empty layout.

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

The reader (``vitfly.datamodules.schema.reader``), the checks every open runs (``.checks``), the writer
(``.writer``) and the rebuild of a crashed file (``.rebuild``) stand beside this module; all their public names
are importable from ``vitfly.datamodules.schema``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import h5py
import numpy as np

from vitfly import __version__
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
