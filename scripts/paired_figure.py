"""Paired differences as a picture, from the trial records of any sweep: a panel per metric, a row per pair of
policies, env and speed (and all speeds pooled), each difference A - B with its paired 95 % interval
(``vitfly.eval.paired``), green where A is decided better, red where B is, grey where the trials cannot tell.
A published folder's ``outcomes.jsonl.gz`` is enough (no flying). Prints every difference as the figure shows it.

Given a study's ``results.json`` (``vitfly reproduce``) instead, it draws that study's paired findings as the
report does (``figures/paired_findings.png``), from the numbers the JSON keeps; no ``--pair`` then.

    python scripts/paired_figure.py docs/results/paper_budget/ablation_native/outcomes.jsonl.gz \
        --pair convnet-state convnet-nostate --pair lstmnet-state lstmnet-nostate \
        --draws convnet-state=convnet-state,convnet-state-s1,convnet-state-s2 \
                convnet-nostate=convnet-nostate,convnet-nostate-s1,convnet-nostate-s2 \
        --out docs/results/paper_budget/ablation_native/state_effect.png
    python scripts/paired_figure.py docs/results/laptop/results.json --out docs/results/laptop/paired_findings.png
    python scripts/paired_figure.py paper=docs/results/paper_budget/evaluation_native/spheres \
        shipped=docs/results/shipped_4_6_7 --speeds 4 6 7 --pair paper/convnet shipped/convnet --envs spheres \
        --draws paper/convnet=paper/convnet,paper/convnet-s1,paper/convnet-s2 shipped/convnet=shipped/convnet \
        --out /tmp/paper_vs_shipped.png
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from vitfly.errors import VitflyError
from vitfly.eval.paired import HIGHER_IS_BETTER, PairedDifference, paired_difference
from vitfly.eval.paired_findings import METRIC_WORDS, PairedFinding
from vitfly.eval.paper_figures import paired_differences_figure, paired_findings_figure
from vitfly.eval.records import merge_records, read_records, report_files


def parse_draws(items: list[str]) -> dict[str, list[str]]:
    """``RUN=LABEL,LABEL,...`` items as {run: [labels]}."""
    draws = {}
    for item in items:
        run, sep, labels = item.partition("=")
        if not sep or not run or not labels:
            raise VitflyError(f"--draws {item!r}: expected RUN=LABEL,LABEL,... (the run's own label among them)")
        draws[run] = labels.split(",")
    return draws


def read(sources: list[str], speeds: list[float] | None = None):
    """The records of trial files, outcomes files or sweep folders, merged by key. A source written
    ``NAME=PATH`` has its policies renamed ``NAME/policy``, so that two sweeps that both flew a "convnet" (the
    shipped weights and a new training, on the same scenes) pair as two policies. ``speeds``: only those."""
    groups = []
    for source in sources:
        name, sep, path = source.partition("=")
        path = Path(path if sep else source)
        files = report_files(path) if path.is_dir() else [path]
        if not files or not all(f.exists() for f in files):
            raise VitflyError(f"{path}: no trials*.jsonl or outcomes.jsonl.gz there")
        for f in files:
            records = [r for r in read_records(f) if speeds is None or float(r.speed) in speeds]
            groups.append([dataclasses.replace(r, policy=f"{name}/{r.policy}") for r in records] if sep else records)
    return merge_records(groups)


def differences(records, pairs: list[list[str]], envs: list[str], metrics: list[str],
                draws: dict[str, list[str]]) -> list[tuple[str, list[PairedDifference]]]:
    """(metric, its differences) per metric: per pair and env, each speed both flew, then all speeds pooled."""
    groups = []
    for metric in metrics:
        diffs = []
        for a, b in pairs:
            for env in envs:
                speeds = sorted({float(r.speed) for r in records if r.policy == a and r.env == env})
                for sel in [[s] for s in speeds] + ([None] if len(speeds) > 1 else []):
                    d = paired_difference(records, a, b, env, metric, sel, draws=draws)
                    if d is not None:
                        diffs.append(d)
        if diffs:
            groups.append((METRIC_WORDS.get(metric, metric), diffs))
    return groups


def study_findings(path: Path) -> list[PairedFinding]:
    """The paired findings a study's results.json keeps."""
    try:
        kept = json.loads(path.read_text())["paired_findings"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        why = f"{type(err).__name__}: {err}"
        raise VitflyError(f"{path}: not a study's results.json with paired_findings ({why})") from None
    return [PairedFinding.from_dict(f, f"{path}: paired_findings[{i}]") for i, f in enumerate(kept)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("records", nargs="+", help="trials*.jsonl, outcomes.jsonl.gz or sweep folders; NAME=PATH names "
                   "the source's policies NAME/policy")
    p.add_argument("--speeds", nargs="+", type=float, help="only these speeds (m/s); default every speed flown")
    p.add_argument("--pair", nargs=2, action="append", default=[], metavar=("A", "B"),
                   help="draw A - B (repeat for more pairs); none for a results.json")
    p.add_argument("--draws", nargs="+", default=[], metavar="RUN=LABEL,...",
                   help="a run's training draws: compared by their mean (vitfly.eval.paired)")
    p.add_argument("--envs", nargs="+", default=["spheres", "trees"])
    p.add_argument("--metrics", nargs="+", default=["success", "collisions"], choices=sorted(HIGHER_IS_BETTER))
    p.add_argument("--title", default="")
    p.add_argument("--out", required=True, help="the figure (.png)")
    args = p.parse_args(argv)
    study = [Path(r).name for r in args.records] == ["results.json"]
    if not (study or args.pair):
        p.error("--pair A B is required (but for a study's results.json)")
    try:
        if study:
            written = paired_findings_figure(study_findings(Path(args.records[0])), args.out, args.title)
            print(f"wrote {written}" if written else f"{args.records[0]}: no finding was compared; nothing drawn")
            return 0
        records = read(args.records, args.speeds)
        groups = differences(records, args.pair, args.envs, args.metrics, parse_draws(args.draws))
        flown = {r.policy for r in records}
        missing = sorted({q for pair in args.pair for q in pair} - flown)
        if missing or not groups:
            raise VitflyError(f"{', '.join(args.records)}: no shared trials of "
                              + (", ".join(missing) if missing else "these pairs in " + ", ".join(args.envs))
                              + f" (flown: {', '.join(sorted(flown))})")
    except VitflyError as err:
        print(f"paired_figure: {err}", file=sys.stderr)
        return 1
    for _, diffs in groups:
        for d in diffs:
            print(f"{d.metric:<10} {d.a} - {d.b}, {d.env}, {'/'.join(f'{s:g}' for s in d.speeds)} m/s: {d.text()}")
    title = args.title or "paired differences A - B with their 95 % intervals"
    print(f"wrote {paired_differences_figure(groups, args.out, title)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
