"""``vitfly export CKPT_OR_NAME --format onnx --out policy.onnx``: a network for deployment.

CKPT_OR_NAME: a checkpoint file, ``pretrained:NAME`` (published weights) or a registry name (random weights).
"""

from __future__ import annotations

import argparse
import os
import sys

from vitfly.errors import VitflyError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "source",
        metavar="CKPT_OR_NAME",
        help="a vitfly/Lightning checkpoint, an original state dict (with --arch), pretrained:NAME (published "
        "weights, e.g. pretrained:vit_lstm), or a registry name (random-initialised weights)",
    )
    parser.add_argument("--format", choices=("onnx",), default="onnx", help="export format")
    parser.add_argument("--out", required=True, help="output file (.onnx)")
    parser.add_argument("--arch", default=None, help="architecture of an original-project state dict")
    parser.add_argument(
        "--batch-size", type=int, default=None, help="fix the batch size (default: dynamic batch axis)"
    )
    parser.add_argument("--no-state", action="store_true", help="with a registry name: the no-state variant")
    parser.add_argument(
        "--no-optimize", action="store_true", help="export the network as written, without inference rewrites"
    )
    parser.add_argument("--opset", type=int, default=None, help="ONNX opset (default: the exporter's)")
    parser.add_argument("--precision", choices=("fp32", "int8"), default="fp32",
                        help="int8: large matrix products in int8 (dynamic quantisation), for CPUs with VNNI; "
                             "the ViTs' mix-FFNs as int8 convolutions calibrated on recorded expert flights")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def run(args: argparse.Namespace) -> int:
    from vitfly.deploy.onnx import export_onnx
    from vitfly.zoo import create_model, list_models, load_network, load_pretrained
    from vitfly.zoo.pretrained import is_pretrained_spec

    if os.path.exists(args.out) and not args.force:
        raise VitflyError(f"{args.out}: already exists; pass --force to overwrite")
    if args.batch_size is not None and args.batch_size < 1:
        raise VitflyError(f"--batch-size must be at least 1, got {args.batch_size}")
    if is_pretrained_spec(args.source):
        if args.arch is not None:
            raise VitflyError(f"--arch {args.arch} only applies to original checkpoints, not to {args.source}")
        net = load_pretrained(args.source)
        origin = args.source
    elif os.path.exists(args.source):
        net = load_network(args.source, arch=args.arch)
        origin = args.source
    elif args.source in list_models():
        net = create_model(args.source, use_state=not args.no_state).eval()
        origin = f"registry model {args.source!r}"
        print(
            f"vitfly: warning: {args.source!r} is a registry name: exporting RANDOM-INITIALISED weights "
            "(pass a checkpoint to export trained ones)",
            file=sys.stderr,
        )
    else:
        raise VitflyError(
            f"{args.source}: neither an existing checkpoint file nor a registry name ({', '.join(list_models())})"
        )
    calibration = None
    if args.precision == "int8" and not args.no_optimize:
        from vitfly.eval.latency import needs_calibration

        if needs_calibration(net):  # a few seconds of simulated expert flight fix the activation ranges
            from vitfly.eval.agreement import calibration_depth

            calibration = calibration_depth()
    diff = export_onnx(
        net,
        args.out,
        optimize=not args.no_optimize,
        opset=args.opset,
        batch_size=args.batch_size,
        precision=args.precision,
        calibration_depth=calibration,
    )
    batch = "dynamic" if args.batch_size is None else str(args.batch_size)
    state = " + LSTM state h0, c0 -> hn, cn" if getattr(net, "is_recurrent", False) else ""
    print(
        f"wrote {args.out}: {net.model_name} from {origin}, batch {batch}{state}, {args.precision}; "
        f"ONNX Runtime matches eager to {diff:.2g}"
    )
    return 0
