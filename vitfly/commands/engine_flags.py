"""The simulator-engine flags (``--sim``, ``--sim-device``, ``--sim-dtype``, ``--sim-compile``) of the commands
that fly: each flag left out keeps what the config says (``vitfly.sim.engine.SimEngine`` checks the choice)."""

from __future__ import annotations

import argparse

from vitfly.sim.engine import SIM_DTYPES, SIM_ENGINES

FIELDS = ("sim", "sim_device", "sim_dtype", "sim_compile")


def add_engine_arguments(parser: argparse.ArgumentParser, flies: str) -> None:
    """The four flags; ``flies``: what they choose the engine of, for the help text."""
    parser.add_argument("--sim", choices=SIM_ENGINES,
                        help=f"simulator engine of {flies}, stated in every record and part of its key: numpy "
                        "(default) or batched (torch, the native physics; float64 on the CPU gives the numpy "
                        "engine's results)")
    parser.add_argument("--sim-device", help="the batched engine's device: cpu (default) or cuda[:N]")
    parser.add_argument("--sim-dtype", choices=SIM_DTYPES,
                        help="the batched engine's precision: float64 (default, exact) or float32 (faster)")
    parser.add_argument("--sim-compile", action="store_true", default=None,
                        help="the batched engine's kernels through torch.compile (seconds once, then faster)")


def engine_overrides(args: argparse.Namespace) -> dict:
    """The engine fields the command line sets (the others stay as the config has them)."""
    return {name: getattr(args, name) for name in FIELDS if getattr(args, name, None) is not None}
