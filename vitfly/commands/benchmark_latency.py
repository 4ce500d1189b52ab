"""``vitfly benchmark-latency``: the paper's latency table (Model, Parameters, CPU ms, GPU ms) for the zoo."""

from __future__ import annotations

import argparse
import json
import os

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.eval.config import BACKENDS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", nargs="+", default=None, help="registry names (default: every registered model)")
    parser.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="auto: CPU, plus the GPU column when CUDA is present",
    )
    parser.add_argument("--threads", type=int, default=1, help="CPU threads (torch / ONNX Runtime intra-op)")
    parser.add_argument("--iters", type=int, default=1000, help="timed calls per model")
    parser.add_argument("--warmup", type=int, default=100, help="untimed calls before timing")
    parser.add_argument("--backend", choices=BACKENDS, default="eager",
                        help="inference back end (onnxruntime-int8: ONNX Runtime with int8 large products)")
    parser.add_argument("--json", default=None, metavar="PATH", help="also write the results as a JSON list")


def run(args: argparse.Namespace) -> int:
    import torch
    from rich.console import Console
    from rich.progress import Progress

    from vitfly.eval.latency import benchmark_model, latency_table
    from vitfly.zoo import list_models

    known = list_models()
    models = args.models or known
    unknown = [m for m in models if m not in known]
    if unknown:
        raise VitflyError(f"--models: unknown model(s) {', '.join(unknown)}; known models: {', '.join(known)}")
    if args.device == "auto":
        devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    else:
        devices = [args.device]
    if args.json:
        directory = os.path.dirname(os.path.abspath(args.json))
        if not os.path.isdir(directory):
            raise VitflyError(f"--json {args.json}: directory {directory} does not exist")

    console = Console(stderr=True)
    results = []
    with Progress(console=console, transient=True) as progress:
        task = progress.add_task("timing", total=len(models) * len(devices))
        for model in models:
            for device in devices:
                progress.update(task, description=f"{model} [{args.backend}, {device}]")
                results.append(
                    benchmark_model(model, args.backend, device, args.threads, args.iters, args.warmup)
                )
                progress.advance(task)
    out = Console()
    if not out.is_terminal:  # keep the table whole when piped to a file
        out = Console(width=max(out.width, 120))
    out.print(latency_table(results))
    if args.json:
        _write_json(args.json, [r.to_dict() for r in results])
        console.print(f"wrote {args.json}")
    return 0


def _write_json(path: str, payload: list[dict]) -> None:
    write_text(path, json.dumps(payload, indent=2) + "\n")
