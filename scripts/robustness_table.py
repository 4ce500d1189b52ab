"""The robustness study's table: each network's success with exact and with modelled (d435) depth, before and
after sensor-model randomisation in training, paired over the same scenes (docs/results.md#robustness).

Policies are named ``NAME`` (shipped weights, exact depth), ``NAME-d435`` (shipped, ``--sensor d435``),
``NAME_dr`` (fine-tuned with ``data.sensor_prob``, exact) and ``NAME_dr-d435``; every sweep directory given is
read (``trials*.jsonl``) and the records are merged, so the four may come from different directories flown with
the same ``--seed``. Writes ``paired.csv`` (every comparison below, per speed and pooled), ``summary.csv``
(success per policy, env and speed) and ``table.md``.

    python scripts/robustness_table.py runs/robust/spheres runs/robust/course runs/robust/ft_spheres \
        runs/robust/ft_course --out docs/results/robustness
"""

from __future__ import annotations

import argparse
import csv
import sys
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy.stats import bootstrap

from vitfly.eval.paired import paired_difference, pairs
from vitfly.eval.records import read_sweep

ARCHS = {"convnet": "ConvNet", "lstmnet": "LSTMnet", "unet_lstm": "UNet+LSTM", "vit": "ViT", "vit_lstm": "ViT+LSTM"}
# (label, a, b): a - b
COMPARISONS = (
    ("d435 - exact, shipped", "{m}-d435", "{m}"),
    ("d435 - exact, randomised", "{m}_dr-d435", "{m}_dr"),
    ("won back: d435, randomised - shipped", "{m}_dr-d435", "{m}-d435"),
    ("exact, randomised - shipped", "{m}_dr", "{m}"),
)


def kept(records, exact: str, modelled: str, env: str, speeds) -> tuple[float, float, float, int] | None:
    """Share of exact-depth success kept with modelled depth on the same scenes, success(modelled) /
    success(exact), with a 95 % percentile interval from a paired bootstrap over scenes; None without pairs."""
    _, _, e, m = pairs(records, exact, modelled, env, "success", speeds)
    if len(e) == 0 or e.sum() == 0:
        return None
    point = m.mean() / e.mean()
    if len(e) < 2 or (np.all(e == m)):
        return point, point, point, len(e)

    def ratio(a, b, axis=-1):  # a resample without an exact-depth success has no ratio: unbounded
        ea = a.mean(axis=axis)
        return np.where(ea > 0, b.mean(axis=axis) / np.where(ea > 0, ea, 1.0), np.inf)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the spread of resamples holding inf (unbounded ratios)
        ci = bootstrap((e, m), ratio, paired=True, vectorized=True, n_resamples=10_000, method="percentile",
                       rng=np.random.default_rng(0)).confidence_interval
    return float(point), float(ci.low), float(ci.high), len(e)


