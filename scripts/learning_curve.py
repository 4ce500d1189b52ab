"""Learning curves of a training study: validation metrics per epoch beside closed-loop success.

Reads what ``scripts/gpu_study.py`` brings back (unpacked into STUDY) and the evaluations flown from its
published snapshots::

    STUDY/logs/metrics_<run>.csv           validation loss and lateral / vertical R^2 per epoch (CSV logger)
    STUDY/<snapshot>/manifest.json         which epoch each published snapshot (end/, middle/) holds
    EVAL/<snapshot>/<run>/                 vitfly evaluate --name <run> of pretrained:<run> from that snapshot

    python scripts/learning_curve.py --study runs/gpu_study --eval runs/gpu_study/sel --out docs/learning_curves.png

Left: validation R^2 of the lateral command (solid) and vertical (dashed) per epoch; right: closed-loop
success (the paper's definition, all speeds pooled) at each evaluated snapshot with its 95 % Wilson
interval. A markdown table of the same numbers is printed.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from vitfly.eval import records  # noqa: E402
from vitfly.eval.aggregate import summarize  # noqa: E402
from vitfly.eval.findings import Table, wilson  # noqa: E402


def validation_curve(metrics_csv: Path) -> list[dict]:
    """One row per validation: epoch (1-based, completed), val/loss, val/r2_lateral, val/r2_vertical."""
    rows = []
    with open(metrics_csv) as f:
        for r in csv.DictReader(f):
            if r.get("val/loss"):
                rows.append({"epoch": int(r["epoch"]) + 1, "loss": float(r["val/loss"]),
                             "r2_lateral": float(r["val/r2_lateral"]), "r2_vertical": float(r["val/r2_vertical"])})
    return rows


def snapshot_epoch(study: Path, snapshot: str, run: str) -> int | None:
    """Epochs completed by the published snapshot (its checkpoint is epochNNN.ckpt, NNN 0-based)."""
    manifest = study / snapshot / "manifest.json"
    if not manifest.exists():
        return None
    entry = json.loads(manifest.read_text())["models"].get(run)
    if entry is None:
        return None
    return int(Path(entry["source_checkpoint"]).stem.removeprefix("epoch")) + 1


def closed_loop(eval_dir: Path, run: str) -> tuple[int, int, dict[float, float]]:
    """(successes, trials) of ``run`` pooled over speeds, and its success rate per speed."""
    table = Table(summarize(records.read_sweep(eval_dir)))
    wins, trials = table.pooled(run)
    per_speed = {s: k / n for s in table.speeds(run) for k, n in [table.rate(run, s)]}
    return wins, trials, per_speed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--study", type=Path, required=True, help="unpacked gpu_study output (logs/, end/, middle/)")
    p.add_argument("--eval", type=Path, required=True, help="EVAL/<snapshot>/<run>/ evaluation directories")
    p.add_argument("--runs", nargs="*", help="runs to show (default: every metrics_<run>.csv)")
    p.add_argument("--out", type=Path, required=True, help="PNG to write")
    args = p.parse_args(argv)
    runs = args.runs or sorted(f.stem.removeprefix("metrics_") for f in (args.study / "logs").glob("metrics_*.csv"))
    fig, (ax_val, ax_cl) = plt.subplots(1, 2, figsize=(11, 4.2))
    print("| run | snapshot | epochs | val R^2 lateral / vertical | success 3 / 5 / 7 m/s | pooled (95 % CI) |")
    print("|---|---|---|---|---|---|")
    for i, run in enumerate(runs):
        color = f"C{i}"
        curve = validation_curve(args.study / "logs" / f"metrics_{run}.csv")
        epochs = [r["epoch"] for r in curve]
        ax_val.plot(epochs, [r["r2_lateral"] for r in curve], color=color, label=run)
        ax_val.plot(epochs, [r["r2_vertical"] for r in curve], color=color, ls="--")
        points = []
        for snapshot in ("middle", "end"):
            eval_dir = args.eval / snapshot / run
            epoch = snapshot_epoch(args.study, snapshot, run)
            if epoch is None or not eval_dir.is_dir():
                continue
            wins, n, per_speed = closed_loop(eval_dir, run)
            lo, hi = wilson(wins, n)
            points.append((epoch, wins / n, lo, hi))
            val = next((r for r in curve if r["epoch"] == epoch), None)
            r2 = f"{val['r2_lateral']:.2f} / {val['r2_vertical']:.2f}" if val else "-"
            speeds = " / ".join(f"{100 * per_speed[s]:.0f}" for s in sorted(per_speed))
            print(f"| {run} | {snapshot} | {epoch} | {r2} | {speeds} % | {100 * wins / n:.0f} % "
                  f"({100 * lo:.0f}-{100 * hi:.0f}), n={n} |")
        if points:
            xs = [x for x, _, _, _ in points]
            ys = [100 * y for _, y, _, _ in points]
            err = [[100 * (y - lo) for _, y, lo, _ in points], [100 * (hi - y) for _, y, _, hi in points]]
            ax_cl.errorbar(xs, ys, yerr=err, color=color, marker="o", capsize=3, label=run)
    ax_val.set(xlabel="epoch", ylabel="validation R$^2$ (solid: lateral, dashed: vertical)", ylim=(0, None))
    ax_cl.set(xlabel="epoch", ylabel="closed-loop success, 3-7 m/s pooled (%)", ylim=(0, 100))
    ax_val.legend(fontsize=8)
    ax_cl.legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
