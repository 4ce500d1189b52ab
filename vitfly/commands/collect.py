"""``vitfly collect``: fly the privileged expert and write trajectories to HDF5 (resumable)."""

from __future__ import annotations

import argparse

from vitfly.datamodules.schema import DEPTH_STORAGE
from vitfly.errors import VitflyError
from vitfly.sim.collect import CollectConfig, collect, load_collect_config
from vitfly.sim.engine import SIM_DTYPES, SIM_ENGINES
from vitfly.sim.physics import PHYSICS_CHOICES
from vitfly.sim.sensor_models import sensor_flag_values

_DEFAULTS = CollectConfig()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    keep = argparse.SUPPRESS  # unset flags leave the YAML's value (or the built-in default) alone
    parser.add_argument("--config", default=keep,
                        help="collect YAML: a path, or a shipped config's name, e.g. collect/spheres")
    parser.add_argument("--out", required=True, help="HDF5 dataset to create, or to resume if it exists")
    parser.add_argument(
        "--trajectories",
        type=int,
        default=keep,
        help=f"trajectories in the finished file (YAML, else {_DEFAULTS.trajectories})",
    )
    parser.add_argument(
        "--speeds",
        type=float,
        nargs=2,
        metavar=("MIN", "MAX"),
        default=keep,
        help=f"desired speed range in m/s, uniform per trajectory (YAML, else {_DEFAULTS.speeds[0]:g} "
        f"{_DEFAULTS.speeds[1]:g})",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=keep,
        help=f"master seed: trajectory k's scene and speed derive from (seed, k) (YAML, else {_DEFAULTS.seed})",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=keep,
        help=f"worker processes; the output does not depend on it (YAML, else {_DEFAULTS.workers})",
    )
    parser.add_argument(
        "--depth-compression",
        choices=tuple(DEPTH_STORAGE),
        default=keep,
        help="depth storage of a new file: none streams several times faster in training, gzip is ~2.8x smaller "
        f"(YAML, else {_DEFAULTS.depth_compression})",
    )
    parser.add_argument(
        "--log-every-tick",
        action="store_true",
        default=keep,
        help="write every control tick of each flight; by default only ticks with "
        f"{_DEFAULTS.log_x_range_m[0]:g} < x < {_DEFAULTS.log_x_range_m[1]:g} m, the original's window "
        "(YAML log_every_tick / log_x_range_m)",
    )
    parser.add_argument(
        "--physics",
        choices=PHYSICS_CHOICES,
        default=keep,
        help="rigid-body physics back end, stored with the dataset: pybullet (the reference), native (numpy, same "
        f"results to rounding) or auto, pybullet where installed (YAML, else {_DEFAULTS.physics})",
    )
    parser.add_argument("--sensor", nargs="+", metavar="MODEL|FIELD=VALUE", default=keep,
                        help="stereo sensor model on the rendered depth, e.g. --sensor d435 delay_ticks=1 "
                        "(vitfly.sim.sensor_models; YAML sensor: {model: d435, ...}; none: the ideal camera)")
    parser.add_argument(
        "--sim",
        choices=SIM_ENGINES,
        default=keep,
        help="simulator engine: numpy, or batched (torch, num_envs trajectories in lockstep, the native physics; "
        f"float64 on the CPU writes the numpy engine's data), stored with the dataset (YAML, else {_DEFAULTS.sim})",
    )
    parser.add_argument("--sim-device", default=keep,
                        help=f"the batched engine's device: cpu or cuda[:N] (YAML, else {_DEFAULTS.sim_device})")
    parser.add_argument("--sim-dtype", choices=SIM_DTYPES, default=keep,
                        help=f"the batched engine's precision: float64 (exact) or float32 (YAML, else "
                        f"{_DEFAULTS.sim_dtype})")
    parser.add_argument("--sim-compile", action="store_true", default=keep,
                        help="the batched engine's kernels through torch.compile (seconds once, then faster)")
    parser.add_argument("--num-envs", type=int, default=keep,
                        help=f"trajectories the batched engine flies in lockstep (YAML, else {_DEFAULTS.num_envs})")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    flags = ("trajectories", "speeds", "seed", "workers", "depth_compression", "log_every_tick", "physics", "sim",
             "sim_device", "sim_dtype", "sim_compile", "num_envs")
    overrides = {name: getattr(args, name, None) for name in flags}
    try:
        overrides["sensor"] = sensor_flag_values(getattr(args, "sensor", None))
    except ValueError as err:
        raise VitflyError(str(err)) from None
    config = load_collect_config(getattr(args, "config", None), overrides)
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
