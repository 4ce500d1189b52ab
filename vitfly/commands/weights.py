"""``vitfly weights [NAME]``: the pretrained weights at hand (name, network, training, closed-loop success).

Without NAME, one line per manifest entry of the weights directory (the shipped ``weights/``, or
``$VITFLY_WEIGHTS_DIR``, or ``--weights-dir``); with NAME, that entry whole, as JSON (provenance, recipe,
closed-loop numbers), for reading or for ``jq``.
"""

from __future__ import annotations

import argparse
import json

from vitfly.errors import VitflyError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", nargs="?", help="print this entry of the manifest as JSON, e.g. convnet_paper")
    parser.add_argument("--weights-dir", help="weights directory (default: $VITFLY_WEIGHTS_DIR, else the shipped "
                        "weights)")


def spheres_success(entry: dict) -> str:
    """The entry's closed-loop success in spheres by speed, e.g. "68 / 45 / 23 % at 3 / 5 / 7 m/s" ("-": none)."""
    cells = (entry.get("closed_loop") or {}).get("spheres") or {}
    speeds = sorted(cells, key=float)
    if not speeds:
        return "-"
    rates = " / ".join(f"{100 * cells[s]['success']:.0f}" for s in speeds)
    return f"{rates} % at {' / '.join(speeds)} m/s"


def run(args: argparse.Namespace) -> int:
    from vitfly.weights_manifest import manifest_entry, read_manifest, weights_dir

    if args.name is not None:
        print(json.dumps(manifest_entry(args.name, args.weights_dir), indent=2))
        return 0
    root = weights_dir(args.weights_dir)
    models = read_manifest(root)["models"]
    if not models:
        raise VitflyError(f"{root}: the manifest lists no weights (publish some with `vitfly publish-weights`)")
    rows = [(name, e.get("model", "?"), "yes" if e.get("use_state", True) else "no", str(e.get("epochs", "-")),
             str(e.get("preset", "-")), spheres_success(e)) for name, e in models.items()]
    header = ("name", "network", "state", "epochs", "preset", "spheres success (no collision)")
    widths = [max(len(r[i]) for r in (header, *rows)) for i in range(len(header) - 1)]
    print(f"weights in {root}: fly them as pretrained:NAME (`vitfly weights NAME` shows an entry whole)")
    for row in (header, *rows):
        print("  ".join(f"{cell:<{w}}" for cell, w in zip(row[:-1], widths, strict=True)) + "  " + row[-1])
    return 0
