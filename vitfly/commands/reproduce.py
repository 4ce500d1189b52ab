"""``vitfly reproduce --config configs/reproduce.yaml [--preset tiny|laptop|paper|paper_vitfly]``: the study."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from vitfly.workflows.reproduce_config import STAGES

    parser.add_argument("--config", default="reproduce",
                        help="reproduce YAML: a path, or a shipped config's name (`vitfly configs`)")
    parser.add_argument("--preset", help="a section under 'presets' in the YAML: tiny (CI, minutes), laptop (one "
                        "working day on 2 CPU cores), paper (the paper's protocol and training recipe, for a GPU), "
                        "paper_vitfly (the same budget with vitfly's recipes in large batches, for a GPU)")
    parser.add_argument("--out", help="run directory (train/, eval/, figures/, results.md)")
    parser.add_argument("--data", help="HDF5 training dataset (collected or completed if needed)")
    parser.add_argument("--models", nargs="+",
                        help="only these architectures (trained with and, where the config says, without state)")
    parser.add_argument("--stages", nargs="+", choices=STAGES, metavar="STAGE",
                        help=f"only these stages (run in the order {', '.join(STAGES)}); None: all of them")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from vitfly.workflows.reproduce import run_reproduce
    from vitfly.workflows.reproduce_config import check_config, load_reproduce_config

    cfg = load_reproduce_config(args.config, args.preset, {"out": args.out, "data": args.data})
    if args.models:
        t = cfg.train
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(
            t, models=list(args.models), nostate_models=[m for m in t.nostate_models if m in args.models],
            publish_models=[m for m in t.publish_models if m in args.models]))
        check_config(cfg, "--models")
    run_reproduce(cfg, args.stages, progress=not args.no_progress)
    return 0
