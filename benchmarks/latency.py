"""Latency of the paper's five networks, vitfly's back ends side by side with the original code, in one run.

Every (model, back end) is built once (ONNX Runtime back ends exported and checked against eager first; the
int8 ViTs calibrated on recorded expert flights), then, model by model, timed with
``vitfly.eval.latency.time_interleaved``: batch 1, one thread, recurrent state carried, the back ends taking
turns in blocks of ``--block`` calls (order reversed every other round) until each has ``--iters`` timed
calls, every call timed on both clocks -- elapsed (wall) time, the paper's measure, and the process's CPU
time, which leaves out the time spent waiting for a core on a machine shared with other jobs. This is done
``--repeats`` times; each repeat gives a median per back end and a ratio to the original's median of the
same repeat, and the table gives the median of those ratios with their spread (min-max over the repeats).

``--original-repo PATH`` points at a checkout of the original project
(anish-bhattacharya/ViT-for-quadrotor-obstacle-avoidance): its ``models/model.py`` is imported and its
networks are timed with the others, called as its deployment code calls them
(``vitfly.eval.original_networks``). Targets: eager no slower than the original, the ONNX Runtime back ends
at most a quarter of it (met when the median ratio is within the target). Without ``--original-repo`` there
is no original column and no target.

    .venv/bin/python benchmarks/latency.py --original-repo ../ViT-for-quadrotor-obstacle-avoidance \\
        --repeats 5 --out runs/latency.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from vitfly.errors import VitflyError
from vitfly.eval.latency import prepare_original, prepare_step, time_interleaved
from vitfly.eval.original_networks import ORIGINAL_NETWORKS, load_original_models

BACKENDS = ("eager", "compiled", "onnxruntime", "onnxruntime-int8")
TARGET_FRACTION = {"eager": 1.0, "compiled": 1.0, "onnxruntime": 0.25, "onnxruntime-int8": 0.25}
CLOCK_NAMES = ("wall", "cpu")


def run(args: argparse.Namespace, log=print) -> dict:
    """Build, time and summarise; returns the JSON payload (``summary`` rows and every repeat's medians)."""
    if args.threads != 1:
        raise VitflyError("--threads: the interleaved timing measures one thread (the CPU clock needs it)")
    module = load_original_models(args.original_repo) if args.original_repo else None
    backends = (["original"] if module is not None else []) + list(args.backends)
    torch.set_num_threads(1)
    summary, repeats = [], []
    for model in args.models:
        steps, prepared = {}, {}
        for backend in backends:
            log(f"building {model} [{backend}]")
            if backend == "original":
                prepared[backend] = prepare_original(module, model, 1)
            else:
                prepared[backend] = prepare_step(model, backend, "cpu", 1)
            steps[backend] = prepared[backend].step
        medians = {backend: {clock: [] for clock in CLOCK_NAMES} for backend in backends}
        for repeat in range(args.repeats):
            log(f"timing {model}, repeat {repeat + 1} of {args.repeats}")
            times = time_interleaved(steps, args.iters, args.block, args.warmup)
            for backend in backends:
                for clock in CLOCK_NAMES:
                    medians[backend][clock].append(float(np.median(times[backend][clock])))
            repeats.append({"model": model, "repeat": repeat,
                            "median_ms": {b: {c: medians[b][c][-1] for c in CLOCK_NAMES} for b in backends},
                            "p90_ms": {b: {c: float(np.percentile(times[b][c], 90)) for c in CLOCK_NAMES}
                                       for b in backends}})  # fmt: skip
        for backend in backends:
            row = {"model": model, "backend": backend, "params": prepared[backend].params,
                   "max_abs_diff": prepared[backend].max_abs_diff}  # fmt: skip
            for clock in CLOCK_NAMES:
                row[f"median_ms_{clock}"] = float(np.median(medians[backend][clock]))
                row[f"medians_ms_{clock}"] = medians[backend][clock]
                if module is not None and backend != "original":
                    ratios = np.array(medians[backend][clock]) / np.array(medians["original"][clock])
                    row[f"ratios_{clock}"] = ratios.tolist()
                    row[f"ratio_{clock}"] = float(np.median(ratios))
            if module is not None and backend != "original":
                row["target_ratio"] = TARGET_FRACTION[backend]
                row["met"] = all(row[f"ratio_{clock}"] <= row["target_ratio"] for clock in CLOCK_NAMES)
            summary.append(row)
    settings = {k: v for k, v in vars(args).items() if k != "out"}
    return {"settings": settings, "summary": summary, "repeats": repeats}


def table(payload: dict) -> Table:
    s = payload["settings"]
    has_original = s["original_repo"] is not None
    table = Table(title=f"Latency, batch 1, 1 thread, {s['iters']} calls per repeat interleaved in blocks of "
                        f"{s['block']}, {s['repeats']} repeats: median ms (spread over repeats), wall / CPU clock")
    columns = ["Model", "Backend", "wall ms", "cpu ms"]
    if has_original:
        columns += ["x original wall", "x original cpu", "Target", "Met"]
    for column in columns:
        table.add_column(column, justify="left" if column in ("Model", "Backend") else "right")

    def cell(values: list[float], digits: int) -> str:
        return f"{np.median(values):.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})"

    for row in payload["summary"]:
        cells = [row["model"], row["backend"], cell(row["medians_ms_wall"], 3), cell(row["medians_ms_cpu"], 3)]
        if has_original:
            if row["backend"] == "original":
                cells += ["1", "1", "", ""]
            else:
                cells += [cell(row["ratios_wall"], 2), cell(row["ratios_cpu"], 2), f"<= {row['target_ratio']:g}",
                          "yes" if row["met"] else "NO"]  # fmt: skip
        table.add_row(*cells)
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(ORIGINAL_NETWORKS), choices=list(ORIGINAL_NETWORKS))
    parser.add_argument("--backends", nargs="+", default=["eager", "onnxruntime", "onnxruntime-int8"],
                        choices=list(BACKENDS))  # fmt: skip
    parser.add_argument("--original-repo", default=None, metavar="PATH",
                        help="checkout of the original project: time its networks in the same run")
    parser.add_argument("--threads", type=int, default=1, help="1 only (kept for the older command lines)")
    parser.add_argument("--iters", type=int, default=1000, help="timed calls per back end and repeat")
    parser.add_argument("--block", type=int, default=20, help="calls in a row before the next back end's turn")
    parser.add_argument("--warmup", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--clock", choices=("wall", "cpu"), default=None,
                        help="ignored: both clocks are always timed (kept for older command lines)")
    parser.add_argument("--out", default=None, help="JSON with the settings, the summary and every repeat")
    args = parser.parse_args(argv)
    console = Console(stderr=True)
    try:
        payload = run(args, log=lambda message: console.log(message))
    except VitflyError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = Console()
    if not out.is_terminal:
        out = Console(width=max(out.width, 160))
    out.print(table(payload))
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        tmp = args.out + ".tmp"
        with open(tmp, "w") as f:
            json.dump(payload, f, indent=2)
        os.replace(tmp, args.out)
    return 0 if all(row.get("met") is not False for row in payload["summary"]) else 1


if __name__ == "__main__":
    sys.exit(main())
