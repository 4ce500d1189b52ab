"""``vitfly collect``: fly the privileged expert and write trajectories to HDF5 (resumable)."""

from __future__ import annotations

import argparse

from vitfly.sim.collect import collect, load_collect_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="collect YAML (e.g. configs/collect/spheres.yaml); flags override it")
    parser.add_argument("--out", required=True, help="HDF5 dataset to create, or to resume if it exists")
    parser.add_argument("--trajectories", type=int, help="number of trajectories in the finished file")
    parser.add_argument("--speeds", type=float, nargs=2, metavar=("MIN", "MAX"), help="desired speed range, m/s")
    parser.add_argument("--seed", type=int, help="master seed: trajectory k's scene and speed derive from (seed, k)")
    parser.add_argument("--workers", type=int, help="worker processes (the output does not depend on it)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    overrides = {
        "trajectories": args.trajectories,
        "speeds": list(args.speeds) if args.speeds else None,
        "seed": args.seed,
        "workers": args.workers,
    }
    config = load_collect_config(args.config, overrides)
    summary = collect(config, args.out, progress=not args.no_progress)
    total_ok = sum(s for s, _ in summary.success_by_speed.values())
    print(
        f"{summary.path}: {summary.trajectories} trajectories ({summary.new_trajectories} new), "
        f"{summary.frames} frames, expert success {total_ok}/{summary.trajectories}, {summary.wall_s:.1f} s"
    )
    print("speed (m/s)  trajectories  expert success")
    for speed, (ok, n) in summary.success_by_speed.items():
        print(f"{speed:>11.0f}  {n:>12d}  {ok / n:>13.0%}")
    return 0
