"""Training from Python: the same PolicyModule / TrajectoryDataModule / Trainer set-up as ``vitfly fit``.

``train_policy(data_path, model, ...)`` is what ``vitfly pipeline`` and ``vitfly ablate`` call; the
shared pieces (checkpoint callback, progress bar, wandb default) are used by ``vitfly.training.cli``.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

from vitfly.errors import VitflyError
from vitfly.training.metrics_csv import join as join_metrics
from vitfly.training.metrics_csv import set_aside as set_metrics_aside

MONITOR = "val/loss"
BEST_NAME = "best"  # checkpoints/best.ckpt: the lowest validation loss so far
CHECKPOINT_DIR = "checkpoints"
SELECT = ("best", "last")  # which epoch a training hands on to be flown
# Lightning's warnings about a run folder that already holds files: train_policy's folders do by design
_RUN_FOLDER_WARNINGS = (r"Experiment logs directory .* exists and is not empty",
                        r"Checkpoint directory .* exists and is not empty")


def checkpoint_defaults() -> dict[str, Any]:
    """ModelCheckpoint arguments for the best checkpoint, best.ckpt (fixed name).

    last.ckpt comes from a second callback, ``vitfly.training.checkpoints.LastCheckpoint``: Lightning's own
    ``save_last`` refreshes it only when the validation loss improves.
    """
    return {
        "monitor": MONITOR,
        "mode": "min",
        "save_top_k": 1,
        "save_last": False,
        "filename": BEST_NAME,
        "auto_insert_metric_name": False,
        "enable_version_counter": False,  # overwrite best.ckpt instead of writing best-v1.ckpt
    }


def default_wandb_offline() -> None:
    """wandb stays offline unless the user has chosen a mode (WANDB_MODE=online to sync)."""
    os.environ.setdefault("WANDB_MODE", "offline")


def finish_wandb() -> None:
    """Close a wandb run if one was started, so the next run in this process starts clean."""
    import sys

    wandb = sys.modules.get("wandb")
    if wandb is not None and getattr(wandb, "run", None) is not None:
        wandb.finish()


def train_policy(
    data_path: str | os.PathLike,
    model: str,
    out_dir: str | os.PathLike,
    use_state: bool = True,
    max_epochs: int = 100,
    batch_size: int = 4,
    val_fraction: float = 0.2,
    seed: int = 0,
    policy_kwargs: dict | None = None,
    data_kwargs: dict | None = None,
    trainer_kwargs: dict | None = None,
    progress_bar: bool = True,
    callbacks: list | None = None,
    init_weights: str | os.PathLike | None = None,
    select: str = "best",
) -> Path:
    """Train ``model`` on ``data_path``; returns the path of the checkpoint to fly: with ``select="best"`` the
    epoch of lowest validation loss (last if no validation), with ``select="last"`` the final epoch (the
    original ViTfly code flies the model its last epoch saved; no best.ckpt is kept then).

    Writes ``out_dir/checkpoints/{best,last}.ckpt``, ``out_dir/metrics.csv`` and ``out_dir/split.json``; while it
    trains, another process calling it on the same ``out_dir`` gets ``vitfly.training.run_lock.RunBusy``.
    An interrupted run resumes from ``out_dir/checkpoints/last.ckpt`` when called again with the same
    arguments, as the uninterrupted run would have gone on (the random generators' state travels in the
    checkpoint: ``vitfly.training.checkpoints.RngState``); a finished run returns at once. The split is frozen
    in ``out_dir/split.json``: a later call on a dataset that grew keeps the validation trajectories and trains
    on the new ones as well.
    ``policy_kwargs`` go to PolicyModule (e.g. lr, tbptt_steps), ``data_kwargs`` to TrajectoryDataModule,
    ``trainer_kwargs`` to lightning.Trainer, ``callbacks`` join the Trainer's (e.g.
    ``vitfly.workflows.closed_loop_check.ClosedLoopCheck``). ``init_weights`` (a checkpoint of the same network,
    e.g. the previous DAgger round's) starts the network from those weights instead of a random initialisation:
    a fine-tune with a fresh optimiser and learning-rate schedule. It applies to a fresh run only; a run that
    resumes from ``last.ckpt`` already holds them.
    """
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint, RichProgressBar
    from lightning.pytorch.loggers import CSVLogger

    from vitfly.datamodules.datamodule import TrajectoryDataModule
    from vitfly.host_memory import keep_freed_memory
    from vitfly.training.checkpoints import LastCheckpoint, RngState
    from vitfly.training.epoch_times import EpochTimes
    from vitfly.training.precision import trainer_precision
    from vitfly.training.run_lock import run_lock
    from vitfly.zoo.policy import create_policy

    if select not in SELECT:
        raise VitflyError(f"select: expected one of {', '.join(SELECT)}, got {select!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    keep_freed_memory()  # on a CPU, large activations reused step after step rather than mapped afresh
    with run_lock(out_dir):  # one process per run folder: a second one is told who trains it
        L.seed_everything(seed, verbose=False)
        policy = create_policy(model, use_state=use_state, **(policy_kwargs or {}))
        data = TrajectoryDataModule(
            str(data_path),
            batch_size=batch_size,
            val_fraction=val_fraction,
            split_seed=seed,
            use_state=use_state,
            **(data_kwargs or {}),
        )
        ckpt_dir = out_dir / CHECKPOINT_DIR
        checkpoint = ModelCheckpoint(dirpath=ckpt_dir, **checkpoint_defaults()) if select == "best" else None
        # best first: Trainer.checkpoint_callback (ckpt_path="best") is the first ModelCheckpoint
        bar = [RichProgressBar()] if progress_bar else []
        trainer_kwargs, notes = trainer_precision(trainer_kwargs or {}, f"train {model}")  # bf16 only where it pays
        # RngState: a resumed run draws the dropout masks the uninterrupted one would have drawn
        callbacks = [*([checkpoint] if checkpoint else []), LastCheckpoint(ckpt_dir), RngState(), EpochTimes(), *bar,
                     *(callbacks or []), *notes]
        trainer = L.Trainer(
            max_epochs=max_epochs,
            default_root_dir=out_dir,
            logger=CSVLogger(save_dir=out_dir, name="", version=""),
            callbacks=callbacks,
            enable_progress_bar=progress_bar,
            # the datamodule's batch sampler shards itself across DDP ranks (trainer_kwargs strategy="ddp", devices=N)
            **{"enable_model_summary": False, "use_distributed_sampler": False, **trainer_kwargs},
        )
        last = ckpt_dir / "last.ckpt"
        if last.exists():
            _check_same_run(last, model, use_state)
            # CSVLogger empties metrics.csv on a resume: the curve so far waits beside it
            set_metrics_aside(out_dir, _epochs_done(last))
        elif init_weights is not None:
            load_initial_weights(policy, init_weights, model, use_state)
        try:
            with warnings.catch_warnings():
                # the folder is the run's own: data.json and split.json sit beside the logs by design, and a
                # resume's earlier metrics wait aside (joined below), so Lightning's "will be deleted" is not so
                for message in _RUN_FOLDER_WARNINGS:
                    warnings.filterwarnings("ignore", message=message, category=UserWarning)
                trainer.fit(policy, datamodule=data, ckpt_path=str(last) if last.exists() else None, weights_only=True)
        finally:
            join_metrics(out_dir)
        best = checkpoint.best_model_path if checkpoint else ""
        path = Path(best) if best else last
        if best and not path.exists() and last.exists():
            raise BestCheckpointMissing(path)
        if not path.exists():
            raise VitflyError(f"{out_dir}: training ended without writing a checkpoint (max_epochs={max_epochs})")
        return path


class BestCheckpointMissing(VitflyError):
    """Training finished, but the best checkpoint its callback names is not on disk: the run was resumed without
    it (a GPU slot's carry leaves best.ckpt at home, ``scripts/gpu_reproduce.py``) and no later epoch beat it."""

    def __init__(self, path: Path):
        super().__init__(f"{path}: the best checkpoint is not here (the run was resumed without it) and no epoch "
                         "since was better; it is where the run came from")
        self.path = path


def load_initial_weights(policy, path: str | os.PathLike, model: str, use_state: bool) -> None:
    """Copy the network weights of ``path`` into ``policy.net``: a checkpoint of the same network, or
    ``pretrained:NAME`` (the shipped weights); one line if it holds another network."""
    from vitfly.zoo.pretrained import load_weights, weights_identity

    stored = weights_identity(path)
    if (stored["model"], stored["use_state"]) != (model, use_state):
        raise VitflyError(
            f"{path}: init_weights holds model {stored['model']!r} (use_state={stored['use_state']}), "
            f"not {model!r} (use_state={use_state})"
        )
    policy.net.load_state_dict(load_weights(path).state_dict())


def _epochs_done(last: Path) -> int:
    """Epochs finished by ``last.ckpt`` (memory-mapped: only its header is read)."""
    import torch

    return int(torch.load(last, map_location="cpu", weights_only=True, mmap=True)["epoch"]) + 1


def _check_same_run(last: Path, model: str, use_state: bool) -> None:
    """Refuse to resume a run of another network (its weights would not load)."""
    import torch

    hparams = torch.load(last, map_location="cpu", weights_only=True).get("hyper_parameters", {})
    stored = (hparams.get("model"), hparams.get("use_state"))
    if stored != (model, use_state):
        raise VitflyError(
            f"{last}: holds a run of model {stored[0]!r} (use_state={stored[1]}), not {model!r} "
            f"(use_state={use_state}); choose another output directory"
        )
