"""Old path of :mod:`vitfly.training.checkpoints`, kept so that configs naming
``vitfly.training_checkpoints.LastCheckpoint`` (or ``RngState``) under ``trainer.callbacks`` still load."""

from vitfly.training.checkpoints import LAST_NAME, LastCheckpoint, RngState

__all__ = ["LAST_NAME", "LastCheckpoint", "RngState"]
