"""Closed loop at scale: a learned policy's evaluation trials per minute and the expert dataset's collection
time, the batched engine on ``--device`` beside the numpy engine, in one run.

    .venv/bin/python benchmarks/sim_scale.py                                  # CPU: 96 trials, 32 flights
    python3 benchmarks/sim_scale.py --device cuda --trials 10000 --num-envs 4096 --flights 588 --warm \\
        --json $OUT/sim_scale.json                                            # one H100 (issue 23)

1. Evaluation: ``vitfly evaluate``'s library call (``vitfly.eval.sweep.run_sweep``) flies ``--policy``
   (default the shipped ViT+LSTM) in spheres/medium at 3, 5 and 7 m/s, ``--trials`` trials in all, with
   ``--sim batched --sim-device DEVICE --device DEVICE`` (the policy on the engine's card, observations never
   leave it), ``--num-envs`` scenes in lockstep, ``--dtype`` (float32 by default), compiled; before it the
   numpy engine flies the first ``--numpy-trials`` of those trials (the policy on the same device, 16 lockstep
   scenes, one process). Trials per minute of each; the batched engine's seconds include its compiles, as a
   user's first sweep in a process would (a fresh machine also fills inductor's disk cache then).
2. Collection: ``vitfly collect``'s library call writes ``--flights`` expert trajectories (spheres/medium,
   3-7 m/s, seed 0, native physics: the ``paper`` preset's data for 588) with the batched engine, all in one
   lockstep batch, ``--collect-dtype`` (float64 by default: the numpy engine's data), compiled; before it the
   numpy engine collects ``--numpy-flights`` (one worker). Seconds, frames per second.

``--warm`` runs the batched engine a second time in each part, in the same process (row ``batched_warm``):
the rate of every sweep after a process's first, its kernels compiled. ``--json`` is written after every
measurement, so a run cut short keeps what it measured.

Issue 23's targets on one H100: 10,000 ViT+LSTM trials in at most 2 minutes; the 588-flight dataset in at
most 10 s. On a CPU the policy's network dominates a learned policy's tick (see docs/performance.md).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path

import torch

from vitfly.eval.config import SweepConfig
from vitfly.eval.sweep import run_sweep, trials_per_minute
from vitfly.sim.collect import CollectConfig, collect

SPEEDS = [3.0, 5.0, 7.0]


def evaluation(args, workdir: Path, engine: str, trials: int, run: str) -> dict:
    """Fly ``trials`` trials (spread over the three speeds) with one engine into ``workdir/run``; trials per
    minute."""
    batched = engine == "batched"
    cfg = SweepConfig(policy=args.policy, name=engine, env=["spheres"], speeds=SPEEDS,
                      trials=math.ceil(trials / len(SPEEDS)), seed=args.seed, out=str(workdir / run),
                      num_envs=args.num_envs if batched else 16, device=args.device, threads=args.threads,
                      sim=engine, sim_device=args.device if batched else "cpu",
                      sim_dtype=args.dtype if batched else "float64", sim_compile=batched and not args.eager,
                      timeout_s=args.timeout, gif=False, plots=False).validate()
    start = time.perf_counter()
    outcome = run_sweep(cfg, progress=False)
    wall = time.perf_counter() - start  # with the policy's loading, as a user's sweep
    success = sum(r.success_paper for r in outcome.records) / max(1, len(outcome.records))
    return {"engine": engine, "trials": outcome.flown, "wall_s": wall, "flying_s": outcome.wall_s,
            "trials_per_min": trials_per_minute(outcome.flown, wall), "success": success,
            "num_envs": cfg.num_envs, "sim_device": cfg.sim_device, "dtype": cfg.sim_dtype,
            "compile": cfg.sim_compile}


def collection(args, workdir: Path, engine: str, flights: int, run: str) -> dict:
    """Collect ``flights`` expert trajectories with one engine into ``workdir/run.h5``; seconds and frames
    per second."""
    batched = engine == "batched"
    cfg = CollectConfig(trajectories=flights, physics="native", seed=0, sim=engine,
                        sim_device=args.device if batched else "cpu",
                        sim_dtype=args.collect_dtype if batched else "float64",
                        sim_compile=batched and not args.eager, num_envs=flights if batched else 8)
    start = time.perf_counter()
    summary = collect(cfg, workdir / f"{run}.h5", progress=False)
    wall = time.perf_counter() - start
    return {"engine": engine, "flights": summary.trajectories, "frames": summary.frames, "wall_s": wall,
            "frames_per_s": summary.frames / wall, "sim_device": cfg.sim_device, "dtype": cfg.sim_dtype,
            "compile": cfg.sim_compile}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="the batched engine's and the policy's device")
    parser.add_argument("--policy", default="pretrained:vit_lstm", help="as `vitfly evaluate --policy` takes it")
    parser.add_argument("--trials", type=int, default=96, help="evaluation trials with the batched engine")
    parser.add_argument("--numpy-trials", type=int, default=48, help="evaluation trials with the numpy engine")
    parser.add_argument("--num-envs", type=int, default=48, help="the batched engine's lockstep scenes")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                        help="the batched engine's precision in the evaluation")
    parser.add_argument("--flights", type=int, default=32, help="expert trajectories collected, batched engine")
    parser.add_argument("--numpy-flights", type=int, default=8, help="expert trajectories, numpy engine")
    parser.add_argument("--collect-dtype", choices=("float32", "float64"), default="float64")
    parser.add_argument("--eager", action="store_true", help="the batched engine without torch.compile")
    parser.add_argument("--warm", action="store_true",
                        help="the batched engine once more in the same process (compiled kernels reused): "
                             "the rate of every sweep after a process's first")
    parser.add_argument("--seed", type=int, default=2323, help="the evaluation's sweep seed")
    parser.add_argument("--timeout", type=float, default=None,
                        help="seconds per evaluation trial (default: the sweep's, longer for slower flights); "
                             "short ones make a quick check of the script, not a measurement")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--skip-eval", action="store_true")
    parser.add_argument("--skip-collect", action="store_true")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    out: dict = {"device": args.device, "policy": args.policy,
                 "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda") else None,
                 "cpu_count": os.cpu_count()}
    def save() -> None:  # after every measurement: a run cut short by a timeout keeps what it measured
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(out, indent=2))

    def part(name: str, measure, workdir: Path, counts: dict, rate: str, line) -> None:
        """Both engines, the short numpy reference first (a timeout in the long run keeps it), then their ratio;
        with ``--warm`` the batched engine again, its kernels compiled (row ``batched_warm``)."""
        rows = out[name] = {}
        runs = [("numpy", "numpy"), ("batched", "batched")] + ([("batched", "batched_warm")] if args.warm else [])
        for engine, run in runs:
            row = rows[run] = measure(args, workdir, engine, counts[engine], run)
            print(f"   {run:12s} {line(row)} (engine on {row['sim_device']}, {row['dtype']}"
                  f"{', compiled' if row['compile'] else ''})", flush=True)
            save()
            if engine == "batched":
                key = "ratio" if run == "batched" else "ratio_warm"
                rows[key] = row[rate] / rows["numpy"][rate]
                print(f"   {run} / numpy: {rows[key]:.2f}x", flush=True)
                save()

    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        if not args.skip_eval:
            print(f"1. evaluation, {args.policy}, spheres/medium at 3/5/7 m/s", flush=True)
            part("evaluation", evaluation, workdir, {"numpy": args.numpy_trials, "batched": args.trials},
                 "trials_per_min",
                 lambda r: (f"{r['trials']:6d} trials in {r['wall_s']:7.1f} s: {r['trials_per_min']:8.1f} trials/min "
                            f"(success {r['success']:.0%}; {r['num_envs']} in lockstep)"))
        if not args.skip_collect:
            print("2. collection, expert, spheres/medium at 3-7 m/s (HDF5 writes included)", flush=True)
            part("collection", collection, workdir, {"numpy": args.numpy_flights, "batched": args.flights},
                 "frames_per_s",
                 lambda r: (f"{r['flights']:5d} flights ({r['frames']} frames) in {r['wall_s']:6.1f} s: "
                            f"{r['frames_per_s']:8.0f} frames/s"))


if __name__ == "__main__":
    main()
