"""A Lightning callback for the DDP tests: each rank writes what it trained and validated on.

``--trainer.callbacks+=ddp_probe.SeenBatches`` (with ``tests/`` on PYTHONPATH) writes
``seen_rank<R>.json`` into the run directory: per batch the stage, epoch, ``traj_index`` values and
valid lengths, and per epoch the rank's optimiser step count.
"""

from __future__ import annotations

import json
from pathlib import Path

from lightning.pytorch.callbacks import Callback


class SeenBatches(Callback):
    def __init__(self) -> None:
        self.batches: list[dict] = []
        self.steps_after_epoch: list[int] = []
        self.run_dir: Path | None = None

    def setup(self, trainer, pl_module, stage: str) -> None:
        self.run_dir = Path(trainer.log_dir or trainer.default_root_dir)  # every rank asks: log_dir is a broadcast

    def _record(self, trainer, stage: str, batch) -> None:
        self.batches.append(
            {
                "stage": "sanity" if trainer.sanity_checking else stage,
                "epoch": trainer.current_epoch,
                "traj": batch["traj_index"].tolist(),
                "lengths": batch["mask"].sum(dim=1).tolist(),
            }
        )

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        self._record(trainer, "train", batch)

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx: int, dataloader_idx: int = 0) -> None:
        self._record(trainer, "val", batch)

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self.steps_after_epoch.append(trainer.global_step)

    def on_fit_end(self, trainer, pl_module) -> None:
        out = self.run_dir / f"seen_rank{trainer.global_rank}.json"
        out.write_text(json.dumps({"batches": self.batches, "steps_after_epoch": self.steps_after_epoch}))
