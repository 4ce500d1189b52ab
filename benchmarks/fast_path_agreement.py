"""Do the fast inference paths fly the eager float32 network's commands? Every model, whole recorded flights.

Flies the privileged expert through ``--envs`` x ``--seeds`` x ``--speeds`` scenes with every depth frame kept
(``vitfly.eval.agreement.record_flights``), then replays each flight tick by tick through every model (seeded
random weights, or ``--checkpoint MODEL=PATH``) on the eager float32 path and on each fast back end, recurrent
state carried from the first tick, and compares the world-frame commands (m/s, after clip / normalise / scale
and the take-off ramp) over every tick. A back end passes when its largest per-component difference stays
within ``--tolerance`` m/s (default ``vitfly.eval.agreement.COMMAND_TOLERANCE_MPS`` per back end).

    .venv/bin/python benchmarks/fast_path_agreement.py --out runs/agreement.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch
from rich.console import Console
from rich.table import Table

from vitfly.deploy.onnx import OnnxPolicyRunner
from vitfly.eval.agreement import (
    COMMAND_TOLERANCE_MPS,
    calibration_depth,
    compare_commands,
    record_flights,
    replay_commands,
)
from vitfly.eval.latency import needs_calibration
from vitfly.eval.learned_policy import LearnedPolicy
from vitfly.eval.original_networks import ORIGINAL_NETWORKS
from vitfly.eval.policy_source import PolicySource
from vitfly.zoo import create_model


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(ORIGINAL_NETWORKS))
    parser.add_argument("--backends", nargs="+", default=["onnxruntime", "onnxruntime-int8"],
                        choices=list(COMMAND_TOLERANCE_MPS))  # fmt: skip
    parser.add_argument("--checkpoint", nargs="*", default=[], metavar="MODEL=PATH",
                        help="fly these weights instead of seeded random ones: a checkpoint path or "
                             "pretrained:NAME (weights/)")  # fmt: skip
    parser.add_argument("--envs", nargs="+", default=["spheres", "trees"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--speeds", type=float, nargs="+", default=[3.0, 5.0, 7.0])
    parser.add_argument("--timeout", type=float, default=None, help="cut flights after this many s")
    parser.add_argument("--tolerance", type=float, default=None, help="m/s, for every fast back end")
    parser.add_argument("--out", default=None, help="JSON with every comparison")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    checkpoints = dict(item.split("=", 1) for item in args.checkpoint)

    t0 = time.perf_counter()
    flights = [f for env in args.envs for f in record_flights(env, args.seeds, args.speeds, timeout_s=args.timeout)]
    ticks = sum(len(f) for f in flights)
    print(f"recorded {len(flights)} flights, {ticks} ticks, in {time.perf_counter() - t0:.0f} s", file=sys.stderr)

    table = Table(title=f"Commands of the fast paths vs eager float32: {len(flights)} recorded flights "
                        f"({', '.join(args.envs)}; {', '.join(f'{s:g}' for s in args.speeds)} m/s), {ticks} ticks")
    for column in ("Model", "Weights", "Backend", "max |d| m/s", "p99 m/s", "mean m/s", "max angle deg", "Tolerance",
                   "Within"):  # fmt: skip
        table.add_column(column, justify="left" if column in ("Model", "Weights", "Backend") else "right")
    rows = []
    for model in args.models:
        torch.manual_seed(0)
        net = PolicySource(checkpoints[model]).load_network() if model in checkpoints else create_model(model)
        net = net.eval()
        weights = checkpoints.get(model, "random, seed 0")
        reference = replay_commands(LearnedPolicy(net), flights)
        for backend in args.backends:
            precision = "int8" if backend == "onnxruntime-int8" else "fp32"
            # the ViTs' int8 convolutions are calibrated on other scenes than the flights compared here
            calibration = calibration_depth() if precision == "int8" and needs_calibration(net) else None
            runner = OnnxPolicyRunner(net, precision=precision, calibration_depth=calibration)
            policy = LearnedPolicy(net, step_fn=runner)
            agreement = compare_commands(reference, replay_commands(policy, flights))
            tolerance = COMMAND_TOLERANCE_MPS[backend] if args.tolerance is None else args.tolerance
            within = agreement.within(tolerance)
            rows.append({"model": model, "weights": weights, "backend": backend, "tolerance_mps": tolerance,
                         "within": within, **agreement.to_dict()})  # fmt: skip
            table.add_row(model, weights, backend, f"{agreement.max_abs_mps:.2e}", f"{agreement.p99_abs_mps:.2e}",
                          f"{agreement.mean_abs_mps:.2e}", f"{agreement.max_angle_deg:.3f}", f"{tolerance:g}",
                          "yes" if within else "NO")  # fmt: skip
    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 150))
    console.print(table)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out + ".tmp", "w") as f:
            json.dump({"settings": vars(args), "flights": len(flights), "ticks": ticks, "rows": rows}, f, indent=2)
        os.replace(args.out + ".tmp", args.out)
    return 0 if all(r["within"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
