"""What a dataset is, in a few numbers to record beside what was trained on it (pretrained weights, runs)."""

from __future__ import annotations

import hashlib
import os

from vitfly.datamodules.schema import open_trajectories

HASH_HEX_DIGITS = 16


def dataset_fingerprint(path: str | os.PathLike) -> dict:
    """``dataset_hash`` (SHA-256 of the file's bytes, 16 hex digits), ``dataset_trajectories``, ``dataset_frames``.

    The file is validated first (one line if it is not a vitfly dataset).
    """
    with open_trajectories(path, check_values=False) as tf:
        trajectories, frames = len(tf), tf.num_rows
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return {"dataset_hash": h.hexdigest()[:HASH_HEX_DIGITS], "dataset_trajectories": int(trajectories),
            "dataset_frames": int(frames)}
