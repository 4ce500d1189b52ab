"""Where an epoch's wall time goes: ``time/train_s`` and ``time/val_s`` in every epoch's row of metrics.csv.

A one-trajectory step (the paper's recipe) leaves a GPU mostly idle, and then the loop around the step, not
the network's arithmetic, sets the pace: on an H200, validating ViT+LSTM one trajectory at a time took 60 % of
an epoch. Benchmarks time the step alone; these two columns time the run itself, for every epoch of every slot.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from lightning.pytorch.callbacks import Callback


class ValidationClock:
    """Seconds spent in validation loops since the last ``take``; the sanity check before the first epoch is not
    counted. Call ``start``/``stop`` from a callback's ``on_validation_start``/``on_validation_end``."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._since: float | None = None
        self._total_s = 0.0

    def start(self, trainer) -> None:
        self._since = None if trainer.sanity_checking else self.clock()

    def stop(self) -> None:
        if self._since is not None:
            self._total_s += self.clock() - self._since
            self._since = None

    def take(self) -> float:
        """The seconds counted so far; the count starts again from 0."""
        total, self._total_s = self._total_s, 0.0
        return total


class EpochTimes(Callback):
    """Logs per epoch ``time/train_s`` (seconds from the epoch's start to its end, less validation) and
    ``time/val_s`` (seconds in the epoch's validation loops; the sanity check before the first epoch is not
    counted)."""

    def __init__(self) -> None:
        self._epoch_start = 0.0
        self._validation = ValidationClock()

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._epoch_start = time.monotonic()
        self._validation.take()

    def on_validation_start(self, trainer, pl_module) -> None:
        self._validation.start(trainer)

    def on_validation_end(self, trainer, pl_module) -> None:
        self._validation.stop()

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        # Lightning runs the epoch's validation before this hook: the epoch's whole time is known here
        epoch_s = time.monotonic() - self._epoch_start
        val_s = self._validation.take()
        pl_module.log("time/train_s", epoch_s - val_s, on_step=False, on_epoch=True)
        pl_module.log("time/val_s", val_s, on_step=False, on_epoch=True)
