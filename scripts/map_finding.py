"""The maps finding ("ConvNet's maps diffuse and inconsistent, ViT+LSTM's consistent and on edges") over several
depths: the claims of each ``vitfly explain --trials`` run's ``paired.json`` for one model against the first
policy, decided together by ``vitfly.eval.paired.claims_verdict``.

    python scripts/map_finding.py --paired exact runs/explain_study/paired.json \
        --paired d435 runs/explain_d435/paired.json
"""

from __future__ import annotations

import argparse
import json
import sys

from vitfly.atomic import write_text
from vitfly.eval.paired import claims_verdict


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--paired", nargs=2, action="append", required=True, metavar=("LABEL", "PAIRED_JSON"),
                   help="a depth label and the paired.json of its explain --trials run")
    p.add_argument("--model", default="ViT+LSTM", help="the model claimed better than the first policy")
    p.add_argument("--out", help="write the finding as JSON here")
    args = p.parse_args(argv)
    claims = []
    for label, path in args.paired:
        try:
            with open(path) as f:
                findings = json.load(f)["findings"]
        except (OSError, ValueError, KeyError) as err:
            print(f"map_finding: error: {path}: not an explain paired.json ({type(err).__name__})", file=sys.stderr)
            return 2
        match = [f for f in findings if f["a"] == args.model]
        if not match:
            print(f"map_finding: error: {path}: field findings has no model {args.model!r}", file=sys.stderr)
            return 2
        claims += [{"depth": label, **c} for c in match[0]["comparisons"]]
    verdict, why = claims_verdict([c["side"] for c in claims])
    for c in claims:
        print(f"{c['depth']}: {c['a']} - {c['b']} {c['metric']} ({c['map_kind']}): {c['diff']:+.3f} "
              f"[{c['low']:+.3f}, {c['high']:+.3f}], {c['trials']} trials: {c['side']}")
    print(f"verdict: {verdict} ({why})")
    if args.out:
        write_text(args.out, json.dumps({"model": args.model, "claims": claims, "verdict": verdict, "why": why},
                                        indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
