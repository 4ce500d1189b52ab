"""The committed part of a file whose writer was killed, copied into a fresh file (the writer renames it over the old).

After a crash HDF5 refuses a plain open ("file is already open for write"); the SWMR-read view still holds every
committed trajectory, and that is what is copied: same attributes, same depth storage, compressed depth chunks
copied as they are.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py

from vitfly.datamodules.schema.checks import _attr_str, optional_fields_of, validate_file
from vitfly.datamodules.schema.layout import (
    OPTIONAL_ROW_FIELDS,
    OPTIONAL_TRAJ_FIELDS,
    ROW_FIELDS,
    TRAJ_FIELDS,
    _create_layout,
    depth_storage_of,
)


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
