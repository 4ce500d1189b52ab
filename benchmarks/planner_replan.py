"""Replan compute time of the modular baselines (vitfly.planners) on this CPU, flown closed-loop.

    PYTHONPATH=. python benchmarks/planner_replan.py fastplanner convex --episodes 4 --speed 3

Flies ``--episodes`` spheres/medium scenes (seeds 0..n-1) in lockstep per planner and prints, per planner,
the outcomes and the mean / 95th percentile of every replan's measured compute time (ms).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vitfly.planners import ModularPolicy, load_planner_options
from vitfly.sim import make_scene, run_episodes
from vitfly.sim.rollout import RolloutConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("planners", nargs="+")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--speed", type=float, default=3.0)
    args = parser.parse_args()
    for name in args.planners:
        policy = ModularPolicy(load_planner_options(name))
        scenes = [make_scene("spheres", "medium", seed=s) for s in range(args.episodes)]
        start = time.perf_counter()
        results = run_episodes(scenes, [args.speed] * len(scenes), policy, RolloutConfig(physics="native"))
        wall = time.perf_counter() - start
        ms = np.asarray(policy.replan_ms)
        ok = sum(r.summary.success for r in results)
        print(f"{name}: {ok}/{len(results)} success, {len(ms)} replans, replan mean {ms.mean():.1f} ms, "
              f"p95 {np.percentile(ms, 95):.1f} ms, max {ms.max():.1f} ms; wall {wall:.0f} s")


if __name__ == "__main__":
    main()
