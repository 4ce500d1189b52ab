"""``vitfly publish-weights CKPT --name NAME``: a checkpoint as ``weights/NAME.safetensors`` (fp16) + manifest."""

from __future__ import annotations

import argparse
import json

from vitfly.errors import VitflyError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", help="a vitfly/Lightning checkpoint (vitfly fit, vitfly reproduce, ...)")
    parser.add_argument("--name", required=True, help="the name it loads by: pretrained:NAME (e.g. vit_lstm)")
    parser.add_argument("--weights-dir", help="weights directory (default: $VITFLY_WEIGHTS_DIR, else <repo>/weights "
                        "in a clone; an installed vitfly asks for one)")
    parser.add_argument("--preset", help="provenance: the preset or recipe it was trained with")
    parser.add_argument("--dataset", help="provenance: the training dataset (its hash and frame count are recorded)")
    parser.add_argument("--field", action="append", default=[], metavar="KEY=JSON",
                        help="another manifest field, value as JSON (repeatable), e.g. notes='\"lr 1e-4\"'")
    parser.add_argument("--closed-loop-from", nargs="+", metavar="DIR",
                        help="evaluation folders (vitfly evaluate / reproduce: trials or published outcomes) whose "
                             "trials of these weights give the manifest's closed_loop numbers; every trial must "
                             "have been flown with this checkpoint's weights")
    parser.add_argument("--closed-loop-policy", metavar="LABEL",
                        help="the label the weights were flown under in those folders (default: --name)")


def parse_fields(items: list[str]) -> dict:
    fields = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise VitflyError(f"--field {item!r}: expected KEY=JSON")
        try:
            fields[key] = json.loads(text)
        except ValueError:
            fields[key] = text  # a bare word is a string
    return fields


def run(args: argparse.Namespace) -> int:
    from vitfly.zoo.pretrained import save_pretrained

    fields = parse_fields(args.field)
    if args.preset:
        fields["preset"] = args.preset
    if args.dataset:
        from vitfly.datamodules.provenance import dataset_fingerprint

        fields.update(dataset_fingerprint(args.dataset))
    if args.closed_loop_from:  # checked before anything is written
        from vitfly.eval.closed_loop import closed_loop_from_sweeps
        from vitfly.zoo.pretrained import load_weights

        fields["closed_loop"] = closed_loop_from_sweeps(args.closed_loop_from, args.closed_loop_policy or args.name,
                                                        load_weights(args.checkpoint))
    elif args.closed_loop_policy:
        raise VitflyError("--closed-loop-policy names a label in the --closed-loop-from folders; give those too")
    path = save_pretrained(args.checkpoint, args.name, fields, args.weights_dir)
    print(f"wrote {path} and its entry in {path.parent / 'manifest.json'}; load it as pretrained:{args.name}")
    return 0
