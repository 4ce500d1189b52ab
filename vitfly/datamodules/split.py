"""The train/validation split of a run: drawn once, by trajectory, then frozen.

A run directory's split is drawn (seeded) the first time the run sets up and recorded in
``split.json``; every later setup of that run (a resume, ``validate``, a resume from its checkpoint in
another directory) reuses the recorded split instead of drawing again. A dataset that grew since
(a collection resumed and appended trajectories) keeps every recorded trajectory where it was and
puts the new ones into training: validation never gains a trajectory that was trained on, and
validation losses before and after the growth are over the same trajectories.

A record names the dataset it was made for by a fingerprint of its trajectories (env, seed and
length of each, in order). It fits a dataset whose first ``num_trajectories`` trajectories have
that fingerprint; anything else (another dataset, a shrunken one, indices beyond the count) is one
clear error.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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


@dataclass(frozen=True)
class TrajectoryIds:
    """What identifies the trajectories of a dataset, in order: env name, seed and length of each."""

    envs: tuple[str, ...]
    seeds: tuple[int, ...]
    lengths: tuple[int, ...]

    @classmethod
    def of(cls, trajectory_file) -> TrajectoryIds:
        """From an open ``TrajectoryFile``."""
        return cls(
            tuple(str(e) for e in trajectory_file.table["env"]),
            tuple(int(s) for s in trajectory_file.table["seed"]),
            tuple(int(n) for n in trajectory_file.lengths),
        )

    def __len__(self) -> int:
        return len(self.seeds)

    def fingerprint(self, count: int | None = None) -> str:
        """sha256 (hex) of the first ``count`` trajectories' (env, seed, length), all by default."""
        count = len(self) if count is None else count
        h = hashlib.sha256()
        for env, seed, length in zip(self.envs[:count], self.seeds[:count], self.lengths[:count], strict=True):
            h.update(f"{env}\0{seed}\0{length}\n".encode())
        return h.hexdigest()


@dataclass(frozen=True)
class Split:
    """Trajectory indices of training and validation; ``added``: trajectories new since the split was frozen
    (they are in ``train``); ``source``: where it came from (a file, a checkpoint, or "drawn")."""

    train: list[int]
    val: list[int]
    source: str = "drawn"
    added: tuple[int, ...] = ()

    def record(self, ids: TrajectoryIds, data_path: str, val_fraction: float, split_seed: int, **extra) -> dict:
        """The JSON-able record (split.json, and the datamodule's checkpoint state)."""
        return {
            "data_path": os.path.abspath(data_path),
            "num_trajectories": len(ids),
            "fingerprint": ids.fingerprint(),
            "val_fraction": val_fraction,
            "split_seed": split_seed,
            **extra,
            "train": list(self.train),
            "val": list(self.val),
            "train_seeds": [ids.seeds[i] for i in self.train],
            "val_seeds": [ids.seeds[i] for i in self.val],
        }


def read_split_file(path: str | os.PathLike) -> dict:
    """The record in a split.json; one-line VitflyError for an unreadable file."""
    path = Path(path)
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise VitflyError(f"{path}: not a readable split file ({err})") from None
    if not isinstance(record, dict):
        raise VitflyError(f"{path}: not a split file (expected a JSON object with 'train' and 'val' index lists)")
    return record


def _indices(record: dict, key: str, source: str) -> list[int]:
    values = record.get(key)
    if not isinstance(values, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in values):
        raise VitflyError(f"{source}: field {key!r} must be a list of trajectory indices, got {values!r:.80}")
    return values


def reuse_split(record: dict, ids: TrajectoryIds, data_path: str, source: str) -> Split:
    """The recorded split applied to the dataset ``ids`` describes (at ``data_path``): recorded trajectories keep
    their side, trajectories beyond the recorded count go to training. Raises VitflyError (one line) when the
    record does not fit the dataset."""
    train, val = _indices(record, "train", source), _indices(record, "val", source)
    count = len(ids)
    for key, values in (("train", train), ("val", val)):
        beyond = [i for i in values if not 0 <= i < count]
        if beyond:
            raise VitflyError(
                f"{source}: field {key!r} holds trajectory {beyond[0]}, but {data_path} holds {count} trajectories "
                "(a split of another dataset?)"
            )
        if len(set(values)) != len(values):
            raise VitflyError(f"{source}: field {key!r} lists a trajectory twice")
    both = sorted(set(train) & set(val))
    if both:
        raise VitflyError(f"{source}: trajectory {both[0]} is in both 'train' and 'val'")
    recorded = record.get("num_trajectories")
    if not isinstance(recorded, int) or isinstance(recorded, bool) or recorded < max([*train, *val], default=-1) + 1:
        raise VitflyError(
            f"{source}: field 'num_trajectories' is {recorded!r}, expected the number of trajectories the split "
            "was made for (at least its largest index + 1)"
        )
    if recorded > count:
        raise VitflyError(
            f"{source}: made for {recorded} trajectories, but {data_path} holds {count} (another or a shrunken dataset)"
        )
    fingerprint = record.get("fingerprint")
    if fingerprint is not None:
        if fingerprint != ids.fingerprint(recorded):
            raise VitflyError(
                f"{source}: made for another dataset: the env, seed and length of trajectories 0..{recorded - 1} "
                f"of {data_path} differ from those it records (field 'fingerprint')"
            )
    else:  # a record written before fingerprints: its seeds must still match
        for key, values in (("train_seeds", train), ("val_seeds", val)):
            seeds = record.get(key)
            if seeds is not None and list(seeds) != [ids.seeds[i] for i in values]:
                raise VitflyError(f"{source}: field {key!r} does not match the seeds in {data_path} (another dataset?)")
    added = tuple(range(recorded, count))
    return Split(sorted([*train, *added]), sorted(val), source, added)


def describe(split: Split, record: dict, val_fraction: float, split_seed: int) -> str:
    """One line on a reused split (for the log)."""
    text = f"split: reusing the frozen split of {split.source} ({len(split.train)} train / {len(split.val)} val"
    if split.added:
        text += f"; {len(split.added)} trajectories new since it was frozen go to training"
    text += ")"
    stored = (record.get("val_fraction"), record.get("split_seed"))
    if None not in stored and stored != (val_fraction, split_seed):
        text += f"; its val_fraction {stored[0]} and split_seed {stored[1]} stand, not {val_fraction} / {split_seed}"
    return text


def same_split(a: Split, b: Split) -> bool:
    return a.train == b.train and a.val == b.val


__all__ = [
    "SPLIT_FILE",
    "Split",
    "TrajectoryIds",
    "describe",
    "read_split_file",
    "reuse_split",
    "same_split",
    "split_trajectories",
]