def compact(records, envs, speeds) -> str:
    """One row per network and env: pooled success and paired differences (points, 95 % interval)."""
    lines = ["| network | env | success exact / d435, shipped | d435 - exact, shipped | success exact / d435, "
             "randomised | d435 - exact, randomised | won back: d435, randomised - shipped | exact, randomised - "
             "shipped |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for env in envs:
        for m, label in ARCHS.items():
            if not any(r.policy == f"{m}-d435" and r.env == env for r in records):
                continue
            cells = []
            for exact, modelled in ((m, f"{m}-d435"), (f"{m}_dr", f"{m}_dr-d435")):
                d = paired_difference(records, modelled, exact, env, "success")
                cells += ["-", "-"] if d is None else [
                    f"{100 * d.mean_b:.0f} / {100 * d.mean_a:.0f} %", f"{pct(d.diff)} [{pct(d.low)}, {pct(d.high)}]"]
            for a, b in ((f"{m}_dr-d435", f"{m}-d435"), (f"{m}_dr", m)):
                d = paired_difference(records, a, b, env, "success")
                cells.append("-" if d is None else f"{pct(d.diff)} [{pct(d.low)}, {pct(d.high)}]")
            n = len({(r.scene_seed, r.speed) for r in records if r.policy == m and r.env == env})
            lines.append(f"| {label} | {env} (n={n}) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def pct(x: float) -> str:
    return f"{100 * x:+.0f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="+", help="sweep directories (trials*.jsonl)")
    parser.add_argument("--out", required=True, help="output directory")
    args = parser.parse_args(argv)
    records = [r for d in args.dirs for r in read_sweep(d)]
    if not records:
        print(f"{args.dirs[0]}: no trials", file=sys.stderr)
        return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    rates: dict[tuple[str, str, float], list[int]] = defaultdict(list)
    for r in records:
        rates[(r.policy, r.env, float(r.speed))].append(int(bool(r.success_paper)))
    with open(out / "summary.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["policy", "env", "speed", "trials", "success"])
        for (policy, env, speed), v in sorted(rates.items()):
            w.writerow([policy, env, f"{speed:g}", len(v), f"{sum(v) / len(v):.4f}"])

    envs = sorted({r.env for r in records}, key=lambda e: (e != "spheres", e))
    speeds = sorted({float(r.speed) for r in records})
    rows, md = [], []
    for env in envs:
        md += [f"### {env}", "",
               "| network | speed (m/s) | exact | d435 | exact, randomised | d435, randomised | "
               + " | ".join(c[0] for c in COMPARISONS) + " | kept with d435, shipped | kept, randomised |",
               "|---|---:|---:|---:|---:|---:|" + "---:|" * (len(COMPARISONS) + 2)]
        for m, label in ARCHS.items():
            for sp in [[s] for s in speeds] + [None]:
                cells = []
                for name in (m, f"{m}-d435", f"{m}_dr", f"{m}_dr-d435"):
                    v = [x for s in (sp or speeds) for x in rates.get((name, env, s), [])]
                    cells.append(f"{100 * sum(v) / len(v):.0f} % (n={len(v)})" if v else "-")
                if all(c == "-" for c in cells):
                    continue
                diffs = []
                for what, a, b in COMPARISONS:
                    d = paired_difference(records, a.format(m=m), b.format(m=m), env, "success", sp)
                    if d is None:
                        diffs.append("-")
                        continue
                    diffs.append(f"{pct(d.diff)} [{pct(d.low)}, {pct(d.high)}], n={d.pairs}")
                    rows.append({"env": env, "network": m, "comparison": what, "a": d.a, "b": d.b,
                                 "speed": "all" if sp is None else f"{sp[0]:g}", "pairs": d.pairs,
                                 "mean_a": f"{d.mean_a:.4f}", "mean_b": f"{d.mean_b:.4f}", "diff": f"{d.diff:.4f}",
                                 "low": f"{d.low:.4f}", "high": f"{d.high:.4f}",
                                 "mcnemar_p": "" if d.mcnemar_p is None else f"{d.mcnemar_p:.4g}"})
                speed = "all" if sp is None else f"{sp[0]:g}"
                for exact, modelled in ((m, f"{m}-d435"), (f"{m}_dr", f"{m}_dr-d435")):
                    k = kept(records, exact, modelled, env, sp)
                    high = "unbounded" if k is not None and not np.isfinite(k[2]) else f"{100 * k[2]:.0f}" if k else ""
                    diffs.append("-" if k is None else f"{100 * k[0]:.0f} % [{100 * k[1]:.0f}, {high}]")
                    if k is not None:
                        rows.append({"env": env, "network": m, "comparison": "kept: success modelled / exact",
                                     "a": modelled, "b": exact, "speed": speed, "pairs": k[3], "mean_a": "",
                                     "mean_b": "", "diff": f"{k[0]:.4f}", "low": f"{k[1]:.4f}",
                                     "high": f"{k[2]:.4f}", "mcnemar_p": ""})
                md.append(f"| {label} | {speed} | " + " | ".join(cells + diffs) + " |")
        md.append("")
    with open(out / "paired.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["env"])
        w.writeheader()
        w.writerows(rows)
    (out / "table.md").write_text("\n".join(md) + "\n")
    (out / "compact.md").write_text(compact(records, envs, speeds))
    print(f"wrote {out / 'paired.csv'}, {out / 'summary.csv'}, {out / 'table.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
