"""Streaming per-trajectory torch Dataset over a vitfly HDF5 file, and the padding collate.

One item is one trajectory, or one window of at most ``max_length`` steps of it. Items are read
from disk on demand; an optional LRU cache keeps recently read trajectories in memory (per process:
each DataLoader worker has its own cache and its own file handle, opened lazily after the fork).
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset, get_worker_info

from vitfly.datamodules.schema import TrajectoryFile, open_trajectories
from vitfly.errors import VitflyError

# what the policy needs from each step (the rest of the schema stays on disk)
TRAINING_FIELDS = ("depth", "desired_speed", "quat", "velocity_cmd")
# optional batch key: each row's valid steps, (B,) int64 kept on the host while the other tensors go to the
# device (resident batches), so that the batch's shape and its TBPTT chunks need not wait for the device
HOST_LENGTHS = "lengths_host"
# optional batch key: a training batch's mirror coins, (B,) bool drawn on the host before the trip to the device
HOST_MIRROR = "mirror_host"
HOST_KEYS = (HOST_LENGTHS, HOST_MIRROR)  # what ``transfer_batch_to_device`` leaves on the host


class TrajectoryCache:
    """Least-recently-used cache of per-trajectory arrays, bounded in bytes."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self.bytes = 0
        self._items: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()

    def get(self, key: int) -> dict[str, np.ndarray] | None:
        item = self._items.get(key)
        if item is not None:
            self._items.move_to_end(key)
        return item

    def put(self, key: int, item: dict[str, np.ndarray]) -> None:
        size = sum(a.nbytes for a in item.values())
        if size > self.max_bytes:
            return
        self._items[key] = item
        self.bytes += size
        while self.bytes > self.max_bytes:
            _, old = self._items.popitem(last=False)
            self.bytes -= sum(a.nbytes for a in old.values())

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: int) -> bool:
        return key in self._items


def make_windows(lengths: Sequence[int], indices: Sequence[int], max_length: int | None) -> list[tuple[int, int, int]]:
    """(trajectory, start, stop) items: whole trajectories, or consecutive windows of <= max_length steps."""
    if max_length is not None and max_length < 1:
        raise VitflyError(f"max_length: expected a positive number of steps or None, got {max_length}")
    windows = []
    for m in indices:
        n = int(lengths[m])
        step = n if max_length is None else max_length
        windows.extend((int(m), lo, min(lo + step, n)) for lo in range(0, n, step))
    return windows


class TrajectoryDataset(Dataset):
    """Trajectories (or windows of them) of a vitfly dataset as dicts of tensors.

    Each item: ``depth`` float32 (T, 1, 60, 90) normalised depth in [0, 1]; ``desired_speed``
    (T, 1) m/s; ``quat`` (T, 4) (w, x, y, z); ``velocity_cmd`` (T, 3) m/s world frame;
    ``traj_index`` and ``start`` (window start step) as ints.

    path: the HDF5 file (validated once here). indices: trajectories to use (default all).
    max_length: cut trajectories into windows of at most this many steps. cache_mb: LRU cache size
    in MiB per process (0 disables it). check_values: scan the telemetry for NaN on opening (skip it
    only for a file validated already).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        indices: Sequence[int] | None = None,
        max_length: int | None = None,
        cache_mb: float = 0.0,
        check_values: bool = True,
    ):
        self.path = os.fspath(path)
        # validates schema, shapes and (unless the caller already did) NaN telemetry
        with open_trajectories(self.path, check_values=check_values) as tf:
            self.lengths = tf.lengths.copy()
            self.num_trajectories = len(tf)
        self.indices = list(range(self.num_trajectories)) if indices is None else [int(i) for i in indices]
        bad = [i for i in self.indices if not 0 <= i < self.num_trajectories]
        if bad:
            raise VitflyError(f"{self.path}: trajectory indices {bad[:5]} out of range [0, {self.num_trajectories})")
        self.max_length = max_length
        self.windows = make_windows(self.lengths, self.indices, max_length)
        self.cache_bytes = int(cache_mb * 2**20)
        self._file: TrajectoryFile | None = None
        self._pid: int | None = None
        self._cache = TrajectoryCache(self.cache_bytes)

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_file"], state["_pid"] = None, None  # h5py handles do not survive pickling / forking
        state["_cache"] = TrajectoryCache(self.cache_bytes)
        return state

    def _handle(self) -> TrajectoryFile:
        if self._file is None or self._pid != os.getpid():
            self._file = open_trajectories(self.path, check_values=False)
            self._pid = os.getpid()
            self._cache = TrajectoryCache(self.cache_bytes)
        return self._file

    def __len__(self) -> int:
        return len(self.windows)

    def window_lengths(self) -> np.ndarray:
        return np.array([hi - lo for _, lo, hi in self.windows])

    def read_arrays(self, m: int) -> dict[str, np.ndarray]:
        """The training fields of trajectory m in on-disk dtypes (depth uint8), through the cache."""
        item = self._cache.get(m)
        if item is None:
            item = self._handle().read(m, TRAINING_FIELDS)
            if self.cache_bytes:
                self._cache.put(m, item)
        return item

    def prefetch(self, items: Sequence[int]) -> None:
        """Start reading the trajectories of ``items`` (dataset indices) in the background (OS read-ahead)."""
        for m in dict.fromkeys(self.windows[i][0] for i in items):  # windows of one trajectory: one hint
            if m not in self._cache:
                self._handle().prefetch(m, TRAINING_FIELDS)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor | int]:
        m, lo, hi = self.windows[i]
        arrays = self.read_arrays(m)
        return {
            "depth": torch.from_numpy(np.ascontiguousarray(arrays["depth"][lo:hi])),  # uint8; collate scales it
            "desired_speed": torch.from_numpy(arrays["desired_speed"][lo:hi]).unsqueeze(-1),
            "quat": torch.from_numpy(arrays["quat"][lo:hi]),
            "velocity_cmd": torch.from_numpy(arrays["velocity_cmd"][lo:hi]),
            "traj_index": m,
            "start": lo,
        }

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def depth_to_unit_float(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Turn a uint8 ``depth`` (round(255 x normalised depth)) into float32 in [0, 1], in place of the key."""
    if batch["depth"].dtype == torch.uint8:
        batch["depth"] = batch["depth"].to(torch.float32).mul_(1.0 / 255.0)
    return batch


