"""Where an epoch's wall time goes: ``time/train_s`` and ``time/val_s`` in every epoch's row of metrics.csv.

A one-trajectory step (the paper's recipe) leaves a GPU mostly idle, and then the loop around the step, not
the network's arithmetic, sets the pace: on an H200, validating ViT+LSTM one trajectory at a time took 60 % of
an epoch. Benchmarks time the step alone; these two columns time the run itself, for every epoch of every slot.
"""

from __future__ import annotations

import time

from lightning.pytorch.callbacks import Callback


class EpochTimes(Callback):
    """Logs per epoch ``time/train_s`` (seconds from the epoch's start to its end, less validation) and
    ``time/val_s`` (seconds in the epoch's validation loops; the sanity check before the first epoch is not
    counted)."""

    def __init__(self) -> None:
        self._epoch_start = 0.0
        self._val_start: float | None = None
        self._val_s = 0.0

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._epoch_start = time.monotonic()
        self._val_s = 0.0

    def on_validation_start(self, trainer, pl_module) -> None:
        self._val_start = None if trainer.sanity_checking else time.monotonic()

    def on_validation_end(self, trainer, pl_module) -> None:
        if self._val_start is not None:
            self._val_s += time.monotonic() - self._val_start
            self._val_start = None

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        # Lightning runs the epoch's validation before this hook: the epoch's whole time is known here
        epoch_s = time.monotonic() - self._epoch_start
        pl_module.log("time/train_s", epoch_s - self._val_s, on_step=False, on_epoch=True)
        pl_module.log("time/val_s", self._val_s, on_step=False, on_epoch=True)
