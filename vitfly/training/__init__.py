"""The training layer: a registered network + a trajectory dataset + a Lightning Trainer.

- :mod:`vitfly.training.fit`: ``train_policy`` (training from Python: ``vitfly pipeline``, ``ablate``, ``dagger``)
  and the set-up it shares with the command line (best checkpoint, wandb default).
- :mod:`vitfly.training.cli`: ``vitfly fit | validate | test | predict`` (LightningCLI).
- :mod:`vitfly.training.checkpoints`: ``last.ckpt`` at the end of every epoch, and the random generators' state
  for an exact resume.
- :mod:`vitfly.training.run_lock`: one training process per run folder (a second one is told which process has it).

Training composes :mod:`vitfly.zoo` (the networks and their ``PolicyModule``) and :mod:`vitfly.datamodules`;
neither of them imports it. Importing this package does not import Lightning.
"""

from vitfly.training.fit import (
    BEST_NAME,
    CHECKPOINT_DIR,
    MONITOR,
    checkpoint_defaults,
    default_wandb_offline,
    finish_wandb,
    load_initial_weights,
    train_policy,
)

__all__ = [
    "BEST_NAME",
    "CHECKPOINT_DIR",
    "MONITOR",
    "checkpoint_defaults",
    "default_wandb_offline",
    "finish_wandb",
    "load_initial_weights",
    "train_policy",
]
