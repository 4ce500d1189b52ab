"""LightningDataModule for behaviour cloning with truncated BPTT over vitfly HDF5 datasets.

Batches follow DESIGN.md's batch contract: B whole trajectories (or ``max_length`` windows of
them), padded to the longest, with a validity mask and ``traj_index``. The train/validation split
is by trajectory, seeded, drawn once per run and then frozen (``vitfly.datamodules.split``): it is
written to ``split.json`` in the run directory and stored in the run's checkpoints, and every later
setup of the run reuses it.
"""

from __future__ import annotations

import functools
import json
import math
import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_info
from torch.utils.data import DataLoader, Sampler

from vitfly.atomic import write_text
from vitfly.datamodules.augment import batch_coins, check_mirror_prob, random_mirror
from vitfly.datamodules.dataset import (
    HOST_KEYS,
    HOST_LENGTHS,
    HOST_MIRROR,
    TrajectoryDataset,
    check_time_bucket,
    collate_trajectories,
    depth_to_unit_float,
    pad_to_bucket,
)
from vitfly.datamodules.resident import (
    ResidentTrajectories,
    WindowIndexDataset,
    collate_windows,
    fits_on,
    resident_bytes,
)
from vitfly.datamodules.schema import open_trajectories
from vitfly.datamodules.sensor_augment import SensorRandomisation, check_sensor
from vitfly.datamodules.split import (
    SPLIT_FILE,
    Split,
    TrajectoryIds,
    describe,
    read_split_file,
    reuse_split,
    same_split,
    split_trajectories,
)
from vitfly.errors import VitflyError

__all__ = ["SPLIT_FILE", "LengthBucketBatchSampler", "TrajectoryDataModule", "split_trajectories"]


