"""Log an evaluation's summary table, plots and GIFs to Weights & Biases (offline with WANDB_MODE=offline)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from vitfly.eval.report import csv_columns


def log_evaluation(project: str, rows: Sequence[dict], images: Mapping[str, Path], out_dir: str | Path,
                   run_name: str | None = None, config: Mapping | None = None) -> str:
    """One wandb run holding ``summary`` (a table, one row per (policy, env, speed)) and every image; returns
    the run's directory."""
    import wandb

    os.environ.setdefault("WANDB_MODE", "offline")  # offline unless the user chose a mode
    columns = csv_columns()
    run = wandb.init(project=project, name=run_name, dir=str(out_dir), config=dict(config or {}), job_type="eval",
                     reinit="finish_previous")
    try:
        table = wandb.Table(columns=columns, data=[[row.get(c) for c in columns] for row in rows])
        payload = {"summary": table}
        for name, path in images.items():
            payload[name] = wandb.Video(str(path), format="gif") if Path(path).suffix == ".gif" else wandb.Image(
                str(path))
        for row in rows:  # scalar series, e.g. success_paper_rate/convnet/spheres at each speed
            key = f"{row['policy']}/{row['env']}"
            for rate in ("success_paper_rate", "success_strict_rate"):
                run.summary[f"{rate}/{key}/{row['speed']:g}"] = row[rate]
            run.summary[f"collisions_mean/{key}/{row['speed']:g}"] = row["collisions_mean"]
        run.log(payload)
        return str(run.dir)
    finally:
        run.finish()
