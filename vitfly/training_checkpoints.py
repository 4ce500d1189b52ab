"""``checkpoints/last.ckpt``: the training state at the end of every epoch, the one to resume from.

Lightning 2.6's ``ModelCheckpoint(save_last=True)`` refreshes ``last.ckpt`` only in a step where it also
saves its top-k checkpoint, i.e. only when the monitored validation loss improves; resuming from it would
silently repeat the epochs since. vitfly therefore runs two checkpoint callbacks into one directory:
``best.ckpt`` (``ModelCheckpoint`` monitoring ``val/loss``, no ``save_last``) and ``LastCheckpoint`` below.
"""

from __future__ import annotations

import os

from lightning.pytorch.callbacks import ModelCheckpoint

LAST_NAME = ModelCheckpoint.CHECKPOINT_NAME_LAST  # last.ckpt: the name `ckpt_path="last"` looks for


class LastCheckpoint(ModelCheckpoint):
    """Write ``dirpath/last.ckpt`` at the end of every training epoch, overwriting the previous one.

    It saves at the end of the training epoch whether or not validation ran in that epoch, so an epoch cut
    short by ``max_steps`` or ``max_time`` is saved too. Its own class gives it a checkpoint state key apart
    from the best-checkpoint ``ModelCheckpoint``'s, whatever that one monitors. Put it after that one in the
    callback list: the ``last.ckpt`` of an epoch then records the best checkpoint's updated score.
    """

    def __init__(self, dirpath: str | os.PathLike | None = None):
        super().__init__(
            dirpath=dirpath,  # None: the logger's run directory, as ModelCheckpoint resolves it
            filename=LAST_NAME,
            monitor=None,  # keep the latest epoch, whatever its loss
            save_top_k=1,
            save_on_train_epoch_end=True,
            auto_insert_metric_name=False,
            enable_version_counter=False,  # overwrite last.ckpt instead of writing last-v1.ckpt
        )
