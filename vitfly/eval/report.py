"""Summary rows -> ``summary.csv``, ``summary.md`` and a comparison table on the console."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path

from vitfly.atomic import write_text
from vitfly.eval.aggregate import AGGREGATED_METRICS, RATE_COLUMNS
from vitfly.eval.findings import wilson

BASE_COLUMNS = ("policy", "policy_id", "env", "speed", "trials", *RATE_COLUMNS)

# Markdown / console table: (header, column stem or rate column, digits). Success is shown twice,
# each header naming its definition (TABLE_LEGEND); the paper's comes first, with its 95 % Wilson interval.
TABLE_COLUMNS: tuple[tuple[str, str, int], ...] = (
    ("success % (paper)", "success_paper_rate", 0),
    ("success % (strict)", "success_strict_rate", 0),
    ("collisions / trial", "collisions", 2),
    ("time in collision (s, paper)", "time_in_collision", 2),
    ("time in collision (s, colliding)", "time_in_collision_colliding", 2),
    ("energy cost (1/s^2)", "energy_cost", 2),
    ("cmd acc (1/s^2)", "cmd_acc", 2),
    ("max lateral dev (m)", "lateral_dev_max", 2),
    ("time to goal (s)", "time_to_goal", 1),
    ("speed ratio", "speed_ratio", 2),
    ("policy ms / tick", "processing_ms", 2),
)
TABLE_LEGEND = ("success (paper) = no collision, the paper's definition; success (strict) = goal reached and no "
                "collision. Time in collision = contact time / collisions: (paper) 0 for trials without one, mean "
                "over all trials, as the paper plots it; (colliding) mean over trials with a collision. "
                "Brackets: the 95 % Wilson interval of the paper's success rate.")
INTERVAL_COLUMNS = ("success_paper_rate",)  # rates shown with their interval: the one the study's verdicts use


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
        if column not in INTERVAL_COLUMNS:
            return f"{100 * v:.{digits}f}"
        low, high = wilson(round(v * row["trials"]), row["trials"])
        return f"{100 * v:.{digits}f} ({100 * low:.0f}-{100 * high:.0f})"
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
    rates = [f"- {column}: {desc}" for column, (_, desc) in RATE_COLUMNS.items()]
    notes = [f"- {stem}: {desc}" + (f" ({unit})" if unit else "")
             for stem, (_, unit, desc) in AGGREGATED_METRICS.items()]
    return "\n".join([*lines, "", TABLE_LEGEND, "",
                      "Rates in %, other cells mean ± std over trials. Columns of summary.csv:", *rates, *notes, ""])


def print_table(rows: Sequence[dict], title: str = "closed-loop evaluation") -> None:
    """The comparison table on the console (rich)."""
    from rich.console import Console
    from rich.table import Table

    header, body = table_cells(rows)
    table = Table(title=title, caption=TABLE_LEGEND)
    for i, h in enumerate(header):
        table.add_column(h, justify="left" if i < 2 else "right")
    for cells in body:
        table.add_row(*cells)
    Console(width=max(Console().width, 200)).print(table)  # logs and pipes get the full table


def summary_title(out_dir: str | Path) -> str | None:
    """The title ``summary.md`` in ``out_dir`` was written with (``summary_markdown``), or None: reports written
    again keep it."""
    path = Path(out_dir) / "summary.md"
    first = path.read_text().partition("\n")[0] if path.exists() else ""
    return first[3:] if first.startswith("## ") else None


def write_reports(out_dir: str | Path, rows: Sequence[dict], title: str | None = None) -> dict[str, Path]:
    """Write ``summary.csv`` and ``summary.md`` into ``out_dir`` (each atomically); return their paths."""
    out = Path(out_dir)
    paths = {"csv": out / "summary.csv", "markdown": out / "summary.md"}
    write_text(paths["csv"], summary_csv(rows))
    write_text(paths["markdown"], summary_markdown(rows, title))
    return paths
