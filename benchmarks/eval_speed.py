"""Closed-loop evaluation speed: trials per minute and real-time factor (RTF) per core.

Flies ``--trials`` trials per case through ``vitfly.eval.sweep.fly_batch`` (the code behind
``vitfly evaluate``: rendering, physics, the policy, metrics and the trials.jsonl write) in one
process with one torch / ONNX Runtime thread, i.e. on one core. The policy is built first and not
timed (loading, and for ONNX Runtime the export and its check against eager, a few seconds once
per process). RTF = simulated flight seconds / wall-clock seconds; trials end at the goal or at
``--timeout`` simulated seconds. Learned policies are randomly initialised zoo networks: the cost
per tick does not depend on the weights, but an untrained network ends its trials early (out of the
box), so compare RTF, or give trained checkpoints with ``--checkpoint convnet=runs/quickstart/...``.

    .venv/bin/python benchmarks/eval_speed.py --trials 16 --num-envs 1 16 --out runs/eval_speed.json

Target (issue 5): ViT+LSTM with 16 lockstep scenes at RTF >= 10 per core.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch
from rich.console import Console
from rich.table import Table

from vitfly.eval import records
from vitfly.eval.config import SweepConfig
from vitfly.eval.policy_source import PolicySource
from vitfly.eval.sweep import fly_batch, make_batches, plan_trials, sweep_identity
from vitfly.zoo import create_model, save_checkpoint

CASES = [("expert", "-"), ("convnet", "eager"), ("convnet", "onnxruntime"), ("vit_lstm", "eager"),
         ("vit_lstm", "onnxruntime")]


def fly(policy: str, backend: str, num_envs: int, args, workdir: Path) -> dict:
    if policy in ("expert", "straight"):
        spec, label = policy, policy
    elif policy in args.checkpoint:
        spec, label = args.checkpoint[policy], policy
    else:
        spec = str(workdir / f"{policy}.ckpt")
        if not Path(spec).exists():
            torch.manual_seed(0)
            save_checkpoint(create_model(policy), policy, True, spec)
        label = policy
    out = workdir / f"{label}-{backend}-{num_envs}"
    cfg = SweepConfig(policy=spec, name=label, env=[args.env], speeds=[args.speed], trials=args.trials,
                      seed=args.seed, out=str(out), num_envs=num_envs, workers=1, threads=1,
                      backend=backend if backend != "-" else "eager", timeout_s=args.timeout, gif=False, plots=False)
    built = PolicySource(cfg.policy, None, cfg.backend, "cpu", 1).build()
    out_file = out / records.TRIALS_FILE
    identity = sweep_identity(cfg)  # what the records are keyed by (hashes the weights: not timed)
    t0 = time.perf_counter()
    for batch in make_batches(plan_trials(cfg), num_envs):
        fly_batch(batch, built, cfg, out_file, identity=identity)
    wall = time.perf_counter() - t0
    flown = records.read_records(out_file)
    sim_s = sum(float(r.path["time"][-1]) + 1.0 / 30.0 for r in flown)
    return {"policy": policy, "backend": backend, "num_envs": num_envs, "trials": len(flown), "sim_s": sim_s,
            "wall_s": wall, "trials_per_min": 60.0 * len(flown) / wall, "rtf_per_core": sim_s / wall,
            "policy_ms_per_env_tick": sum(r.metrics["processing_ms"] for r in flown) / len(flown)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=16, help="trials per case")
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--cases", nargs="+", default=[f"{p}:{b}" for p, b in CASES],
                        help="policy:backend pairs, e.g. vit_lstm:onnxruntime expert:-")
    parser.add_argument("--env", default="spheres")
    parser.add_argument("--speed", type=float, default=5.0, help="desired speed, m/s")
    parser.add_argument("--timeout", type=float, default=6.0, help="simulated seconds per trial at most")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--checkpoint", nargs="+", default=[], metavar="MODEL=PATH",
                        help="fly these trained checkpoints instead of random weights")
    parser.add_argument("--out", help="write every measurement as JSON")
    args = parser.parse_args(argv)
    args.checkpoint = dict(item.split("=", 1) for item in args.checkpoint)
    torch.set_num_threads(1)

    results = []
    with tempfile.TemporaryDirectory(prefix="vitfly-eval-speed-") as tmp:
        for case in args.cases:
            policy, backend = case.split(":")
            for n in args.num_envs:
                results.append(fly(policy, backend, n, args, Path(tmp)))
                r = results[-1]
                print(f"{policy:9s} {backend:12s} num_envs={n:3d}: {r['trials_per_min']:6.1f} trials/min, "
                      f"RTF/core {r['rtf_per_core']:5.1f}", flush=True)

    table = Table(title=f"closed-loop evaluation speed, one core ({args.env}, {args.speed:g} m/s, "
                        f"<= {args.timeout:g} s per trial)")
    for col in ("policy", "back end", "num-envs", "trials", "trials/min", "RTF per core", "policy ms/env/tick"):
        table.add_column(col, justify="left" if col in ("policy", "back end") else "right")
    for r in results:
        table.add_row(r["policy"], r["backend"], str(r["num_envs"]), str(r["trials"]), f"{r['trials_per_min']:.1f}",
                      f"{r['rtf_per_core']:.1f}", f"{r['policy_ms_per_env_tick']:.2f}")
    Console(width=max(Console().width, 120)).print(table)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"args": vars(args), "results": results}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
