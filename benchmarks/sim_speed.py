"""Simulator speed: real-time factor of an expert trial, depth frames per second, collection frames/s.

    .venv/bin/python benchmarks/sim_speed.py                 # all three, defaults below
    .venv/bin/python benchmarks/sim_speed.py --trials 10 --collect-trajectories 16 --json out.json

1. Real-time factor (simulated s / wall s) of one expert trial: 60 m at 5 m/s in spheres/medium,
   physics 240 Hz, expert and depth camera at 30 Hz (every frame rendered and kept, as `collect`
   does), one process, one BLAS/OpenMP thread. Median over ``--trials`` scenes.
2. Depth frames per second: the camera alone, re-rendering the poses of those trials.
3. Collection frames per second with ``--workers 2`` (also 1 for comparison): `vitfly collect`'s
   library call end to end, HDF5 writes included, into a temporary file.
"""

from __future__ import annotations

import os

# one core: must be set before numpy is imported
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from vitfly.sim import DepthCamera, ExpertPolicy, RolloutConfig, make_scene, run_episodes  # noqa: E402
from vitfly.sim.collect import CollectConfig, collect  # noqa: E402
from vitfly.sim.quadrotor import quat_wxyz_to_matrix  # noqa: E402


def trial_rtf(trials: int, speed: float) -> tuple[list[float], list[float], list]:
    """Real-time factors by wall clock and by this process's CPU time (robust to a busy machine)."""
    cfg = RolloutConfig(record_depth=True)
    wall_rtf, cpu_rtf, results = [], [], []
    run_episodes([make_scene("spheres", "medium", 999)], [speed], ExpertPolicy(), cfg)  # warm-up
    for i in range(trials):
        scene = make_scene("spheres", "medium", 20_000 + i)
        start, start_cpu = time.perf_counter(), time.process_time()
        res = run_episodes([scene], [speed], ExpertPolicy(), cfg)[0]
        wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
        wall_rtf.append(res.summary.duration_s / wall)
        cpu_rtf.append(res.summary.duration_s / cpu)
        results.append(res)
    return wall_rtf, cpu_rtf, results


def depth_fps(results) -> float:
    camera = DepthCamera()
    frames = 0
    start = time.perf_counter()
    for res in results:
        rot = quat_wxyz_to_matrix(res.log.quat)
        for pos, r in zip(res.log.position, rot, strict=True):
            camera.render(res.scene, pos, r)
            frames += 1
    return frames / (time.perf_counter() - start)


def collect_fps(workers: int, trajectories: int) -> tuple[float, int, float]:
    cfg = CollectConfig(trajectories=trajectories, workers=workers, seed=5, speeds=(3.0, 7.0))
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        summary = collect(cfg, Path(tmp) / "bench.h5", progress=False)
        wall = time.perf_counter() - start
    return summary.frames / wall, summary.frames, wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=5, help="expert trials for the real-time factor")
    parser.add_argument("--speed", type=float, default=5.0, help="desired speed of those trials, m/s")
    parser.add_argument("--collect-trajectories", type=int, default=8, help="trajectories per collect run")
    parser.add_argument("--skip-collect", action="store_true")
    parser.add_argument("--json", help="also write the numbers here")
    args = parser.parse_args()

    out: dict = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs"}
    wall_rtf, cpu_rtf, results = trial_rtf(args.trials, args.speed)
    out["rtf_wall_median"], out["rtf_wall_min"] = float(np.median(wall_rtf)), float(np.min(wall_rtf))
    out["rtf_cpu_median"] = float(np.median(cpu_rtf))
    out["expert_success"] = f"{sum(r.summary.success for r in results)}/{len(results)}"
    print(
        f"real-time factor, expert trial spheres/medium {args.speed:g} m/s, 30 Hz camera, 1 thread, "
        f"{args.trials} trials: wall clock median {out['rtf_wall_median']:.1f} (min {out['rtf_wall_min']:.1f}), "
        f"CPU time median {out['rtf_cpu_median']:.1f}"
    )
    out["depth_fps"] = depth_fps(results)
    print(f"depth frames per second (60x90, camera alone): {out['depth_fps']:.0f}")
    if not args.skip_collect:
        for workers in (1, 2):
            fps, frames, wall = collect_fps(workers, args.collect_trajectories)
            out[f"collect_fps_workers{workers}"] = fps
            print(
                f"collect, --workers {workers}: {fps:.0f} frames/s ({frames} frames in {wall:.1f} s, "
                f"{args.collect_trajectories} trajectories, HDF5 writes included)"
            )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
