"""``vitfly dagger --config configs/dagger.yaml [--preset tiny|laptop|paper]``: DAgger with the privileged expert."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from vitfly.commands.engine_flags import add_engine_arguments
    from vitfly.workflows.dagger_stages import STAGE_NAMES_HELP

    parser.add_argument("--config", default="dagger",
                        help="dagger YAML: a path, or a shipped config's name (`vitfly configs`)")
    parser.add_argument("--preset", help="a section under 'presets' in the YAML: tiny (CI, under a minute), laptop "
                        "(ConvNet, ~30-45 min on 2 CPU cores), paper (ViT+LSTM at the paper's data scale, a GPU)")
    parser.add_argument("--model", help="architecture to train (overrides train.model), e.g. convnet or vit_lstm")
    parser.add_argument("--out", help="run directory (data/, train/, eval/, paths/, manifests/, dagger.md)")
    parser.add_argument("--rounds", type=int, help="DAgger rounds after round 0 (overrides schedule.rounds)")
    parser.add_argument("--threads", type=int,
                        help="torch threads for training, the students' flights and the evaluation (0: all cores)")
    add_engine_arguments(parser, "every flight (the rounds' collections, in one process: batched sets data.workers "
                         "1; the sweeps; the paths fly numpy)")
    parser.add_argument("--stop-after", metavar="STAGE",
                        help=f"stop after this stage ({STAGE_NAMES_HELP}); rerun without it to go on")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def config_overrides(args: argparse.Namespace) -> dict:
    """What the flags set over the YAML and its preset."""
    from vitfly.commands.engine_flags import engine_overrides

    engine = engine_overrides(args)  # one engine for the collections and the sweeps
    overrides = {"out": args.out, "threads": args.threads, "train": {"model": args.model},
                 "schedule": {"rounds": args.rounds}, "data": {"collect": engine}, "evaluate": dict(engine)}
    if engine.get("sim") == "batched":  # data.workers are the numpy engine's processes; batched flies in this one
        overrides["data"]["workers"] = 1
    if args.threads:
        overrides["evaluate"]["threads"] = args.threads
    return overrides


def run(args: argparse.Namespace) -> int:
    from vitfly.workflows.dagger import run_dagger
    from vitfly.workflows.dagger_config import load_dagger_config

    cfg = load_dagger_config(args.config, args.preset, config_overrides(args))
    run_dagger(cfg, args.stop_after, progress=not args.no_progress)
    return 0
