"""LightningDataModule for behaviour cloning with truncated BPTT over vitfly HDF5 datasets.

Batches follow DESIGN.md's batch contract: B whole trajectories (or ``max_length`` windows of
them), padded to the longest, with a validity mask and ``traj_index``. The train/validation split
is by trajectory, seeded, and written to ``split.json`` in the run directory.
"""

from __future__ import annotations

import functools
import json
import math
import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler

from vitfly.atomic import write_text
from vitfly.datamodules.dataset import TrajectoryDataset, collate_trajectories, depth_to_unit_float
from vitfly.datamodules.resident import (
    ResidentTrajectories,
    WindowIndexDataset,
    collate_windows,
    fits_on,
    resident_bytes,
)
from vitfly.datamodules.schema import open_trajectories
from vitfly.errors import VitflyError

SPLIT_FILE = "split.json"


def split_trajectories(num_trajectories: int, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """Seeded split of trajectory indices into (train, val); val gets round(fraction * M), at least 1 if M > 1."""
    if not 0.0 <= val_fraction < 1.0:
        raise VitflyError(f"val_fraction: expected a number in [0, 1), got {val_fraction}")
    order = np.random.default_rng(seed).permutation(num_trajectories)
    n_val = int(round(val_fraction * num_trajectories))
    if val_fraction > 0 and num_trajectories > 1:
        n_val = min(max(n_val, 1), num_trajectories - 1)
    return sorted(order[n_val:].tolist()), sorted(order[:n_val].tolist())


class LengthBucketBatchSampler(Sampler[list[int]]):
    """Batches of items with similar lengths (less padding), shuffled, reproducible per (seed, epoch).

    Items are shuffled, cut into pools of ``batch_size * pool_batches``, sorted by length within a
    pool (unless ``sort_by_length`` is False), cut into batches, and the batches shuffled.
    ``prefetch(items)``, if given, is called with the next batch whenever one is handed out, so its
    data can be read ahead while this one is used.
    """

    def __init__(
        self,
        lengths: Sequence[int],
        batch_size: int,
        shuffle: bool,
        seed: int,
        pool_batches: int = 50,
        prefetch: Callable[[list[int]], None] | None = None,
        sort_by_length: bool = True,
    ):
        self.lengths = np.asarray(lengths)
        self.batch_size = batch_size
        self.shuffle = shuffle
        self.seed = seed
        self.pool = batch_size * pool_batches
        self.epoch = 0
        self.prefetch = prefetch
        self.sort_by_length = sort_by_length

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return math.ceil(len(self.lengths) / self.batch_size)

    def _batches(self) -> list[list[int]]:
        n = len(self.lengths)
        if not self.shuffle:
            return [list(range(i, min(i + self.batch_size, n))) for i in range(0, n, self.batch_size)]
        rng = np.random.default_rng((self.seed, self.epoch))
        self.epoch += 1  # also advances when nobody calls set_epoch
        order = rng.permutation(n)
        batches = []
        for p in range(0, n, self.pool):
            pool = order[p : p + self.pool]
            if self.sort_by_length:
                pool = pool[np.argsort(self.lengths[pool], kind="stable")]
            batches.extend(pool[i : i + self.batch_size].tolist() for i in range(0, len(pool), self.batch_size))
        return [batches[i] for i in rng.permutation(len(batches))]

    def __iter__(self) -> Iterator[list[int]]:
        batches = self._batches()
        for k, batch in enumerate(batches):
            if self.prefetch is not None:
                if k == 0:
                    self.prefetch(batch)
                if k + 1 < len(batches):
                    self.prefetch(batches[k + 1])
            yield batch


class TrajectoryDataModule(L.LightningDataModule):
    """Train/validation (and test/predict) loaders over a vitfly HDF5 dataset.

    Args:
        data_path: HDF5 dataset (schema v1) to train and validate on.
        batch_size: trajectories (or windows) per batch.
        val_fraction: share of trajectories held out for validation (split by trajectory).
        split_seed: seed of the split (and of the batch order).
        split_file: reuse the split recorded in an earlier run's split.json instead of drawing one.
        max_length: cut trajectories longer than this many steps into windows (None: whole).
        num_workers: DataLoader worker processes (each opens the file itself).
        cache_mb: per-process in-memory LRU cache of trajectories, MiB (0: always read from disk).
        readahead: while a batch is read, ask the OS to start reading the next one from disk.
        bucket_by_length: batch trajectories of similar lengths together (less padding).
        use_state: passed through from the policy (recorded with the split; the network zeros the
            state itself when it is False).
        test_path / predict_path: other datasets for ``vitfly test`` / ``vitfly predict``
            (default: the validation trajectories).
        resident: keep the whole dataset (uint8 depth) on the training device and gather the train and
            validation batches there; the loader then hands over only trajectory/window indices
            (``vitfly.datamodules.resident``). ``auto``: on a CUDA device when the dataset takes at
            most half its free memory; ``true``: on any device (on the CPU: no HDF5 reads, no loader
            workers after the first load); ``false``: stream from the file.
    """

    def __init__(
        self,
        data_path: str,
        batch_size: int = 4,
        val_fraction: float = 0.1,
        split_seed: int = 0,
        split_file: str | None = None,
        max_length: int | None = None,
        num_workers: int = 0,
        cache_mb: float = 256.0,
        readahead: bool = True,
        bucket_by_length: bool = True,
        use_state: bool = True,
        test_path: str | None = None,
        predict_path: str | None = None,
        resident: bool | str = "auto",
    ):
        super().__init__()
        if resident not in (True, False, "auto"):
            raise VitflyError(f"resident: expected true, false or auto, got {resident!r}")
        if batch_size < 1:
            raise VitflyError(f"batch_size: expected a positive number of trajectories, got {batch_size}")
        self.save_hyperparameters()
        self.data_path = data_path
        self.batch_size = batch_size
        self.val_fraction = val_fraction
        self.split_seed = split_seed
        self.split_file = split_file
        self.max_length = max_length
        self.num_workers = num_workers
        self.cache_mb = cache_mb
        self.readahead = readahead
        self.bucket_by_length = bucket_by_length
        self.use_state = use_state
        self.test_path = test_path
        self.predict_path = predict_path
        self.resident = resident
        self._resident: ResidentTrajectories | None = None
        self.train_indices: list[int] = []
        self.val_indices: list[int] = []
        self._datasets: dict[str, TrajectoryDataset] = {}

    # -- split ---------------------------------------------------------------------------------

    def _load_split(self, num_trajectories: int) -> tuple[list[int], list[int]]:
        path = Path(self.split_file)
        try:
            split = json.loads(path.read_text())
            train, val = [int(i) for i in split["train"]], [int(i) for i in split["val"]]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise VitflyError(f"{path}: not a readable split file with 'train' and 'val' index lists ({err})") from None
        if split.get("num_trajectories") != num_trajectories:
            raise VitflyError(
                f"{path}: field 'num_trajectories' is {split.get('num_trajectories')}, "
                f"but {self.data_path} holds {num_trajectories} trajectories"
            )
        return train, val

    def split_record(self) -> dict:
        with open_trajectories(self.data_path, check_values=False) as tf:
            seeds = [int(s) for s in tf.table["seed"]]
        return {
            "data_path": os.path.abspath(self.data_path),
            "num_trajectories": len(seeds),
            "val_fraction": self.val_fraction,
            "split_seed": self.split_seed,
            "use_state": self.use_state,
            "train": self.train_indices,
            "val": self.val_indices,
            "train_seeds": [seeds[i] for i in self.train_indices],
            "val_seeds": [seeds[i] for i in self.val_indices],
        }

    def save_split(self, directory: str | os.PathLike) -> Path:
        """Write split.json into ``directory`` atomically; returns its path."""
        out = Path(directory) / SPLIT_FILE
        write_text(out, json.dumps(self.split_record(), indent=1))
        return out

    # -- Lightning hooks -----------------------------------------------------------------------

    def setup(self, stage: str | None = None) -> None:
        if "train" not in self._datasets:
            with open_trajectories(self.data_path) as tf:  # the one full validation of the file
                num_trajectories = len(tf)
            if self.split_file:
                self.train_indices, self.val_indices = self._load_split(num_trajectories)
            else:
                self.train_indices, self.val_indices = split_trajectories(
                    num_trajectories, self.val_fraction, self.split_seed
                )
            self._datasets["train"] = self._subset(self.train_indices)
            self._datasets["val"] = self._subset(self.val_indices) if self.val_indices else None
            trainer = self.trainer
            if trainer is not None and trainer.is_global_zero:
                self.save_split(trainer.log_dir or trainer.default_root_dir)
        if stage == "test" and self.test_path and "test" not in self._datasets:
            self._datasets["test"] = TrajectoryDataset(self.test_path, max_length=self.max_length)
        if stage == "predict" and self.predict_path and "predict" not in self._datasets:
            self._datasets["predict"] = TrajectoryDataset(self.predict_path, max_length=self.max_length)

    def _subset(self, indices: list[int]) -> TrajectoryDataset:
        return TrajectoryDataset(
            self.data_path, indices, max_length=self.max_length, cache_mb=self.cache_mb, check_values=False
        )

    def _loader(self, dataset: TrajectoryDataset, shuffle: bool) -> DataLoader:
        sampler = LengthBucketBatchSampler(
            dataset.window_lengths(),
            self.batch_size,
            shuffle,
            self.split_seed,
            prefetch=dataset.prefetch if self.readahead else None,
            sort_by_length=self.bucket_by_length,
        )
        return DataLoader(
            dataset,
            # depth stays uint8 through the loader (4x less to copy, to pass between processes and to send
            # to a GPU); on_after_batch_transfer makes it the float32 of the batch contract on the device
            collate_fn=functools.partial(collate_trajectories, depth_dtype=torch.uint8),
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            batch_sampler=sampler,
        )

    def on_after_batch_transfer(self, batch: dict, dataloader_idx: int) -> dict:
        if "depth" not in batch and "length" in batch:  # a resident batch: indices only, gathered here
            batch = self._resident_store(batch["length"].device).gather(
                batch["traj_index"], batch["start"], batch["length"]
            )
        return depth_to_unit_float(batch)

    # -- resident dataset (train/validation loaders only; test/predict may read other files) ----------

    def _training_device(self) -> torch.device:
        trainer = self.trainer
        return trainer.strategy.root_device if trainer is not None else torch.device("cpu")

    def use_resident(self, device: torch.device | None = None) -> bool:
        """Whether train/validation batches are gathered from a device-resident copy of the dataset."""
        if self.resident != "auto":
            return bool(self.resident)
        device = self._training_device() if device is None else device
        if device.type != "cuda":
            return False
        with open_trajectories(self.data_path, check_values=False) as tf:
            return fits_on(device, resident_bytes(tf.num_rows))

    def _resident_store(self, device: torch.device) -> ResidentTrajectories:
        if self._resident is None or self._resident.device != device:
            self._resident = ResidentTrajectories(self.data_path, device)
        return self._resident

    def _train_val_loader(self, dataset: TrajectoryDataset, shuffle: bool) -> DataLoader:
        loader = self._loader(dataset, shuffle)
        if not self.use_resident():
            return loader
        # the same batches (same sampler) as indices only; nothing to read ahead from the file
        sampler = loader.batch_sampler
        if getattr(sampler, "prefetch", None) is not None:
            sampler.prefetch = None
        return DataLoader(WindowIndexDataset(dataset.windows), collate_fn=collate_windows, batch_sampler=sampler)

    def train_dataloader(self) -> DataLoader:
        return self._train_val_loader(self._datasets["train"], shuffle=True)

    def val_dataloader(self) -> DataLoader | list:
        val = self._datasets.get("val")
        return [] if val is None else self._train_val_loader(val, shuffle=False)

    def test_dataloader(self) -> DataLoader:
        dataset = self._datasets.get("test") or self._datasets.get("val")
        if dataset is None:
            raise VitflyError("data.test_path: no test dataset given and no validation trajectories to test on")
        return self._loader(dataset, shuffle=False)

    def predict_dataloader(self) -> DataLoader:
        dataset = self._datasets.get("predict") or self._datasets.get("val")
        if dataset is None:
            raise VitflyError("data.predict_path: no dataset given and no validation trajectories to predict on")
        return self._loader(dataset, shuffle=False)
