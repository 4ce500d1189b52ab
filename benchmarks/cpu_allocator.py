"""CPU training with glibc's allocator as it comes against vitfly's setting (``vitfly.host_memory``), side by side.

Each sample is one fresh process (``train_speed.py``'s worker: the arm's training step on a synthetic
batch of ``--steps`` frames per trajectory, as ``benchmarks/train_speed.py --arm`` measures it), run once with
``VITFLY_MALLOC=default`` (glibc's thresholds: every large activation a fresh ``mmap``) and once with vitfly's
(freed blocks kept for the next step), alternating A B B A so that drift on a shared machine falls on both.
Per model: median frames/s of each, the ratio pair by pair (median, min-max), and the share of the process's
CPU time spent in the kernel (``getrusage`` of the finished child: page faults show up there).

    python benchmarks/cpu_allocator.py --arm paper --models unet_lstm convnet --threads 1 --repeats 3
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH_DIR))
import train_speed  # noqa: E402  (benchmarks/ is not a package)

SETTINGS = {"glibc": "default", "vitfly": None}  # label -> VITFLY_MALLOC


def one_sample(spec: dict, setting: str) -> dict:
    """frames/s of one fresh worker process under ``setting``, with its CPU seconds in user and kernel mode."""
    os.environ.pop("VITFLY_MALLOC", None)  # run_sample hands this process's environment to the worker
    if SETTINGS[setting] is not None:
        os.environ["VITFLY_MALLOC"] = SETTINGS[setting]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = train_speed.run_sample(train_speed.ROOT, dict(spec))
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    user, kernel = after.ru_utime - before.ru_utime, after.ru_stime - before.ru_stime
    return {"fps": result["fps"], "kernel_share": kernel / max(user + kernel, 1e-9)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arm", choices=tuple(train_speed.ARMS), default="paper",
                        help="train each model as this arm's preset does (eager, unpadded: the CPU's path)")
    parser.add_argument("--models", nargs="+", default=["unet_lstm"], choices=train_speed.ALL_MODELS)
    parser.add_argument("--batch", type=int, default=None, help="trajectories per batch (default: the arm's)")
    parser.add_argument("--steps", type=int, default=train_speed.MEAN_FLIGHT_STEPS, help="frames per trajectory")
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="fp32")
    parser.add_argument("--iters", type=int, default=8, help="timed steps per sample")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps first")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--repeats", type=int, default=2, help="pairs of samples per model")
    args = parser.parse_args(argv)

    rows = []
    for model in args.models:
        arm = train_speed.arm_settings(args.arm, model, "unpadded")
        spec = {"kind": "arm", "model": model, "policy_kwargs": arm["policy_kwargs"],
                "batch": args.batch or arm["batch"], "steps": args.steps, "bucket": None,
                "precision": args.precision, "iters": args.iters, "warmup": args.warmup, "device": "cpu",
                "threads": args.threads, "profile": False}  # fmt: skip
        samples: dict[str, list[dict]] = {s: [] for s in SETTINGS}
        for r in range(args.repeats):
            for setting in SETTINGS if r % 2 == 0 else reversed(SETTINGS):
                samples[setting].append(one_sample(spec, setting))
                print(f"  [{r}] {model} {setting}: {samples[setting][-1]['fps']:,.1f} frames/s, "
                      f"{samples[setting][-1]['kernel_share']:.0%} of CPU time in the kernel", flush=True)
        ratios = [v["fps"] / g["fps"] for v, g in zip(samples["vitfly"], samples["glibc"], strict=True)]
        rows.append((model, spec["batch"], samples, ratios))

    threads = args.threads or "torch's default"
    print(f"\ncpu, {threads} threads, the {args.arm} arm's step (eager, unpadded, {args.precision}), "
          f"{args.steps} frames per trajectory; medians of {args.repeats} samples each")
    print("| model | batch | glibc frames/s | vitfly frames/s | ratio (min-max) | kernel share glibc / vitfly |")
    print("|---|---|---|---|---|---|")
    for model, batch, samples, ratios in rows:
        fps = {s: statistics.median(x["fps"] for x in samples[s]) for s in SETTINGS}
        kernel = {s: statistics.median(x["kernel_share"] for x in samples[s]) for s in SETTINGS}
        print(f"| {model} | {batch} | {fps['glibc']:,.0f} | {fps['vitfly']:,.0f} | "
              f"{statistics.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f}) | "
              f"{kernel['glibc']:.0%} / {kernel['vitfly']:.0%} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
