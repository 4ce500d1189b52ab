"""Import the original ViTfly dataset (folders of ``<timestamp>.png`` + ``data.csv``) into HDF5 schema v1.

Original layout, one folder per trajectory::

    DIR/<trajectory>/<timestamp>.png     8-bit depth images; pixel / 255 = normalised depth
    DIR/<trajectory>/data.csv            written by pandas: an unnamed index column, then
        timestamp, desired_vel, quat_1..quat_4 (w, x, y, z), pos_x/y/z, vel_x/y/z, velcmd_x/y/z,
        ct_cmd, br_cmd_x/y/z, is_collide (True/False)

Known quirks, handled as the original training code did: one extra image after the last telemetry
row (dropped); telemetry rows holding NaN (dropped with their image); folders whose image and row
counts still disagree, or that are empty or lack data.csv (skipped with a warning and counted).
Images of another size are resized to 60 x 90 bilinearly (half-pixel centres, no antialiasing, as
OpenCV's default resize in the original code).

The imported file records the original camera (root attribute ``camera``, see ``original_camera``):
Flightmare rendered 640 x 480 depth with a 100 degree vertical field of view from 0.3 m forward of the
body origin, and ``user_code`` resized it to 90 x 60. It records no ``control_hz``: the original logged a
row whenever more than 0.03 s had passed since the last one, at whatever rate the simulator's
callbacks came, so the rate of the rows is not a known constant.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from vitfly.datamodules.schema import (
    DEFAULT_DEPTH_MAX_M,
    IMAGE_SHAPE,
    TrajectoryRecord,
    TrajectoryWriter,
    encode_depth,
)
from vitfly.errors import VitflyError

LEGACY_ENV = "legacy"
CSV_NAME = "data.csv"


def original_camera(depth_max_m: float) -> dict:
    """The camera of the original dataset as ``vitfly.sim.camera.CameraConfig`` fields (plain values: this package
    does not import the simulator): the camera visionsim_node actually rendered with, ``rgb_camera`` of
    flightpy/configs/vision/config.yaml (its camera_config.yaml is skipped, see ``vitfly.sim.camera``): a 640 x 480
    render at a 100 degree vertical field of view, mounted 0.3 m forward of the body origin, resized to 90 x 60;
    depth normalised by ``depth_max_m``."""
    return {
        "height": IMAGE_SHAPE[0],
        "width": IMAGE_SHAPE[1],
        "vertical_fov_deg": 100.0,
        "source_width": 640,
        "source_height": 480,
        "mount_offset_m": [0.3, 0.0, 0.0],
        "max_range_m": float(depth_max_m),
    }


# data.csv columns vitfly keeps (the thrust/body-rate commands ct_cmd, br_cmd_* are not part of schema v1)
NUMERIC_COLUMNS = (
    "timestamp", "desired_vel",
    "quat_1", "quat_2", "quat_3", "quat_4",
    "pos_x", "pos_y", "pos_z",
    "vel_x", "vel_y", "vel_z",
    "velcmd_x", "velcmd_y", "velcmd_z",
)  # fmt: skip
COLLISION_COLUMN = "is_collide"
_TRUE = {"true", "1", "1.0"}
_FALSE = {"false", "0", "0.0"}


@dataclass
class ImportSummary:
    """What an import did; folders skipped are listed with the reason."""

    imported: int = 0
    already_present: int = 0
    rows: int = 0
    extra_images_dropped: int = 0
    nan_rows_dropped: int = 0
    skipped: dict[str, str] = field(default_factory=dict)

    def lines(self) -> list[str]:
        out = [
            f"imported {self.imported} trajectories ({self.rows} steps)",
            f"already in the output (resumed): {self.already_present}",
            f"extra trailing images dropped: {self.extra_images_dropped}",
            f"telemetry rows with NaN dropped: {self.nan_rows_dropped}",
            f"folders skipped: {len(self.skipped)}",
        ]
        out += [f"  {name}: {reason}" for name, reason in sorted(self.skipped.items())]
        return out


class SkipFolder(Exception):
    """A trajectory folder that cannot be imported (the reason is the message)."""


def read_telemetry(csv_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """data.csv -> (numeric float64 (N, len(NUMERIC_COLUMNS)) with NaN for empty/bad cells, collision (N,))."""
    with open(csv_path, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise SkipFolder(f"{CSV_NAME} is empty") from None
        columns = {name.strip(): i for i, name in enumerate(header)}
        missing = [c for c in (*NUMERIC_COLUMNS, COLLISION_COLUMN) if c not in columns]
        if missing:
            raise SkipFolder(f"{CSV_NAME} lacks column(s) {', '.join(missing)}")
        index = [columns[c] for c in NUMERIC_COLUMNS]
        col_idx = columns[COLLISION_COLUMN]
        numeric, collision = [], []
        for row in reader:
            if not row:
                continue
            values = []
            for i in index:
                try:
                    values.append(float(row[i]) if i < len(row) and row[i].strip() else np.nan)
                except ValueError:
                    values.append(np.nan)
            flag = row[col_idx].strip().lower() if col_idx < len(row) else ""
            if flag in _TRUE:
                collision.append(True)
            elif flag in _FALSE:
                collision.append(False)
            else:  # unknown collision flag: the row is unusable, like a NaN
                collision.append(False)
                values[0] = np.nan
            numeric.append(values)
    return np.asarray(numeric, dtype=np.float64).reshape(-1, len(NUMERIC_COLUMNS)), np.asarray(collision, bool)


def image_timestamp(path: Path) -> float:
    try:
        return float(path.stem)
    except ValueError:
        raise SkipFolder(f"image name {path.name!r} is not <timestamp>.png") from None


def read_depth_png(path: Path) -> np.ndarray:
    """Normalised depth float32 (60, 90) in [0, 1] from one original PNG (resized if needed)."""
    with Image.open(path) as img:
        if img.mode in ("I;16", "I;16B", "I;16L", "I"):
            depth = np.asarray(img, dtype=np.float32) / 65535.0
        else:
            depth = np.asarray(img.convert("L"), dtype=np.float32) / 255.0
    if depth.shape != IMAGE_SHAPE:
        resized = F.interpolate(
            torch.from_numpy(depth)[None, None], size=IMAGE_SHAPE, mode="bilinear", align_corners=False
        )
        depth = resized[0, 0].numpy()
    return depth


def load_folder(folder: Path, summary: ImportSummary) -> dict[str, np.ndarray]:
    """Read one trajectory folder into schema-ready arrays; raises SkipFolder with the reason."""
    images = sorted(folder.glob("*.png"), key=image_timestamp)
    if not images:
        raise SkipFolder("no images")
    csv_path = folder / CSV_NAME
    if not csv_path.is_file():
        raise SkipFolder(f"no {CSV_NAME}")
    numeric, collision = read_telemetry(csv_path)
    if len(numeric) == 0:
        raise SkipFolder(f"{CSV_NAME} has no rows")
    extra = 0
    if len(images) == len(numeric) + 1 and image_timestamp(images[-1]) > numeric[-1, 0]:
        images, extra = images[:-1], 1  # the camera's last frame has no telemetry row
    if len(images) != len(numeric):
        raise SkipFolder(f"{len(images)} images but {len(numeric)} telemetry rows")
    keep = np.isfinite(numeric).all(axis=1)
    if not keep.any():
        raise SkipFolder("every telemetry row holds NaN")
    summary.extra_images_dropped += extra
    summary.nan_rows_dropped += int((~keep).sum())
    numeric, collision = numeric[keep], collision[keep]
    depth = np.stack([read_depth_png(images[i]) for i in np.flatnonzero(keep)])
    return {
        "depth": encode_depth(depth),
        "desired_speed": numeric[:, 1],
        "quat": numeric[:, 2:6],
        "position": numeric[:, 6:9],
        "velocity": numeric[:, 9:12],
        "velocity_cmd": numeric[:, 12:15],
        "time": numeric[:, 0] - numeric[0, 0],
        "collision": collision,
    }


def trajectory_folders(source: Path) -> list[Path]:
    if not source.is_dir():
        raise VitflyError(f"{source}: not a directory; expected the original dataset (one folder per trajectory)")
    folders = sorted(p for p in source.iterdir() if p.is_dir())
    if not folders:
        raise VitflyError(f"{source}: holds no trajectory folders (expected <trajectory>/<timestamp>.png + data.csv)")
    return folders


def import_legacy(
    source: str | os.PathLike,
    out: str | os.PathLike,
    depth_max_m: float = DEFAULT_DEPTH_MAX_M,
    depth_compression: str = "none",
    warn: Callable[[str], None] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Import every trajectory folder of ``source`` into ``out`` (resumes a partial ``out``).

    Trajectory m's seed is its folder's position in name order, so a rerun skips folders already
    imported. ``warn(message)`` is called for each skipped folder; ``progress(done, total)`` after
    each folder. ``depth_compression``: "none" or "gzip" (``TrajectoryWriter``). Raises VitflyError
    if nothing at all could be imported (no file is left behind).
    """
    source, out = Path(source), Path(out)
    folders = trajectory_folders(source)
    names = [f.name for f in folders]
    summary = ImportSummary()
    created = not out.exists()
    config = {"source": "legacy", "source_dir": str(source.resolve()), "folders": names}
    try:
        camera = original_camera(depth_max_m)
        with TrajectoryWriter(out, config, depth_max_m, depth_compression, camera=camera) as writer:
            if writer.config.get("folders", names) != names:
                raise VitflyError(
                    f"{out}: holds an import of another folder list (config 'folders'); choose another --out"
                )
            done = set(writer.seeds())
            summary.already_present = len(done)
            for seed, folder in enumerate(folders):
                if seed not in done:
                    try:
                        arrays = load_folder(folder, summary)
                    except SkipFolder as reason:
                        summary.skipped[folder.name] = str(reason)
                        if warn is not None:
                            warn(f"skipping {folder}: {reason}")
                    else:
                        collision = arrays["collision"]
                        n_collisions = int(collision[0]) + int(np.count_nonzero(collision[1:] & ~collision[:-1]))
                        writer.append(
                            TrajectoryRecord(
                                **arrays,
                                env=LEGACY_ENV,
                                seed=seed,
                                n_collisions=n_collisions,
                                success=n_collisions == 0,  # the original goal is unknown: collision-free
                            )
                        )
                        summary.imported += 1
                        summary.rows += len(collision)
                if progress is not None:
                    progress(seed + 1, len(folders))
            total = writer.num_trajectories
    except BaseException:
        if created and summary.imported == 0:
            out.unlink(missing_ok=True)  # nothing committed: leave no empty file behind
        raise
    if total == 0:
        out.unlink(missing_ok=True)
        raise VitflyError(f"{source}: no folder could be imported ({len(summary.skipped)} skipped); see the warnings")
    return summary
