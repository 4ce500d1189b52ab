"""Validation of an open dataset file: schema, version, shapes, dtypes, commit records, NaN telemetry, sensor.

Readers accept files written by other tools: ``/trajectories/env`` may be any HDF5 string type
(fixed or variable length, ASCII or UTF-8), integer fields any signed or unsigned integer type, and
every dataset any storage layout (contiguous, chunked, compressed or not). Appending needs the
resizable (chunked) layout that ``writer`` creates.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from vitfly.datamodules.schema.layout import (
    CAMERA_ATTR,
    CONTROL_HZ_ATTR,
    FLOAT_ROW_FIELDS,
    IMAGE_SHAPE,
    OPTIONAL_ROW_FIELDS,
    OPTIONAL_TRAJ_FIELDS,
    ROW_FIELDS,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    TRAJ_FIELDS,
)
from vitfly.errors import VitflyError


def _is_crash_flag_error(err: OSError) -> bool:
    return "already open for write" in str(err) or "consistency flags" in str(err)


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
