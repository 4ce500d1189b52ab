"""Latency of the paper's five networks, eager and ONNX Runtime, against the issue's targets.

Runs ``vitfly.eval.latency.benchmark_model`` (batch 1, one thread by default, warm-up, then ``--iters``
timed calls, recurrent state carried) ``--repeats`` times per (model, back end), interleaved so that a
burst of load from other processes hits every model alike, and reports each repeat's median plus the
best (lowest) median with its p90. The targets are the original implementation's medians on this
machine class (issue 2): eager must be no slower, ONNX Runtime at most a quarter.

    .venv/bin/python benchmarks/latency.py --repeats 3 --out runs/latency.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from rich.console import Console
from rich.progress import Progress
from rich.table import Table

from vitfly.eval.latency import benchmark_model

# Original implementation, one thread, median of 1000 calls, on this machine class (issue 2)
ORIGINAL_MS = {"convnet": 0.17, "lstmnet": 4.5, "unet_lstm": 5.5, "vit": 6.1, "vit_lstm": 8.8}
TARGET_FRACTION = {"eager": 1.0, "onnxruntime": 0.25}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(ORIGINAL_MS))
    parser.add_argument("--backends", nargs="+", default=["eager", "onnxruntime"], choices=list(TARGET_FRACTION))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--iters", type=int, default=1000)
    parser.add_argument("--warmup", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="JSON with every repeat and the summary")
    args = parser.parse_args(argv)

    runs: dict[tuple[str, str], list] = {(m, b): [] for m in args.models for b in args.backends}
    with Progress(console=Console(stderr=True), transient=True) as progress:
        task = progress.add_task("latency", total=len(runs) * args.repeats)
        for repeat in range(args.repeats):
            for model, backend in runs:
                progress.update(task, description=f"repeat {repeat + 1}: {model} [{backend}]")
                runs[(model, backend)].append(
                    benchmark_model(model, backend, "cpu", args.threads, args.iters, args.warmup)
                )
                progress.advance(task)

    table = Table(title=f"Latency, batch 1, {args.threads} thread(s), median of {args.iters} calls")
    for column in ("Model", "Backend", "Medians of the repeats (ms)", "Best median", "p90", "Target", "Met"):
        table.add_column(column, justify="left" if column in ("Model", "Backend") else "right")
    summary = []
    for (model, backend), results in runs.items():
        best = min(results, key=lambda r: r.median_ms)
        target = ORIGINAL_MS.get(model)
        target = None if target is None else target * TARGET_FRACTION[backend]
        met = None if target is None else best.median_ms <= target
        table.add_row(
            model,
            backend,
            " ".join(f"{r.median_ms:.3f}" for r in results),
            f"{best.median_ms:.3f}",
            f"{best.p90_ms:.3f}",
            "n/a" if target is None else f"<= {target:.3f}",
            "n/a" if met is None else ("yes" if met else "NO"),
        )
        summary.append(
            {"model": model, "backend": backend, "best_median_ms": best.median_ms, "best_p90_ms": best.p90_ms,
             "target_ms": target, "met": met, "medians_ms": [r.median_ms for r in results]}
        )  # fmt: skip
    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 120))
    console.print(table)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        tmp = args.out + ".tmp"
        with open(tmp, "w") as f:
            json.dump({"summary": summary, "runs": [r.to_dict() for rs in runs.values() for r in rs]}, f, indent=2)
        os.replace(tmp, args.out)
    return 0 if all(s["met"] is not False for s in summary) else 1


if __name__ == "__main__":
    sys.exit(main())
