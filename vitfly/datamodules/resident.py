"""A whole dataset held on the training device (uint8 depth), and batches gathered there.

On a GPU the data loader then moves only three small index tensors per batch (trajectory, window start,
window length); ``ResidentTrajectories.gather`` builds the padded batch of DESIGN.md's batch contract on
the device with one indexing operation per field. The paper-scale set (about 112k frames) is about
0.6 GB of uint8 depth, which fits beside the model on any current GPU.

Written device-agnostic; on the CPU it is exercised by the tests, on CUDA it trained the shipped weights
(scripts/gpu_study.py on one H100).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from vitfly.datamodules.dataset import HOST_LENGTHS, TRAINING_FIELDS
from vitfly.datamodules.schema import open_trajectories

# bytes per step: uint8 60 x 90 depth + float32 speed (1), quat (4), velocity_cmd (3)
TELEMETRY_BYTES = 4 * (1 + 4 + 3)
# share of the device's free memory the dataset may take when ``resident: auto`` decides
AUTO_MAX_FREE_FRACTION = 0.5


def resident_bytes(num_rows: int, image_shape: Sequence[int] = (60, 90)) -> int:
    """Device memory ``ResidentTrajectories`` needs for ``num_rows`` steps (one padding row included)."""
    return (num_rows + 1) * (int(np.prod(image_shape)) + TELEMETRY_BYTES)


def fits_on(device: torch.device, nbytes: int) -> bool:
    """Whether ``nbytes`` fit in the free memory of CUDA ``device`` (at most half of it; False off CUDA)."""
    if device.type != "cuda" or not torch.cuda.is_available():
        return False
    free, _total = torch.cuda.mem_get_info(device)
    return nbytes <= AUTO_MAX_FREE_FRACTION * free


class ResidentTrajectories:
    """Every row of a vitfly dataset's training fields in flat device tensors, plus one all-zero padding row.

    ``depth`` (N + 1, 60, 90) uint8; ``desired_speed`` (N + 1, 1), ``quat`` (N + 1, 4), ``velocity_cmd``
    (N + 1, 3) float32; ``offsets`` (M,) int64 first row of each trajectory. Row N is the padding row.
    """

    def __init__(self, path: str | os.PathLike, device: torch.device | str = "cpu") -> None:
        self.path = os.fspath(path)
        device = torch.device(device)
        with open_trajectories(self.path, check_values=False) as tf:
            offsets = np.asarray(tf.offsets, dtype=np.int64)
            rows = int(offsets[-1])
            arrays = {}
            for name in TRAINING_FIELDS:
                first = tf.read(0, (name,))[name] if len(tf) else np.zeros((0,), np.float32)
                # one extra zero row at the end: padded steps index it
                arrays[name] = np.zeros((rows + 1, *first.shape[1:]), dtype=first.dtype)
            for m in range(len(tf)):
                lo, hi = int(offsets[m]), int(offsets[m + 1])
                for name, values in tf.read(m, TRAINING_FIELDS).items():
                    arrays[name][lo:hi] = values
        self.pad_row = rows
        self.offsets = torch.from_numpy(offsets[:-1].copy()).to(device)
        self.depth = torch.from_numpy(arrays["depth"]).to(device)
        self.desired_speed = torch.from_numpy(arrays["desired_speed"]).unsqueeze(-1).to(device)
        self.quat = torch.from_numpy(arrays["quat"]).to(device)
        self.velocity_cmd = torch.from_numpy(arrays["velocity_cmd"]).to(device)

    @property
    def device(self) -> torch.device:
        return self.depth.device

    @property
    def nbytes(self) -> int:
        tensors = (self.depth, self.desired_speed, self.quat, self.velocity_cmd, self.offsets)
        return sum(t.numel() * t.element_size() for t in tensors)

    def gather(self, traj_index: torch.Tensor, start: torch.Tensor, length: torch.Tensor,
               lengths_host: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The padded batch of windows ``[start, start + length)`` of trajectories ``traj_index`` (each (B,)).

        Same tensors as ``collate_trajectories(..., depth_dtype=torch.uint8)`` of the same windows: depth
        uint8 (B, T, 1, 60, 90), desired_speed (B, T, 1), quat (B, T, 4), velocity_cmd (B, T, 3), mask
        (B, T), traj_index and start (B,), zeros on padded steps; T is the longest window. ``lengths_host``:
        ``length`` as the host had it before the batch went to the device; the batch's shape comes from it
        without waiting for the device, and the batch carries it on (``HOST_LENGTHS``).
        """
        device = self.device
        traj_index, start, length = (t.to(device=device, dtype=torch.long) for t in (traj_index, start, length))
        known = length if lengths_host is None else lengths_host  # on the device, the host waits for its queue
        t_max = int(known.max()) if known.numel() else 0
        steps = torch.arange(t_max, device=device)
        mask = steps.unsqueeze(0) < length.unsqueeze(1)
        rows = (self.offsets[traj_index] + start).unsqueeze(1) + steps.unsqueeze(0)
        rows = torch.where(mask, rows, torch.full_like(rows, self.pad_row))
        return {
            "depth": self.depth[rows].unsqueeze(2),
            "desired_speed": self.desired_speed[rows],
            "quat": self.quat[rows],
            "velocity_cmd": self.velocity_cmd[rows],
            "mask": mask,
            "traj_index": traj_index,
            "start": start,
            **({HOST_LENGTHS: lengths_host} if lengths_host is not None else {}),
        }


class WindowIndexDataset(Dataset):
    """The items of a TrajectoryDataset as (trajectory, start, stop) only: what a resident batch needs."""

    def __init__(self, windows: Sequence[tuple[int, int, int]]) -> None:
        self.windows = list(windows)

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, i: int) -> tuple[int, int, int]:
        return self.windows[i]


def collate_windows(items: list[tuple[int, int, int]]) -> dict[str, torch.Tensor]:
    """(trajectory, start, stop) items -> ``traj_index``, ``start``, ``length`` (B,) int64 for ``gather``."""
    table = torch.tensor(items, dtype=torch.long).reshape(-1, 3)
    return {"traj_index": table[:, 0], "start": table[:, 1], "length": table[:, 2] - table[:, 1]}
