"""Old path of :mod:`vitfly.training.cli` (``vitfly fit | validate | test | predict``), kept so imports of it work."""

from vitfly.training.cli import VitflyCLI, build_cli, resolve_config_args, run_lightning_cli

__all__ = ["VitflyCLI", "build_cli", "resolve_config_args", "run_lightning_cli"]