class LengthBucketBatchSampler(Sampler[list[int]]):
    """Batches of items with similar lengths (less padding), shuffled, reproducible per (seed, epoch),
    sharded over ``num_replicas`` data-parallel ranks.

    Items are shuffled, cut into pools of ``batch_size * num_replicas * pool_batches``, sorted by length
    within a pool (unless ``sort_by_length`` is False), and cut into groups of ``batch_size * num_replicas``;
    the groups are shuffled. Each group is one step: its items are dealt out as ``num_replicas`` consecutive
    slices, and this rank (``rank``) gets its own slice, so the ranks' batches are disjoint and of similar
    lengths. Every rank gets the same number of batches, ``ceil(items / (batch_size * num_replicas))``:
    the last, smaller group is split evenly (batches smaller than ``batch_size``), and if it holds fewer
    items than there are ranks, its items are repeated to give every rank one (padding by repeating, as
    torch's DistributedSampler does: at most ``num_replicas - 1`` items a second time per epoch).
    Every rank must be built with the same lengths, seed and epoch. Without shuffling the groups are
    consecutive items in order. ``prefetch(items)``, if given, is called with this rank's next batch
    whenever one is handed out, so its data can be read ahead while this one is used.

    The epoch (``set_epoch``; Lightning calls it at each epoch start through ``.sampler``) seeds the
    order; a shuffled pass also advances it by one, for loops that never call ``set_epoch``.
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
        num_replicas: int = 1,
        rank: int = 0,
    ):
        if not 0 <= rank < num_replicas:
            raise VitflyError(f"rank: expected 0 <= rank < num_replicas ({num_replicas}), got {rank}")
        self.lengths = np.asarray(lengths)
        self.batch_size = batch_size
        self.shuffle = shuffle
        self.seed = seed
        self.num_replicas = num_replicas
        self.rank = rank
        self.group = batch_size * num_replicas  # items per step over all ranks
        self.pool = self.group * pool_batches
        self.epoch = 0
        self.prefetch = prefetch
        self.sort_by_length = sort_by_length

    @property
    def sampler(self) -> LengthBucketBatchSampler:
        """Itself: Lightning's loops call ``batch_sampler.sampler.set_epoch(epoch)`` at each epoch start
        (never the batch sampler's own), so a resumed run shuffles epoch N as an uninterrupted one does."""
        return self

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return math.ceil(len(self.lengths) / self.group)

    def _deal(self, items: list[int]) -> list[list[int]]:
        """One group's items as ``num_replicas`` consecutive slices, sizes differing by at most one."""
        w = self.num_replicas
        if len(items) < w:  # fewer items than ranks: repeat them so that every rank has a batch
            items = [items[i % len(items)] for i in range(w)]
        bounds = [len(items) * r // w for r in range(w + 1)]
        return [items[bounds[r] : bounds[r + 1]] for r in range(w)]

    def _groups(self) -> list[list[list[int]]]:
        """The epoch's steps, each a list of one batch per rank (the same on every rank)."""
        n = len(self.lengths)
        if not self.shuffle:
            return [self._deal(list(range(i, min(i + self.group, n)))) for i in range(0, n, self.group)]
        rng = np.random.default_rng((self.seed, self.epoch))
        self.epoch += 1  # also advances when nobody calls set_epoch
        order = rng.permutation(n)
        groups = []
        for p in range(0, n, self.pool):
            pool = order[p : p + self.pool]
            if self.sort_by_length:
                pool = pool[np.argsort(self.lengths[pool], kind="stable")]
            groups.extend(self._deal(pool[i : i + self.group].tolist()) for i in range(0, len(pool), self.group))
        return [groups[i] for i in rng.permutation(len(groups))]

    def __iter__(self) -> Iterator[list[int]]:
        batches = [group[self.rank] for group in self._groups()]
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
        batch_size: trajectories (or windows) per training batch (one optimiser step's).
        val_batch_size: trajectories (or windows) per validation batch (None: ``batch_size``). Validation takes
            no optimiser step, so its metrics are those of one-trajectory batches (masked means over the
            valid steps; padding at the end of a row never reaches a causal network's valid outputs) in fewer
            calls: with the paper's one-trajectory steps, validating ViT+LSTM one trajectory at a time took 60 %
            of an epoch on a GPU (docs/training.md#validation-batches-and-where-an-epochs-time-goes).
        cpu_val_batch_size: ``val_batch_size`` for a trainer on a CPU (None: ``val_batch_size``), so that one recipe
            validates in large calls on a GPU and in small ones on a CPU, where a call's activations take the
            host's memory (two UNet+LSTM runs validating 16 trajectories a call ran a 24 GB machine out of it).
            Like ``val_batch_size`` it changes the number of calls, never the metrics.
        val_fraction: share of trajectories held out for validation (split by trajectory) when a split is drawn.
        split_seed: seed of the split (and of the batch order).
        split_file: reuse the split recorded in an earlier run's split.json instead of drawing one. Without it, a
            run reuses its own frozen split: the run directory's split.json, else the one stored in the
            checkpoint it resumes (``--ckpt_path``); it draws one only when it has neither. Trajectories the
            dataset gained since a split was frozen go to training.
        max_length: cut trajectories longer than this many steps into windows (None: whole).
        num_workers: DataLoader worker processes (each opens the file itself).
        cache_mb: per-process in-memory LRU cache of trajectories, MiB (0: always read from disk).
        readahead: while a batch is read, ask the OS to start reading the next one from disk.
        bucket_by_length: batch trajectories of similar lengths together (less padding).
        use_state: passed through from the policy (recorded with the split; the network zeros the
            state itself when it is False).
        test_path / predict_path: other datasets for ``vitfly test`` / ``vitfly predict``
            (default: the validation trajectories).
        mirror_prob: probability that a training trajectory (or window) is mirrored left-right in an
            epoch: depth flipped, the command's y and the attitude mirrored (``vitfly.datamodules.augment``).
            Training batches only; default 0.0 (off, the paper's training).
        sensor_prob: probability that a training trajectory (or window) is seen through ``sensor`` in an epoch
            (a seeded coin per trajectory, window start and epoch; default 0.0: off): its exact frames become the
            sensor model's deployed frames (``vitfly.datamodules.sensor_augment``), after any mirroring.
        sensor: the sensor model for ``sensor_prob``, as ``vitfly evaluate --sensor`` takes it:
            ``{model: d435, FIELD: VALUE, ...}`` (fields of ``vitfly.sensors.stereo.StereoDepthConfig``);
            the camera geometry is the dataset's. Validation batches keep their exact frames.
        resident: keep the whole dataset (uint8 depth) on the training device and gather the train and
            validation batches there; the loader then hands over only trajectory/window indices
            (``vitfly.datamodules.resident``). ``auto``: on a CUDA device when the dataset takes at
            most half its free memory; ``true``: on any device (on the CPU: no HDF5 reads, no loader
            workers after the first load); ``false``: stream from the file.
        time_bucket_steps: pad each training and validation batch's time axis with masked steps up to a
            multiple of this many steps, and a smaller last batch up to ``batch_size`` rows (validation:
            ``val_batch_size``; None: batches are as long as their longest trajectory). With the policy's
            ``static_shapes`` an epoch then has at most (longest trajectory / ``time_bucket_steps``, rounded up)
            batch shapes, each compiled or recorded as a CUDA graph once; padding is masked, so the loss and
            gradients do not change.
            Choose a multiple of ``tbptt_steps`` when chunks are used (every chunk then has one shape).
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
        mirror_prob: float = 0.0,
        sensor_prob: float = 0.0,
        sensor: dict[str, Any] | None = None,
        resident: bool | str = "auto",
        time_bucket_steps: int | None = None,
        val_batch_size: int | None = None,
        cpu_val_batch_size: int | None = None,
    ):
        super().__init__()
        if resident not in (True, False, "auto"):
            raise VitflyError(f"resident: expected true, false or auto, got {resident!r}")
        sizes = {"batch_size": batch_size, "val_batch_size": 1 if val_batch_size is None else val_batch_size,
                 "cpu_val_batch_size": 1 if cpu_val_batch_size is None else cpu_val_batch_size}
        for name, size in sizes.items():
            if size < 1:
                raise VitflyError(f"{name}: expected a positive number of trajectories, got {size}")
        self.time_bucket_steps = check_time_bucket(time_bucket_steps)
        self.save_hyperparameters()
        self.data_path = data_path
        self.batch_size = batch_size
        self.val_batch_size = val_batch_size or batch_size
        self.cpu_val_batch_size = cpu_val_batch_size
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
        self.mirror_prob = check_mirror_prob(mirror_prob, "data.mirror_prob")
        self.sensor_prob = float(sensor_prob)
        self.sensor_config = check_sensor(sensor, self.sensor_prob)
        self._sensor_aug: SensorRandomisation | None = None
        self.resident = resident
        self._resident: ResidentTrajectories | None = None
        self.train_indices: list[int] = []
        self.val_indices: list[int] = []
        # the sensor the dataset was recorded with (plain values; the policy stores it in its checkpoints):
        # {"depth_max_m": m, "camera": dict of the camera's settings or None, "control_hz": Hz or None}
        self.sensor: dict[str, Any] | None = None
        self._split: Split | None = None
        self._split_saved = False
        self._ids: TrajectoryIds | None = None
        self._datasets: dict[str, TrajectoryDataset | None] = {}

    # -- split ---------------------------------------------------------------------------------

    def _run_dir(self) -> Path | None:
        trainer = self.trainer
        if trainer is None:
            return None
        return Path(trainer.log_dir or trainer.default_root_dir)

    def _frozen_record(self) -> tuple[dict, str] | None:
        """(record, where it is) of the split this run must reuse: ``split_file``, else the run dir's split.json."""
        if self.split_file:
            return read_split_file(self.split_file), str(self.split_file)
        run_dir = self._run_dir()
        if run_dir is not None and (run_dir / SPLIT_FILE).is_file():
            return read_split_file(run_dir / SPLIT_FILE), str(run_dir / SPLIT_FILE)
        return None

    def _reuse(self, record: dict, source: str) -> Split:
        split = reuse_split(record, self._ids, self.data_path, source)
        rank_zero_info(describe(split, record, self.val_fraction, self.split_seed))
        return split

    def _apply_split(self, split: Split) -> None:
        self._split = split
        self._split_saved = False
        self.train_indices, self.val_indices = list(split.train), list(split.val)
        self._datasets["train"] = self._subset(self.train_indices)
        self._datasets["val"] = self._subset(self.val_indices) if self.val_indices else None

    def _save_split_once(self) -> None:
        """Write split.json into the run directory when the first loader is asked for: after a checkpoint's split
        was checked (``load_state_dict`` runs between ``setup`` and the loaders), so a refused resume leaves the
        run's recorded split as it was."""
        trainer = self.trainer
        if not self._split_saved and trainer is not None:
            run_dir = self._run_dir()  # trainer.log_dir is a broadcast under DDP: every rank must ask
            if trainer.is_global_zero:
                self.save_split(run_dir)
        self._split_saved = True

    def split_record(self) -> dict:
        """The split as recorded in split.json and in checkpoints (indices, seeds, dataset fingerprint)."""
        if self._split is None or self._ids is None:
            raise VitflyError("TrajectoryDataModule.split_record: call setup() first")
        added = {"added_to_train": list(self._split.added)} if self._split.added else {}
        return self._split.record(
            self._ids, self.data_path, self.val_fraction, self.split_seed, use_state=self.use_state, **added
        )

    def save_split(self, directory: str | os.PathLike) -> Path:
        """Write split.json into ``directory`` atomically; returns its path."""
        out = Path(directory) / SPLIT_FILE
        write_text(out, json.dumps(self.split_record(), indent=1))
        return out

    def state_dict(self) -> dict[str, Any]:
        """Stored in every checkpoint: the split, so a resume elsewhere (or ``validate``) reuses it."""
        return {"split": self.split_record()} if self._split is not None else {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Called after ``setup`` when a run starts from a checkpoint: reuse the split it was trained with."""
        record = state_dict.get("split") if isinstance(state_dict, dict) else None
        if not isinstance(record, dict) or self._split is None:
            return  # a checkpoint from before splits were stored
        trainer = self.trainer
        source = f"checkpoint {trainer.ckpt_path}" if trainer is not None and trainer.ckpt_path else "the checkpoint"
        if self._split.source == "drawn":
            self._apply_split(self._reuse(record, source))
            return
        fitting = trainer is not None and trainer.state.fn == "fit"
        if fitting and not same_split(reuse_split(record, self._ids, self.data_path, source), self._split):
            raise VitflyError(
                f"{self._split.source}: its train/validation split differs from the one {source} was trained "
                "with; resuming would validate on trained-on trajectories (drop data.split_file, or start a new run)"
            )

    # -- Lightning hooks -----------------------------------------------------------------------

    def setup(self, stage: str | None = None) -> None:
        if "train" not in self._datasets:
            with open_trajectories(self.data_path) as tf:  # the one full validation of the file
                self._ids = TrajectoryIds.of(tf)
                self.sensor = dict(tf.sensor)
                recorded_model = ((tf.config or {}).get("collect") or {}).get("sensor")
            if self.sensor_prob > 0.0 and recorded_model:  # modelling a modelled frame twice
                model = recorded_model.get("model") if isinstance(recorded_model, dict) else recorded_model
                raise VitflyError(f"{self.data_path}: field config.collect.sensor is {model!r}: its frames are "
                                  "already modelled; data.sensor_prob expects a dataset of exact renders")
            frozen = self._frozen_record()
            if frozen is not None:
                split = self._reuse(*frozen)
            else:
                split = Split(*split_trajectories(len(self._ids), self.val_fraction, self.split_seed))
            self._apply_split(split)
        if stage == "test" and self.test_path and "test" not in self._datasets:
            self._datasets["test"] = TrajectoryDataset(self.test_path, max_length=self.max_length)
        if stage == "predict" and self.predict_path and "predict" not in self._datasets:
            self._datasets["predict"] = TrajectoryDataset(self.predict_path, max_length=self.max_length)

    def teardown(self, stage: str | None = None) -> None:
        """Close this process's file handles (they reopen on the next read), so that the dataset can be appended
        to once training is over (HDF5 holds a lock while a file is open)."""
        for dataset in self._datasets.values():
            if dataset is not None:
                dataset.close()

    def _subset(self, indices: list[int]) -> TrajectoryDataset:
        return TrajectoryDataset(
            self.data_path, indices, max_length=self.max_length, cache_mb=self.cache_mb, check_values=False
        )

    def _replicas(self) -> dict[str, int]:
        """This process's data-parallel shard from the Trainer's strategy (``num_replicas``, ``rank``)."""
        trainer = self.trainer
        shard = trainer.distributed_sampler_kwargs if trainer is not None else None
        return {"num_replicas": shard["num_replicas"], "rank": shard["rank"]} if shard else {}

    def _loader(self, dataset: TrajectoryDataset, shuffle: bool, batch_size: int | None = None) -> DataLoader:
        # under DDP the batch sampler shards itself (Lightning's DistributedSampler cannot be injected into it:
        # vitfly's Trainers run with use_distributed_sampler=False)
        sampler = LengthBucketBatchSampler(
            dataset.window_lengths(),
            batch_size or self.batch_size,
            shuffle,
            self.split_seed,
            prefetch=dataset.prefetch if self.readahead else None,
            sort_by_length=self.bucket_by_length,
            **self._replicas(),
        )
        return DataLoader(
            dataset,
            # depth stays uint8 through the loader (4x less to copy, to pass between processes and to send
            # to a GPU); on_after_batch_transfer makes it the float32 of the batch contract on the device
            collate_fn=functools.partial(collate_trajectories, depth_dtype=torch.uint8),
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            batch_sampler=sampler,
            generator=_own_generator(shuffle),
        )

    def on_before_batch_transfer(self, batch: dict, dataloader_idx: int) -> dict:
        # what the host will need of the batch, taken while it is here: read back from a device, each would wait
        # for every step queued before it
        if "depth" not in batch and "length" in batch:  # a resident batch: its lengths stay on the host too
            batch[HOST_LENGTHS] = batch["length"]
        trainer = self.trainer
        if self.mirror_prob > 0.0 and trainer is not None and trainer.training:
            batch[HOST_MIRROR] = batch_coins(batch, self.mirror_prob, self.split_seed, trainer.current_epoch)
        return batch

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        """Every tensor to ``device`` but those of ``HOST_KEYS``, which are there to stay on the host."""
        host = {k: batch.pop(k) for k in HOST_KEYS if k in batch} if isinstance(batch, dict) else {}
        batch = super().transfer_batch_to_device(batch, device, dataloader_idx)
        return {**batch, **host} if host else batch

    def on_after_batch_transfer(self, batch: dict, dataloader_idx: int) -> dict:
        if "depth" not in batch and "length" in batch:  # a resident batch: indices only, gathered here
            batch = self._resident_store(batch["length"].device).gather(
                batch["traj_index"], batch["start"], batch["length"], batch.get(HOST_LENGTHS)
            )
        # the one place augmentation happens: training batches only, once the batch holds its depth
        # (streamed or gathered from the resident copy)
        trainer = self.trainer
        coins = batch.pop(HOST_MIRROR, None)
        if self.mirror_prob > 0.0 and trainer is not None and trainer.training:
            batch = random_mirror(batch, self.mirror_prob, self.split_seed, trainer.current_epoch, coins)
        if self.sensor_prob > 0.0 and trainer is not None and trainer.training:
            batch = self.sensor_randomisation()(batch, self.split_seed, trainer.current_epoch)
        fitting = trainer is not None and (trainer.training or trainer.validating or trainer.sanity_checking)
        if self.time_bucket_steps and fitting:  # test/predict rows stay one per trajectory
            rows = self.batch_size if trainer.training else self.val_rows()
            batch = pad_to_bucket(batch, self.time_bucket_steps, rows)
        return depth_to_unit_float(batch)

    def sensor_randomisation(self) -> SensorRandomisation:
        """The sensor model on the dataset's camera and depth range (after ``setup``)."""
        if self._sensor_aug is None:
            recorded = self.sensor or {}
            self._sensor_aug = SensorRandomisation(self.sensor_config, self.sensor_prob, recorded.get("camera"),
                                                   float(recorded.get("depth_max_m") or 10.0))
        return self._sensor_aug

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

    def _train_val_loader(self, dataset: TrajectoryDataset, shuffle: bool, batch_size: int) -> DataLoader:
        loader = self._loader(dataset, shuffle, batch_size)
        if not self.use_resident():
            return loader
        # the same batches (same sampler) as indices only; nothing to read ahead from the file
        sampler = loader.batch_sampler
        if getattr(sampler, "prefetch", None) is not None:
            sampler.prefetch = None
        return DataLoader(WindowIndexDataset(dataset.windows), collate_fn=collate_windows, batch_sampler=sampler,
                          generator=_own_generator(shuffle))

    def train_dataloader(self) -> DataLoader:
        self._save_split_once()
        return self._train_val_loader(self._datasets["train"], shuffle=True, batch_size=self.batch_size)

    def val_dataloader(self) -> DataLoader | list:
        self._save_split_once()
        val = self._datasets.get("val")
        return [] if val is None else self._train_val_loader(val, shuffle=False, batch_size=self.val_rows())

    def val_rows(self) -> int:
        """Trajectories (or windows) per validation call on the training device: ``cpu_val_batch_size`` on a
        CPU where it is set, else ``val_batch_size``. The loader and the padding both ask here."""
        if self.cpu_val_batch_size is not None and self._training_device().type == "cpu":
            return self.cpu_val_batch_size
        return self.val_batch_size

    def test_dataloader(self) -> DataLoader:
        self._save_split_once()
        dataset = self._datasets.get("test") or self._datasets.get("val")
        if dataset is None:
            raise VitflyError("data.test_path: no test dataset given and no validation trajectories to test on")
        return self._loader(dataset, shuffle=False)

    def predict_dataloader(self) -> DataLoader:
        self._save_split_once()
        dataset = self._datasets.get("predict") or self._datasets.get("val")
        if dataset is None:
            raise VitflyError("data.predict_path: no dataset given and no validation trajectories to predict on")
        return self._loader(dataset, shuffle=False)


def _own_generator(shuffle: bool) -> torch.Generator | None:
    """A generator of its own for a loader that draws nothing random (validation, test, predict).

    A DataLoader draws a seed for its workers each time it starts, from the global generator unless it is given
    one: a validation would shift every later dropout mask of the training, so how often a run validates
    (``check_val_every_n_epoch``) would change the weights it trains. With its own generator it does not. The
    training loader keeps the global one, whose state travels in checkpoints (``RngState``).
    """
    return None if shuffle else torch.Generator()
