"""A Lightning callback that times training batches, for ``benchmarks/train_speed.py --fit``.

Given to ``vitfly fit`` as ``--trainer.callbacks+=fit_timer.FitTimer`` (this folder on PYTHONPATH), so
the same file times today's code and an older revision alike. Writes, at the end of fit, a JSON list of
``[seconds since fit start at batch end, valid frames in the batch]`` to $VITFLY_FIT_TIMER_OUT (when set;
``train_speed.py``'s loop mode reads ``batches`` in its own process).
"""

from __future__ import annotations

import json
import os
import time

from lightning.pytorch.callbacks import Callback


class FitTimer(Callback):
    def __init__(self) -> None:
        self.start = 0.0
        self.batches: list[list[float]] = []

    def on_fit_start(self, trainer, pl_module) -> None:
        self.start = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.batches.append([time.perf_counter() - self.start, int(batch["mask"].sum())])

    def on_fit_end(self, trainer, pl_module) -> None:
        out = os.environ.get("VITFLY_FIT_TIMER_OUT")  # in-process callers read ``batches`` instead
        if out:
            with open(out, "w") as f:
                json.dump(self.batches, f)
