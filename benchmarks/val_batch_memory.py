"""Validation on a CPU: peak memory and frames/s of one validation call per batch size, each in a fresh process.

What ``data.cpu_val_batch_size`` is chosen by (docs/training.md#validation-batches-and-where-an-epochs-time-goes).
Each sample is one new process: the network as the ``paper`` arm trains it (eager, unpadded), in eval mode
without autograd (as Lightning validates), on a synthetic batch of B trajectories of ``--steps`` frames (uint8
depth turned into [0, 1] floats as the datamodule does), ``--calls`` forward calls after one warm-up call, with
vitfly's allocator setting (``vitfly.host_memory``). Reported per batch size, medians over ``--repeats``
samples (sizes alternating, so drift on a shared machine falls on all): the process's peak resident memory
(``getrusage``), that peak less the process's before the first call (the call's own share), and frames/s.

    python benchmarks/val_batch_memory.py --model unet_lstm --batches 1 4 16 --repeats 2 --threads 1
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH_DIR))
import train_speed  # noqa: E402  (benchmarks/ is not a package)

GB = 1e9


def rss_peak_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB


def measure(model: str, batch: int, steps: int, calls: int, threads: int) -> dict:
    """One validation call's memory and speed in this (fresh) process."""
    import torch

    from vitfly.datamodules.dataset import depth_to_unit_float
    from vitfly.host_memory import keep_freed_memory
    from vitfly.zoo.policy import create_policy

    keep_freed_memory()
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    module = create_policy(model, **train_speed.arm_settings("paper", model, "unpadded")["policy_kwargs"]).eval()
    data = depth_to_unit_float(train_speed.synthetic_batch(batch, steps, "cpu"))
    before = rss_peak_bytes()
    times = []
    with torch.inference_mode():
        for _ in range(calls + 1):  # the first call warms up
            start = time.perf_counter()
            module(data["depth"], data["desired_speed"], data["quat"])
            times.append(time.perf_counter() - start)
    peak = rss_peak_bytes()
    return {"peak_gb": peak / GB, "call_gb": (peak - before) / GB,
            "fps": batch * steps / statistics.median(times[1:])}


def sample(args: argparse.Namespace, batch: int) -> dict:
    spec = {"model": args.model, "batch": batch, "steps": args.steps, "calls": args.calls, "threads": args.threads}
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(train_speed.ROOT)})
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise SystemExit(f"batch {batch}: the measuring process failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--model", default="unet_lstm", choices=train_speed.ALL_MODELS)
    p.add_argument("--batches", type=int, nargs="+", default=[1, 4, 16], help="trajectories per validation call")
    p.add_argument("--steps", type=int, default=train_speed.MEAN_FLIGHT_STEPS, help="frames per trajectory")
    p.add_argument("--calls", type=int, default=2, help="timed calls per sample, after one warm-up call")
    p.add_argument("--repeats", type=int, default=2, help="samples per batch size, each a fresh process")
    p.add_argument("--threads", type=int, default=1, help="torch threads (a CPU run of the paper arm: 1)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print("RESULT " + json.dumps(measure(**json.loads(args.worker))), flush=True)
        return
    results: dict[int, list[dict]] = {b: [] for b in args.batches}
    for r in range(args.repeats):
        for b in args.batches if r % 2 == 0 else reversed(args.batches):
            results[b].append(sample(args, b))
            print(f"  batch {b}: {results[b][-1]}", file=sys.stderr, flush=True)
    print(f"{args.model}, paper arm, {args.steps} frames a trajectory, {args.threads} thread(s), "
          f"medians of {args.repeats} processes each\n")
    print("| trajectories a call | peak memory (GB) | of it the call's (GB) | frames/s (min-max) |")
    print("|---:|---:|---:|---:|")
    for b, rows in results.items():
        fps = [row["fps"] for row in rows]
        print(f"| {b} | {statistics.median(row['peak_gb'] for row in rows):.2f} "
              f"| {statistics.median(row['call_gb'] for row in rows):.2f} "
              f"| {statistics.median(fps):,.0f} ({min(fps):,.0f}-{max(fps):,.0f}) |")


if __name__ == "__main__":
    main()
