"""Success rates of the expert and of straight flight on one scene family, for calibrating presets.

DESIGN.md asks that spheres/medium discriminates: at 3 m/s the expert succeeds in roughly 80-90 %
of trials and straight flight in at most ~30 %. Success = reached x = 60 m with zero collisions
(vitfly's strict definition; the paper's counts a trial without collision).

    .venv/bin/python benchmarks/sim_calibration.py --env spheres --preset medium --speed 3 --trials 100

``expert`` is the default expert, which sees what Flightmare published: the 10 nearest objects within
10 m. ``expert-all-seeing`` is the same expert given every obstacle (vitfly's expert before it
followed the original).

Scene seeds are 10_000 + i (disjoint from small collect seeds); all trials of a policy fly in one
lockstep batch.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vitfly.sim import ENVS, ExpertPolicy, make_builtin_policy, make_scene, run_episodes
from vitfly.sim.expert import ALL_SEEING


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=ENVS, default="spheres")
    parser.add_argument("--preset", default="medium", help="easy, medium, hard (course also: single, gap, multi)")
    parser.add_argument("--speed", type=float, nargs="+", default=[3.0], help="desired speeds, m/s")
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument(
        "--policies", nargs="+", default=["expert", "straight"], help="expert, straight or expert-all-seeing"
    )
    args = parser.parse_args()
    scenes = [make_scene(args.env, args.preset, 10_000 + i) for i in range(args.trials)]
    print(f"{args.env}/{args.preset}, {args.trials} trials per row")
    print("policy             speed  success  95% CI        collisions/trial  end reasons                  wall s")
    for speed in args.speed:
        for name in args.policies:
            start = time.perf_counter()
            policy = ExpertPolicy(ALL_SEEING) if name == "expert-all-seeing" else make_builtin_policy(name)
            results = run_episodes(scenes, [speed] * len(scenes), policy)
            wall = time.perf_counter() - start
            ok = sum(r.summary.success for r in results)
            lo, hi = wilson_interval(ok, len(results))
            reasons: dict[str, int] = {}
            for r in results:
                reasons[r.summary.end_reason] = reasons.get(r.summary.end_reason, 0) + 1
            collisions = np.mean([r.summary.n_collisions for r in results])
            print(
                f"{name:<18} {speed:>5.1f}  {ok / len(results):>6.0%}   [{lo:.0%}, {hi:.0%}]   {collisions:>16.2f}  "
                f"{', '.join(f'{k} {v}' for k, v in sorted(reasons.items())):<27}  {wall:>6.1f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