def check_time_bucket(steps: int | None, source: str = "data.time_bucket_steps") -> int | None:
    """``steps`` if it is a positive whole number of time steps or None; else one error line naming ``source``."""
    if steps is None or (isinstance(steps, int) and not isinstance(steps, bool) and steps >= 1):
        return steps
    raise VitflyError(f"{source}: expected a positive number of time steps (or null: no padding), got {steps!r}")


def pad_to_bucket(batch: dict[str, torch.Tensor], bucket_steps: int, batch_size: int | None = None) -> dict:
    """The batch padded at the end of its time axis to the next multiple of ``bucket_steps``, and along its
    batch axis to ``batch_size`` rows (a smaller last batch), so that an epoch has at most as many batch
    shapes as there are buckets (the longest trajectory / ``bucket_steps``, rounded up).

    Padding is zeros with ``mask`` false, as ``collate_trajectories``'s; the added rows have ``traj_index``
    -1 (no trajectory) and ``start`` 0. A new dict; a batch already of that shape is returned as is.
    """
    b, t = batch["mask"].shape
    t_to = math.ceil(t / bucket_steps) * bucket_steps
    b_to = max(b, batch_size or b)
    if (b_to, t_to) == (b, t):
        return batch
    out = {}
    for key, value in batch.items():
        if value.dim() >= 2 and tuple(value.shape[:2]) == (b, t):  # per step: depth, telemetry, mask
            padded = value.new_zeros((b_to, t_to, *value.shape[2:]))
            padded[:b, :t] = value
        elif value.dim() == 1 and value.shape[0] == b:  # per row: traj_index, start, lengths_host (0: no step)
            padded = value.new_full((b_to,), -1 if key == "traj_index" else 0)
            padded[:b] = value
        else:
            padded = value
        out[key] = padded
    return out


def _batch_buffer(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """An uninitialised tensor; in a DataLoader worker, in shared memory, as torch's default_collate does, so
    the batch is not copied once more on its way to the main process."""
    if get_worker_info() is None:
        return torch.empty(shape, dtype=dtype)
    storage = torch.UntypedStorage._new_shared(math.prod(shape) * dtype.itemsize)
    return torch.empty(0, dtype=dtype).set_(storage).view(shape)


def collate_trajectories(items: list[dict], depth_dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """Pad B items to the longest and stack them (the batch contract of DESIGN.md).

    depth float32 (B, T, 1, 60, 90) in [0, 1]; desired_speed (B, T, 1); quat (B, T, 4);
    velocity_cmd (B, T, 3); mask bool (B, T), true on real steps; traj_index (B,); start (B,).
    Padding is zeros (and never reaches the loss: the policy masks it out).
    ``depth_dtype=torch.uint8`` keeps depth as stored (0..255) for ``depth_to_unit_float`` to convert
    later, on the training device.
    """
    b = len(items)
    t = max(item["depth"].shape[0] for item in items)
    h, w = items[0]["depth"].shape[1:]
    # depth is the bulk of a batch: convert uint8 straight into the output, zero only the padding
    depth = _batch_buffer((b, t, 1, h, w), depth_dtype)
    speed = torch.zeros((b, t, 1), dtype=torch.float32)
    quat = torch.zeros((b, t, 4), dtype=torch.float32)
    cmd = torch.zeros((b, t, 3), dtype=torch.float32)
    mask = torch.zeros((b, t), dtype=torch.bool)
    for i, item in enumerate(items):
        n = item["depth"].shape[0]
        depth[i, :n, 0].copy_(item["depth"])
        depth[i, n:].zero_()
        speed[i, :n] = item["desired_speed"]
        quat[i, :n] = item["quat"]
        cmd[i, :n] = item["velocity_cmd"]
        mask[i, :n] = True
    if depth_dtype != torch.uint8:
        depth.mul_(1.0 / 255.0)
    return {
        "depth": depth,
        "desired_speed": speed,
        "quat": quat,
        "velocity_cmd": cmd,
        "mask": mask,
        "traj_index": torch.tensor([item["traj_index"] for item in items], dtype=torch.long),
        "start": torch.tensor([item["start"] for item in items], dtype=torch.long),
    }
