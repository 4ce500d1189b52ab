"""How often a paired interval decides between two networks that are equal in expectation, when each training
draw of a network flies differently: one draw per network, and several compared by their mean
(``vitfly.eval.paired``, two-level bootstrap, with and without spreading the draws, and with a network trained
once borrowing the pooled spread of the study's other networks' draws).

A simulated study: ``--scenes`` scenes, each with its own difficulty (normal on the logit scale, sd 1, shared by
every policy), and networks whose every training draw gets its own skill (normal on the logit scale, with the sd
that ``--draw-sd-points`` sets near 50 % success: 4 x points / 100). Both networks have the same expected skill, so
every decided interval is a false verdict; a calibrated 95 % interval decides about 5 % of the time. The pooled
spread comes from the compared networks' own draws (where they have several) and from ``--pool-draws`` more
networks of the same study (the laptop preset: ConvNet's five draws, LSTMnet's, ViT's and ViT+LSTM's three).

    python scripts/paired_calibration.py                      # the table in docs/evaluation.md
    python scripts/paired_calibration.py --draw-sd-points 0   # no training noise: the scenes' alone
    python scripts/paired_calibration.py --scenes 500 --draw-sd-points 3 --difference-points 5 \
        --draws 1x1 3x1 --pool-draws 3 3                      # the power of the paper preset's verdicts

With ``--difference-points D`` the first network's expected success is D points higher (over the scenes'
difficulties), and the table gives the power: the share of studies whose interval decides it better.
"""

from __future__ import annotations

import argparse
import re
import sys

import numpy as np

from vitfly.eval.paired import pooled_draw_variance, two_level_bootstrap_interval


def logit_lead(points: float) -> float:
    """The skill (logit) that raises success by ``points`` in expectation over the scenes' difficulties (N(0, 1)):
    E[sigmoid(lead - d) - sigmoid(-d)] = points / 100, by Gauss-Hermite quadrature and root-finding."""
    from scipy.optimize import brentq

    d, w = np.polynomial.hermite_e.hermegauss(64)
    w = w / w.sum()

    def gain(lead: float) -> float:
        return float((w * (1 / (1 + np.exp(d - lead)) - 1 / (1 + np.exp(d)))).sum()) - points / 100

    return brentq(gain, 0.0, 20.0) if points else 0.0


def flights(n: int, difficulty: np.ndarray, draw_sd_points: float, rng, lead: float = 0.0) -> np.ndarray:
    """n training draws of one network flying the scenes of ``difficulty`` (logit): 0/1 success, one row a draw;
    ``lead``: the network's expected skill (logit) above the other's."""
    skill = rng.normal(lead, 4 * draw_sd_points / 100, (n, 1))
    return (rng.random((n, len(difficulty))) < 1 / (1 + np.exp(difficulty - skill))).astype(float)


def decided_share(draws_a: int, draws_b: int, args: argparse.Namespace, spread: bool, borrow: bool, rng) -> float:
    """Share of simulated studies whose interval excludes 0 (a false verdict: the networks are equal), or with
    ``args.difference_points``, whose interval decides the better network better (the power)."""
    decided, lead = 0, logit_lead(args.difference_points)
    for _ in range(args.studies):
        difficulty = rng.normal(0.0, 1.0, args.scenes)
        va = flights(draws_a, difficulty, args.draw_sd_points, rng, lead)
        vb = flights(draws_b, difficulty, args.draw_sd_points, rng)
        borrowed = 0.0
        if borrow and 1 in (draws_a, draws_b):
            others = [flights(n, difficulty, args.draw_sd_points, rng) for n in args.pool_draws]
            pooled = pooled_draw_variance([va, vb, *others])
            borrowed = ((draws_a == 1) + (draws_b == 1)) * pooled[0] if pooled else 0.0
        low, high = two_level_bootstrap_interval(np.arange(args.scenes), va, vb,
                                                 resamples=args.resamples, seed=int(rng.integers(2**31)),
                                                 spread=spread, borrowed_var=borrowed)
        decided += low > 0 if args.difference_points else (low > 0 or high < 0)
    return decided / args.studies


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=90, help="shared scenes per study (the laptop preset's spheres: 90)")
    p.add_argument("--draw-sd-points", type=float, default=15.0,
                   help="spread of one network's draws in success points (the laptop ConvNet's five: about 15)")
    p.add_argument("--draws", nargs="+", default=["1x1", "2x2", "3x3", "5x5", "5x3", "3x1"], metavar="AxB",
                   help="draws of the two networks")
    p.add_argument("--pool-draws", nargs="*", type=int, default=[5, 3, 3], metavar="N",
                   help="draws of the study's other networks, whose spread a network trained once borrows")
    p.add_argument("--difference-points", type=float, default=0.0,
                   help="the first network's lead in success points (0: equal networks, the false verdicts)")
    p.add_argument("--studies", type=int, default=400, help="simulated studies per row")
    p.add_argument("--resamples", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    pairs = [tuple(int(v) for v in d.split("x")) if re.fullmatch(r"[1-9]\d*x[1-9]\d*", d) else None
             for d in args.draws]
    if None in pairs:
        print(f"--draws: expected AxB with A, B >= 1 (e.g. 3x3), got {' '.join(args.draws)}", file=sys.stderr)
        return 2
    if args.scenes < 2 or args.studies < 1 or any(n < 1 for n in args.pool_draws):
        print("--scenes must be >= 2, --studies >= 1 and --pool-draws >= 1 each", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    what = (f"share of intervals deciding the network {args.difference_points:g} points better better (the power)"
            if args.difference_points else
            "share of intervals deciding between equal networks (95 %: about 0.05 when calibrated)")
    print(f"{args.studies} studies a row, {args.scenes} scenes, draws' sd {args.draw_sd_points:g} points: {what}")
    print("| draws | draws resampled as they are | draws spread by sqrt(n / (n - 1)) | and one draw borrowing the "
          f"pooled spread (pool: {' '.join(map(str, args.pool_draws)) or 'the two'}) |")
    print("|---|---:|---:|---:|")
    for a, b in pairs:
        plain = decided_share(a, b, args, False, False, rng)
        spread = decided_share(a, b, args, True, False, rng)
        # only a network trained once borrows: elsewhere the column is the one before
        borrowed = decided_share(a, b, args, True, True, rng) if 1 in (a, b) else spread
        print(f"| {a} vs {b} | {plain:.3f} | {spread:.3f} | {borrowed:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
