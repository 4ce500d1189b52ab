"""``vitfly convert-checkpoint original.pth --arch NAME --out X.ckpt``: original state dict -> vitfly checkpoint."""

from __future__ import annotations

import argparse
import os

from vitfly.errors import VitflyError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", help="original-project state dict (torch.save(model.state_dict()) file)")
    parser.add_argument(
        "--arch",
        default=None,
        help="architecture name (convnet, lstmnet, unet_lstm, vit, vit_lstm); recognised from the keys if omitted",
    )
    parser.add_argument("--out", required=True, help="where to write the vitfly checkpoint (.ckpt)")
    parser.add_argument("--no-state", action="store_true", help="the network was trained without the state input")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def run(args: argparse.Namespace) -> int:
    from vitfly.zoo import load_legacy_checkpoint, save_checkpoint
    from vitfly.zoo.legacy import identify_architecture, read_torch_file

    if os.path.exists(args.out) and not args.force:
        raise VitflyError(f"{args.out}: already exists; pass --force to overwrite")
    arch = args.arch
    if arch is None:
        arch = identify_architecture(read_torch_file(args.checkpoint))
        if arch is None:
            raise VitflyError(f"{args.checkpoint}: keys match no known architecture; pass --arch NAME")
    use_state = not args.no_state
    net = load_legacy_checkpoint(arch, args.checkpoint, use_state=use_state)
    save_checkpoint(
        net, arch, use_state=use_state, path=args.out,
        metadata={"converted_from": os.path.abspath(args.checkpoint)},
    )  # fmt: skip
    params = sum(p.numel() for p in net.parameters())
    print(f"wrote {args.out}: {arch} ({params:,} parameters, use_state={use_state}) from {args.checkpoint}")
    return 0
