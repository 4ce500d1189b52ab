"""A ``vitfly reproduce`` preset as every ``scripts/gpu.py`` command names it: its config, its runs' folders by
label (MODEL-state, MODEL-nostate, -s<seed> for another training draw) and the hash of its dataset here."""

from __future__ import annotations

import argparse
from pathlib import Path


def load_cfg(args: argparse.Namespace):
    from vitfly.workflows.reproduce_config import load_reproduce_config

    return load_reproduce_config(args.config, args.preset, {"out": args.run_dir, "data": args.data})


def parse_label(label: str):
    """A run's folder name (MODEL-state, MODEL-nostate, with -s<seed> for another training draw) as a Run."""
    from vitfly.errors import VitflyError
    from vitfly.workflows.reproduce_config import Run

    try:
        return Run.parse(label)
    except VitflyError as err:
        raise SystemExit(f"--runs: {err}") from None


def run_dir(cfg, label: str) -> Path:
    return cfg.train_dir(*parse_label(label))


def flies_best(cfg, run) -> bool:
    """Whether the preset flies ``run``'s best epoch (``select: best``), so that a best.ckpt travels with it;
    with ``select: last`` (the paper arm) no run ever has one."""
    from vitfly.workflows.reproduce_config import train_stage

    return train_stage(cfg, run.model, run.use_state, seed=run.seed).select == "best"


def local_data_hash(cfg) -> str:
    from vitfly.datamodules.provenance import dataset_fingerprint

    if not Path(cfg.data).exists():
        raise SystemExit(f"{cfg.data}: no dataset here to check the returned runs against; collect it first "
                         f"(vitfly reproduce --preset {cfg.preset} --stages data)")
    return dataset_fingerprint(cfg.data)["dataset_hash"]
