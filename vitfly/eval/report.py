"""Summary rows -> ``summary.csv``, ``summary.md`` and a comparison table on the console."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path

from vitfly.atomic import write_text
from vitfly.eval.aggregate import AGGREGATED_METRICS

BASE_COLUMNS = ("policy", "env", "speed", "trials", "success_rate", "reached_goal_rate", "collision_free_rate")

# Markdown / console table: (header, column stem or rate column, digits)
TABLE_COLUMNS: tuple[tuple[str, str, int], ...] = (
    ("success %", "success_rate", 0),
    ("collisions / trial", "collisions", 2),
    ("time in collision (s)", "time_in_collision", 2),
    ("energy cost (1/s^2)", "energy_cost", 2),
    ("cmd acc (1/s^2)", "cmd_acc", 2),
    ("max lateral dev (m)", "lateral_dev_max", 2),
    ("speed ratio", "speed_ratio", 2),
    ("policy ms / tick", "processing_ms", 2),
)


def csv_columns() -> list[str]:
    cols = list(BASE_COLUMNS)
    for stem in AGGREGATED_METRICS:
        cols += [f"{stem}_mean", f"{stem}_std"]
    return cols


def summary_csv(rows: Sequence[dict]) -> str:
    """CSV text, one row per (policy, env, speed); undefined values are empty cells."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=csv_columns(), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()})
    return buf.getvalue()


def _cell(row: dict, column: str, digits: int) -> str:
    if column.endswith("_rate"):
        v = row[column]
        return f"{100 * v:.{digits}f}"
    mean, std = row[f"{column}_mean"], row[f"{column}_std"]
    if not math.isfinite(mean):
        return "-"
    return f"{mean:.{digits}f} ± {std:.{digits}f}" if math.isfinite(std) else f"{mean:.{digits}f}"


def table_cells(rows: Sequence[dict]) -> tuple[list[str], list[list[str]]]:
    """Header and cell strings of the comparison table (mean ± std; rates in %)."""
    header = ["policy", "env", "speed (m/s)", "trials", *(h for h, _, _ in TABLE_COLUMNS)]
    body = [
        [str(r["policy"]), str(r["env"]), f"{r['speed']:g}", str(r["trials"]),
         *(_cell(r, c, d) for _, c, d in TABLE_COLUMNS)]
        for r in rows
    ]
    return header, body


def summary_markdown(rows: Sequence[dict], title: str | None = None) -> str:
    header, body = table_cells(rows)
    lines = [f"## {title}", ""] if title else []
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "|".join("---" if i < 2 else "---:" for i in range(len(header))) + "|")
    lines += ["| " + " | ".join(cells) + " |" for cells in body]
    notes = [f"- {stem}: {desc}" + (f" ({unit})" if unit else "")
             for stem, (_, unit, desc) in AGGREGATED_METRICS.items()]
    return "\n".join([*lines, "", "Mean ± std over trials. Columns of summary.csv:", *notes, ""])


def print_table(rows: Sequence[dict], title: str = "closed-loop evaluation") -> None:
    """The comparison table on the console (rich)."""
    from rich.console import Console
    from rich.table import Table

    header, body = table_cells(rows)
    table = Table(title=title)
    for i, h in enumerate(header):
        table.add_column(h, justify="left" if i < 2 else "right")
    for cells in body:
        table.add_row(*cells)
    Console(width=max(Console().width, 170)).print(table)  # logs and pipes get the full table


def write_reports(out_dir: str | Path, rows: Sequence[dict], title: str | None = None) -> dict[str, Path]:
    """Write ``summary.csv`` and ``summary.md`` into ``out_dir`` (each atomically); return their paths."""
    out = Path(out_dir)
    paths = {"csv": out / "summary.csv", "markdown": out / "summary.md"}
    write_text(paths["csv"], summary_csv(rows))
    write_text(paths["markdown"], summary_markdown(rows, title))
    return paths
