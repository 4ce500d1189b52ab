"""The avoidance onset finding ("ViT+LSTM avoids earlier than ConvNet") from evaluation sweeps on single-obstacle
course scenes (``vitfly.eval.avoidance_onset``): Markdown table and verdict on stdout, everything as JSON.

    python scripts/avoidance_onset.py --sweep exact runs/onset/exact/s3 runs/onset/exact/s5 runs/onset/exact/s7 \\
        --sweep d435 runs/onset/d435/s3 runs/onset/d435/s5 runs/onset/d435/s7 --out runs/onset/onset.json

Each sweep: ``vitfly evaluate --policy pretrained:vit_lstm --name vit_lstm --env course --preset easy ...`` and the
same for ConvNet (``--name convnet``) into the same ``--out`` (docs/results.md gives the commands).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.eval.avoidance_onset import RANGE_M, THRESHOLD_FRACTION, onset_finding, onset_markdown
from vitfly.eval.records import read_sweep


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sweep", nargs="+", action="append", required=True, metavar=("LABEL", "DIR"),
                   help="a depth label (exact, d435) and its evaluation directories")
    p.add_argument("--a", default="vit_lstm", help="policy label claimed to avoid earlier")
    p.add_argument("--b", default="convnet", help="policy label it is compared with")
    p.add_argument("--threshold", type=float, default=THRESHOLD_FRACTION,
                   help="onset: |v_y command| above this fraction of the desired speed")
    p.add_argument("--range-m", type=float, default=RANGE_M, help="only ticks with the obstacle this close, m")
    p.add_argument("--out", help="write the finding as JSON here")
    args = p.parse_args(argv)
    try:
        sweeps = {}
        for label, *dirs in args.sweep:
            if not dirs:
                raise VitflyError(f"--sweep {label}: give at least one evaluation directory after the label")
            records = []
            for d in dirs:
                if not (Path(d) / "trials.jsonl").is_file():
                    raise VitflyError(f"{d}/trials.jsonl: missing (expected a vitfly evaluate --out directory)")
                records += read_sweep(d)
            sweeps[label] = records
        finding = onset_finding(sweeps, args.a, args.b, args.threshold, args.range_m)
    except VitflyError as err:
        print(f"avoidance_onset: error: {err}", file=sys.stderr)
        return 2
    print(onset_markdown(finding))
    if args.out:
        write_text(args.out, json.dumps(finding, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
