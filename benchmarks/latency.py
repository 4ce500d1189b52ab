"""Latency of the paper's five networks, vitfly's back ends side by side with the original code, in one run.

Every (model, back end) is built once (ONNX Runtime back ends exported and checked against eager first),
then timed ``--repeats`` times with ``vitfly.eval.latency.time_step``: batch 1, ``--threads`` thread(s),
``--warmup`` untimed calls, then ``--iters`` individually timed ones, median and p90, recurrent state carried.
Within a repeat the back ends of one model run one after another, so a burst of load from other processes
hits them alike. ``--clock cpu`` times each call by the calling thread's CPU time instead of elapsed time:
on a machine shared with other jobs it leaves out the time spent waiting for a core (not cache contention).

``--original-repo PATH`` points at a checkout of the original project
(anish-bhattacharya/ViT-for-quadrotor-obstacle-avoidance): its ``models/model.py`` is imported and its five
networks are timed in the same run with the same settings, called as its deployment code calls them
(``vitfly.eval.original_networks``). The table then gives each back end's ratio to the original (per repeat,
then the median of those ratios) and the targets: eager no slower than the original, ONNX Runtime back
ends at most a quarter of it. Without ``--original-repo`` there is no original column and no target.

    .venv/bin/python benchmarks/latency.py --original-repo ../ViT-for-quadrotor-obstacle-avoidance \\
        --repeats 3 --out runs/latency.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
from rich.console import Console
from rich.progress import Progress
from rich.table import Table

from vitfly.errors import VitflyError
from vitfly.eval.latency import BACKENDS, prepare_original, prepare_step, time_step
from vitfly.eval.original_networks import ORIGINAL_NETWORKS, load_original_models

TARGET_FRACTION = {"eager": 1.0, "onnxruntime": 0.25, "onnxruntime-int8": 0.25}


def run(args: argparse.Namespace) -> dict:
    """Build, time and summarise; returns the JSON payload (``summary`` rows and every ``runs`` result)."""
    module = load_original_models(args.original_repo) if args.original_repo else None
    backends = (["original"] if module is not None else []) + list(args.backends)
    console = Console(stderr=True)
    prepared = {}
    with Progress(console=console, transient=True) as progress:
        task = progress.add_task("building", total=len(args.models) * len(backends))
        for model in args.models:
            for backend in backends:
                progress.update(task, description=f"building {model} [{backend}]")
                if backend == "original":
                    prepared[(model, backend)] = prepare_original(module, model, args.threads)
                else:
                    prepared[(model, backend)] = prepare_step(model, backend, "cpu", args.threads)
                progress.advance(task)
        runs: dict[tuple[str, str], list] = {key: [] for key in prepared}
        task = progress.add_task("timing", total=len(prepared) * args.repeats)
        for repeat in range(args.repeats):
            for key, step in prepared.items():
                progress.update(task, description=f"repeat {repeat + 1}: {key[0]} [{key[1]}]")
                runs[key].append(time_step(step, args.iters, args.warmup, args.clock))
                progress.advance(task)
    summary = []
    for (model, backend), results in runs.items():
        best = min(results, key=lambda r: r.median_ms)
        row = {"model": model, "backend": backend, "params": best.params, "best_median_ms": best.median_ms,
               "best_p90_ms": best.p90_ms, "medians_ms": [r.median_ms for r in results],
               "max_abs_diff": best.max_abs_diff}  # fmt: skip
        if module is not None and backend != "original":
            original = runs[(model, "original")]
            ratios = [r.median_ms / o.median_ms for r, o in zip(results, original, strict=True)]
            row["ratios_to_original"] = ratios
            row["ratio_to_original"] = float(np.median(ratios))
            row["target_ratio"] = TARGET_FRACTION[backend]
            row["met"] = row["ratio_to_original"] <= TARGET_FRACTION[backend]
        summary.append(row)
    return {"settings": {k: v for k, v in vars(args).items() if k != "out"}, "summary": summary,
            "runs": [r.to_dict() for rs in runs.values() for r in rs]}  # fmt: skip


def table(payload: dict) -> Table:
    s = payload["settings"]
    has_original = s["original_repo"] is not None
    table = Table(title=f"Latency, batch 1, {s['threads']} thread(s), median of {s['iters']} calls, "
                        f"{s['repeats']} repeat(s), ms ({s['clock']} clock)")  # fmt: skip
    columns = ["Model", "Backend", "Medians of the repeats", "Best median", "p90"]
    if has_original:
        columns += ["x original (per repeat)", "x original", "Target", "Met"]
    for column in columns:
        table.add_column(column, justify="left" if column in ("Model", "Backend") else "right")
    for row in payload["summary"]:
        cells = [row["model"], row["backend"], " ".join(f"{m:.3f}" for m in row["medians_ms"]),
                 f"{row['best_median_ms']:.3f}", f"{row['best_p90_ms']:.3f}"]  # fmt: skip
        if has_original:
            if row["backend"] == "original":
                cells += ["", "1", "", ""]
            else:
                cells += [" ".join(f"{r:.2f}" for r in row["ratios_to_original"]), f"{row['ratio_to_original']:.2f}",
                          f"<= {row['target_ratio']:g}", "yes" if row["met"] else "NO"]  # fmt: skip
        table.add_row(*cells)
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(ORIGINAL_NETWORKS), choices=list(ORIGINAL_NETWORKS))
    parser.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=list(BACKENDS))
    parser.add_argument("--original-repo", default=None, metavar="PATH",
                        help="checkout of the original project: time its networks in the same run")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--iters", type=int, default=1000)
    parser.add_argument("--warmup", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                        help="wall: elapsed time per call (the paper's measure); cpu: the thread's CPU time per call, "
                        "which leaves out waiting for a core on a shared machine")  # fmt: skip
    parser.add_argument("--out", default=None, help="JSON with the settings, the summary and every repeat")
    args = parser.parse_args(argv)
    try:
        payload = run(args)
    except VitflyError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 160))
    console.print(table(payload))
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        tmp = args.out + ".tmp"
        with open(tmp, "w") as f:
            json.dump(payload, f, indent=2)
        os.replace(tmp, args.out)
    return 0 if all(row.get("met") is not False for row in payload["summary"]) else 1


if __name__ == "__main__":
    sys.exit(main())
