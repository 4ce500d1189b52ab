"""``checkpoints/last.ckpt``: the training state at the end of every epoch, the one to resume from.

Lightning 2.6's ``ModelCheckpoint(save_last=True)`` refreshes ``last.ckpt`` only in a step where it also
saves its top-k checkpoint, i.e. only when the monitored validation loss improves; resuming from it would
silently repeat the epochs since. vitfly therefore runs two checkpoint callbacks into one directory:
``best.ckpt`` (``ModelCheckpoint`` monitoring ``val/loss``, no ``save_last``) and ``LastCheckpoint`` below.
``RngState`` adds what Lightning leaves out of a checkpoint for an exact resume: the random generators.
"""

from __future__ import annotations

import os

from lightning.pytorch.callbacks import Callback, ModelCheckpoint

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


class RngState(Callback):
    """The global random generators' state in every checkpoint, restored on resume.

    Lightning checkpoints the weights, the optimiser and the loops but not the generators, and ``train_policy``
    seeds them afresh at every start: a resumed run would draw other dropout masks (ViT+LSTM's LSTM dropout)
    than an uninterrupted one. The state is taken when a checkpoint is written (``last.ckpt``: at the end of
    an epoch) and set back before the resumed fit creates its first data-loader iterator, as in the run that
    went on. CUDA states are restored only on a machine with as many CUDA devices; a move between CPU and GPU
    keeps the CPU generator and draws the rest afresh.
    """

    def state_dict(self) -> dict:
        import random

        import numpy as np
        import torch

        kind, keys, pos, has_gauss, gauss = np.random.get_state()
        state = {"torch": torch.get_rng_state(), "python": random.getstate(),
                 "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, gauss]}
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            state["cuda"] = torch.cuda.get_rng_state_all()
        return state

    def load_state_dict(self, state: dict) -> None:
        import random

        import numpy as np
        import torch

        torch.set_rng_state(state["torch"])
        random.setstate(state["python"])
        kind, keys, pos, has_gauss, gauss = state["numpy"]
        np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
        cuda = state.get("cuda")
        if cuda is not None and torch.cuda.is_available() and torch.cuda.device_count() == len(cuda):
            torch.cuda.set_rng_state_all(cuda)
