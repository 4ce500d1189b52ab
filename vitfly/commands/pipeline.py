"""``vitfly pipeline``: the main job -- collect if missing, train, fly against expert and straight, report."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default="quickstart",
                        help="pipeline YAML: a path, or a shipped config's name (`vitfly configs`)")
    parser.add_argument("--out", help="run directory (train/, eval/, pipeline.json)")
    parser.add_argument("--data", help="HDF5 dataset: used if complete, collected or completed if not")
    parser.add_argument("--physics", choices=("auto", "pybullet", "native"),
                        help="rigid-body physics back end of both collect and evaluate (default: the config's, auto: "
                             "pybullet where installed, else native)")
    parser.add_argument("--wandb-project", help="also log the comparison and plots to this wandb project")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from vitfly.workflows.pipeline import load_pipeline_config, run_pipeline

    cfg = load_pipeline_config(args.config, {"out": args.out, "data": args.data, "wandb_project": args.wandb_project,
                                             "physics": args.physics})
    run_pipeline(cfg, progress=not args.no_progress)
    return 0
