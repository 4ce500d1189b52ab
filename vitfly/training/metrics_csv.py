"""A run's ``metrics.csv`` whole across resumes.

Lightning's ``CSVLogger`` empties ``metrics.csv`` when a run resumes in the same folder, so the learning curve
before the resume would be lost. ``set_aside`` moves the rows of the finished epochs into ``metrics.earlier.csv``
before the resume; ``join`` puts earlier and new rows back into ``metrics.csv`` afterwards. A session killed
between the two leaves both files, and the next ``set_aside`` joins them again (rows of an epoch the killed
session did not finish are dropped: the resume trains that epoch again).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

METRICS = "metrics.csv"
EARLIER_METRICS = "metrics.earlier.csv"  # rows of the epochs before a resume


def merge_metrics(parts: list[Path], dst: Path, epochs: int | None = None) -> None:
    """The rows of ``parts`` (CSVLogger files, oldest first) as one CSV in ``dst``, columns united; with
    ``epochs``, only rows of epochs below it (a killed run's rows of the epoch it did not finish go)."""
    header: list[str] = []
    rows: list[dict] = []
    for part in parts:
        if not part.exists():
            continue
        with open(part, newline="") as f:
            reader = csv.DictReader(f)
            header += [c for c in reader.fieldnames or [] if c not in header]
            rows += [r for r in reader if epochs is None or not r.get("epoch") or float(r["epoch"]) < epochs]
    if not header:
        return
    tmp = dst.with_name(dst.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=header)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, dst)


def set_aside(run_dir: Path, epochs_done: int) -> None:
    """Before a run resumes after ``epochs_done`` epochs: its rows so far into ``metrics.earlier.csv``."""
    current, earlier = run_dir / METRICS, run_dir / EARLIER_METRICS
    if current.exists():
        merge_metrics([earlier, current], earlier, epochs_done)
        current.unlink()


def join(run_dir: Path) -> None:
    """After a resumed session: the earlier rows and the new ones as one ``metrics.csv``."""
    earlier = run_dir / EARLIER_METRICS
    if earlier.exists():
        merge_metrics([earlier, run_dir / METRICS], run_dir / METRICS)
        earlier.unlink()


def epoch_curves(run_dir: Path, columns: tuple[str, ...] = ("train/loss_epoch", "val/loss")) -> dict[str, list]:
    """Per column, ``[(epoch, value), ...]`` (epochs counted from 1, ascending) of a run's logged epochs, across
    resumes: ``metrics.earlier.csv`` (a session stopped between ``set_aside`` and ``join``) first, then
    ``metrics.csv``, a later row of the same epoch winning. Columns never logged give an empty list."""
    values: dict[str, dict[int, float]] = {c: {} for c in columns}
    for part in (run_dir / EARLIER_METRICS, run_dir / METRICS):
        if not part.exists():
            continue
        with open(part, newline="") as f:
            for row in csv.DictReader(f):
                if not row.get("epoch"):
                    continue
                for column in columns:
                    if row.get(column):
                        values[column][int(float(row["epoch"])) + 1] = float(row[column])
    return {c: sorted(v.items()) for c, v in values.items()}
