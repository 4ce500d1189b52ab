"""``vitfly ablate --no-state``: with vs without the state input, per architecture, beside the paper's table."""

from __future__ import annotations

import argparse

from vitfly.errors import VitflyError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-state", action="store_true",
                        help="the state-input ablation (paper: table-no-state-info); the only one so far")
    parser.add_argument("--config", default="ablate",
                        help="ablation YAML: a path, or a shipped config's name (`vitfly configs`)")
    parser.add_argument("--preset", help="a section under 'presets' in the YAML, e.g. tiny (CI-sized)")
    parser.add_argument("--models", nargs="+", help="architectures (default: the paper's five)")
    parser.add_argument("--out", help="run directory (train/, eval/, ablation.md)")
    parser.add_argument("--data", help="HDF5 training dataset (collected or completed if needed)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from vitfly.workflows.ablation import load_ablation_config, run_ablation

    if not args.no_state:
        raise VitflyError("choose an ablation: --no-state (train with and without the state input)")
    cfg = load_ablation_config(args.config, args.preset, {"models": args.models, "out": args.out, "data": args.data})
    run_ablation(cfg, progress=not args.no_progress)
    return 0
