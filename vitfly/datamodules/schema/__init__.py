"""The HDF5 trajectory dataset, schema version 1 (docs/datasets.md): one import for all of it.

- ``layout``: names, version, fields, depth storage and codec, ``TrajectoryRecord``, the empty file's layout;
  its docstring is the documented schema.
- ``checks``: what every open validates (schema, version, shapes, dtypes, commit records, NaN telemetry, sensor).
- ``reader``: ``open_trajectories`` / ``TrajectoryFile``.
- ``writer``: ``TrajectoryWriter``, crash-safe appends.
- ``rebuild``: the committed part of a file whose writer was killed.
"""

from vitfly.datamodules.schema.checks import (
    check_finite,
    optional_fields_of,
    read_sensor_attrs,
    validate_file,
)
from vitfly.datamodules.schema.layout import (
    CAMERA_ATTR,
    CONTROL_HZ_ATTR,
    DEFAULT_DEPTH_MAX_M,
    DEPTH_CHUNK_FRAMES,
    DEPTH_STORAGE,
    ENV_NAME_BYTES,
    FLOAT_ROW_FIELDS,
    IMAGE_SHAPE,
    OPTIONAL_FIELDS,
    OPTIONAL_ROW_FIELDS,
    OPTIONAL_TRAJ_FIELDS,
    ROW_FIELDS,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    TELEMETRY_CHUNK_ROWS,
    TRAJ_FIELDS,
    TrajectoryRecord,
    check_depth_compression,
    decode_depth,
    depth_storage_of,
    encode_depth,
    sensor_attrs,
)
from vitfly.datamodules.schema.reader import TrajectoryFile, open_trajectories
from vitfly.datamodules.schema.rebuild import _rebuild_committed  # noqa: F401  (tests rebuild a crashed file)
from vitfly.datamodules.schema.writer import TrajectoryWriter

__all__ = [
    "CAMERA_ATTR",
    "CONTROL_HZ_ATTR",
    "DEFAULT_DEPTH_MAX_M",
    "DEPTH_CHUNK_FRAMES",
    "DEPTH_STORAGE",
    "ENV_NAME_BYTES",
    "FLOAT_ROW_FIELDS",
    "IMAGE_SHAPE",
    "OPTIONAL_FIELDS",
    "OPTIONAL_ROW_FIELDS",
    "OPTIONAL_TRAJ_FIELDS",
    "ROW_FIELDS",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "TELEMETRY_CHUNK_ROWS",
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
