"""``vitfly reproduce --config configs/reproduce.yaml [--preset tiny|laptop|paper|paper_vitfly]``: the study."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from vitfly.commands.engine_flags import add_engine_arguments
    from vitfly.workflows.reproduce_config import STAGES

    parser.add_argument("--config", default="reproduce",
                        help="reproduce YAML: a path, or a shipped config's name (`vitfly configs`)")
    parser.add_argument("--preset", help="a section under 'presets' in the YAML: tiny (CI, minutes), laptop (about "
                        "4 h on 2 CPU cores), paper (the paper's protocol and training recipe, for a GPU), "
                        "paper_vitfly (the same budget with vitfly's recipes in large batches, for a GPU)")
    parser.add_argument("--out", help="run directory (train/, eval/, figures/, results.md)")
    parser.add_argument("--data", help="HDF5 training dataset (collected or completed if needed)")
    parser.add_argument("--models", nargs="+",
                        help="only these architectures (trained with and, where the config says, without state, "
                        "and their train.draws)")
    parser.add_argument("--train-seed", type=int, metavar="N",
                        help="train every run with this seed (its validation split and initialisation) instead of "
                        "the recipes' own, and no train.draws; needs --out, so that runs of two seeds never share a "
                        "directory")
    parser.add_argument("--stages", nargs="+", choices=STAGES, metavar="STAGE",
                        help=f"only these stages (run in the order {', '.join(STAGES)}); None: all of them")
    parser.add_argument("--threads", type=int, metavar="N",
                        help="torch threads for training instead of the config's `threads` (0: all cores); on a "
                        "CPU two commands with --threads 1 side by side train two runs of a study at once")
    add_engine_arguments(parser, "the sweeps (the data stage collects as the YAML's collect section says)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def config_from_args(args: argparse.Namespace):
    """The study's ``ReproduceConfig``: the YAML and its preset, then --out, --data, --threads, --train-seed,
    --models and the engine flags (--sim ...)."""
    import dataclasses

    from vitfly.commands.engine_flags import engine_overrides
    from vitfly.errors import VitflyError
    from vitfly.workflows.reproduce_config import check_config, load_reproduce_config

    cfg = load_reproduce_config(args.config, args.preset, {"out": args.out, "data": args.data})
    if args.threads is not None:
        if args.threads < 0:
            raise VitflyError(f"--threads {args.threads}: expected 0 (all cores) or more")
        cfg = dataclasses.replace(cfg, threads=args.threads)
    if args.train_seed is not None:
        if args.out is None:
            raise VitflyError(f"--train-seed {args.train_seed}: give --out too (the preset's {cfg.out} holds the "
                              "runs of the recipes' own seeds)")
        t = cfg.train  # another copy of the study: its own runs, no draws
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(t, overrides={**t.overrides, "seed": args.train_seed},
                                                                 draws={}))
    if args.models:
        t = cfg.train
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(
            t, models=list(args.models), nostate_models=[m for m in t.nostate_models if m in args.models],
            publish_models=[m for m in t.publish_models if m in args.models],
            draws={run: seeds for run, seeds in t.draws.items() if run.removesuffix("-nostate") in args.models},
            slot_order=[m for m in t.slot_order if m in args.models],
            cpu_models=[m for m in t.cpu_models if m in args.models]))
    engine = engine_overrides(args)
    if engine:  # the sweeps' engine
        cfg = dataclasses.replace(cfg, evaluate=dataclasses.replace(cfg.evaluate, **engine))
    if args.models or args.train_seed is not None or engine:
        check_config(cfg, "--models" if args.models else "--train-seed" if args.train_seed is not None else "--sim")
    return cfg


def run(args: argparse.Namespace) -> int:
    from vitfly.workflows.reproduce import run_reproduce

    run_reproduce(config_from_args(args), args.stages, progress=not args.no_progress)
    return 0
