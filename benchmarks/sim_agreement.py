"""Do float32 flights of the batched engine end as float64 flights do? Outcome agreement of a seeded sweep.

    .venv/bin/python benchmarks/sim_agreement.py --trials 20 --speeds 3 7               # CPU, the expert
    python3 benchmarks/sim_agreement.py --device cuda --num-envs 1024 --trials 200 \\
        --policies expert pretrained:vit_lstm --json $OUT/sim_agreement.json         # a GPU (issue 23)

Flies every ``--policies`` entry through ``vitfly evaluate --sim batched`` twice on the same scenes (sweep
``--seed``), once with ``--sim-dtype float64`` and once with ``float32`` on ``--device`` (the learned policy
on the same device), into ``--out`` (labels ``<policy>-float64`` and ``<policy>-float32``; an interrupted run
resumes there). It then pairs the trials by (env, speed, trial) and reports, per policy, the share of
trials whose outcome is the same in both precisions: success (the paper's: no collision), goal reached and
the number of collisions all equal. Beside it the share whose *ending* is the same: success and the end
reason (goal, timeout, out of bounds), collision counts aside, which is what success rates and the paper's
tables rest on. The 95 % intervals are Clopper-Pearson on the agreeing counts. Issue 23's target: at least
98 % agreement on a GPU in float32.

Rounding differs at 1e-7 relative in float32, and a closed loop amplifies it near a decision (a sphere
grazed or not), so some disagreement is expected; what matters is that it is rare and not one-sided.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

from scipy.stats import binomtest

from vitfly.eval.records import TrialRecord, read_sweep

DTYPES = ("float64", "float32")


def outcome(rec: TrialRecord) -> tuple[bool, bool, int]:
    """What must agree: the paper's success, goal reached, collision count."""
    return rec.success_paper, rec.reached_goal, int(rec.metrics["collisions"])


def ending(rec: TrialRecord) -> tuple[bool, str]:
    """How a trial ended: the paper's success and the end reason (a graze counted twice instead of once, or
    a collision more in a trial that collides anyway, leaves it alone)."""
    return rec.success_paper, rec.end_reason


def _share(agree: int, pairs: int) -> tuple[float, list[float]]:
    ci = binomtest(agree, pairs).proportion_ci(0.95, method="exact")
    return agree / pairs, [ci.low, ci.high]


def agreement(records: list[TrialRecord], label: str) -> dict:
    """Pair ``label``-float64 with ``label``-float32 trials by (env, speed, trial); agreement and its interval.

    Also counts the direction of the disagreements in success (float32 better / worse), since a one-sided
    shift would bias a study flown in float32 even at a high agreement."""
    runs = {dtype: {(r.env, r.speed, r.trial): r for r in records if r.policy == f"{label}-{dtype}"}
            for dtype in DTYPES}
    keys = sorted(set(runs["float64"]) & set(runs["float32"]))
    if not keys:
        raise SystemExit(f"no trials of {label} flown in both float64 and float32")
    same = sum(outcome(runs["float64"][k]) == outcome(runs["float32"][k]) for k in keys)
    same_end = sum(ending(runs["float64"][k]) == ending(runs["float32"][k]) for k in keys)
    flips = Counter()
    for k in keys:
        a, b = runs["float64"][k].success_paper, runs["float32"][k].success_paper
        if a != b:
            flips["float32 succeeds, float64 not" if b else "float64 succeeds, float32 not"] += 1
    (share, ci), (share_end, ci_end) = _share(same, len(keys)), _share(same_end, len(keys))
    return {"policy": label, "pairs": len(keys), "agree": same, "agreement": share, "ci95": ci,
            "agree_end": same_end, "agreement_end": share_end, "ci95_end": ci_end, "success_flips": dict(flips),
            "success_float64": sum(runs["float64"][k].success_paper for k in keys) / len(keys),
            "success_float32": sum(runs["float32"][k].success_paper for k in keys) / len(keys)}


def fly(policy: str, dtype: str, args: argparse.Namespace) -> None:
    label = f"{policy.split(':')[-1]}-{dtype}"
    cmd = [sys.executable, "-c", "from vitfly.cli import main; main()", "evaluate", "--policy", policy,
           "--name", label, "--out", str(args.out), "--seed", str(args.seed), "--env", *args.env,
           "--speeds", *[str(s) for s in args.speeds], "--trials", str(args.trials),
           "--num-envs", str(args.num_envs), "--workers", "1", "--threads", str(args.threads),
           "--sim", "batched", "--sim-dtype", dtype, "--sim-device", args.device, "--device", args.device,
           "--no-gif", "--no-plots"]
    if args.compile:
        cmd.append("--sim-compile")
    print("$", " ".join(cmd[3:]), flush=True)
    subprocess.run(cmd, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policies", nargs="+", default=["expert"],
                        help="policies as `vitfly evaluate --policy` takes them (default: expert)")
    parser.add_argument("--env", nargs="+", default=["spheres"])
    parser.add_argument("--speeds", nargs="+", type=float, default=[3.0, 5.0, 7.0])
    parser.add_argument("--trials", type=int, default=20, help="trials per (env, speed)")
    parser.add_argument("--seed", type=int, default=3030, help="sweep seed (scenes)")
    parser.add_argument("--device", default="cpu", help="the engine's and the policy's device: cpu or cuda")
    parser.add_argument("--num-envs", type=int, default=64, help="scenes in lockstep")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--compile", action="store_true", help="--sim-compile on both runs")
    parser.add_argument("--out", type=Path, default=Path("runs/sim_agreement"))
    parser.add_argument("--json", type=Path, default=None, help="write the results here too")
    args = parser.parse_args()
    for policy in args.policies:
        for dtype in DTYPES:
            fly(policy, dtype, args)
    records = read_sweep(args.out)
    rows = [agreement(records, p.split(":")[-1]) for p in args.policies]
    for r in rows:
        print(f"{r['policy']}: {r['agree']}/{r['pairs']} trials end alike in float32 and float64 "
              f"({100 * r['agreement']:.1f} %, 95 % CI {100 * r['ci95'][0]:.1f}-{100 * r['ci95'][1]:.1f}); "
              f"success and end reason alike in {r['agree_end']} ({100 * r['agreement_end']:.1f} %, 95 % CI "
              f"{100 * r['ci95_end'][0]:.1f}-{100 * r['ci95_end'][1]:.1f}); "
              f"success {100 * r['success_float64']:.1f} % (float64) vs {100 * r['success_float32']:.1f} % "
              f"(float32); flips {r['success_flips'] or 'none'}")
    if args.json:
        args.json.write_text(json.dumps({"device": args.device, "seed": args.seed, "results": rows}, indent=2))


if __name__ == "__main__":
    main()
