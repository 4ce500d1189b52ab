"""Resume states of runs that ``scripts/gpu.py train`` trains across GPU slots: what travels, and how it is
checked and put back in place (packing and unpacking: ``scripts/gpu_pack.py``).

An unfinished run travels as its run directory: ``checkpoints/last.ckpt`` (the Lightning checkpoint of its last
finished epoch: fp32 weights, the Adam moments, loop and callback state, the random generators' state),
``checkpoints/best.ckpt`` (the best epoch so far, network weights in fp16, as every returned run's), metrics,
split and ``unfinished.json``, the marker this module writes and reads (epochs done, data hash, slots so far).
It goes back lean, kept in the repository (``scripts/gpu_carry.py``): without best.ckpt where the preset flies its
last epoch, beside a working tree that takes half of the call's 64 MiB (``travelling_bytes``).
Checkpoints are taken at epoch ends only: Lightning resumes an epoch-end checkpoint exactly, a mid-epoch one
replays batches.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

from lightning.pytorch.callbacks import Callback

from scripts.gpu_pack import safe_extract, tree_bytes  # noqa: F401  (one unpacking path; the tests call it here)
from vitfly.training.epoch_times import ValidationClock
from vitfly.training.metrics_csv import set_aside

MARKER = "unfinished.json"
CARRY_BYTES = 64 * 2**20  # what the device tool carries to the machine, all paths together
# room a plan keeps for .whl/ before `gpu.py wheels` has fetched it (a new checkout): 1.2 MiB on 2026-12-05
WHEELS_RESERVE = 2 * 2**20
MOMENTS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")  # Adam's per-parameter state besides `step`
DROPPED_KEYS = ("optimizer_states", "lr_schedulers", "callbacks", "loops")  # resume state, not the network
RUN_FILES = ("metrics.csv", "split.json", "cost.json", "hparams.yaml", "data.json")  # what travels besides checkpoints


class SlotEnded(Exception):
    """Raised at an epoch start to end a run's slot cleanly: the previous epoch's last.ckpt is on disk."""


def stop_reason(now: float, stop_at: float | None, epoch_s: float | None, trained: int,
                max_epochs_this_slot: int | None) -> str | None:
    """Why a run should not start another epoch in this slot (None: it should)."""
    if max_epochs_this_slot is not None and trained >= max_epochs_this_slot:
        return f"{trained} epochs this slot (--stop-after-epochs)"
    if stop_at is not None and epoch_s is not None and now + epoch_s > stop_at:
        return f"another epoch (about {epoch_s:.0f} s) would end after the slot's deadline"
    return None


def steady_epoch_s(measured: list[float]) -> float:
    """The epoch length to plan with: the longest measured epoch, the first left out once there is a second (it
    carries the compilation and CUDA-graph capture)."""
    return max(measured[1:] or measured)


def next_epoch_s(measured: list[float], val_s: list[float], validates: bool | None,
                 hint_s: float | None = None) -> float:
    """The length of the epoch about to start, from this slot's epochs (``measured``: wall seconds; ``val_s``: the
    validation in each): the longest training part (``steady_epoch_s``), plus the longest validation if this epoch
    validates. A run that validates every 5th epoch (the ``paper`` preset) thus judges four epochs of five by
    their training alone. ``validates`` None (not known): the longest whole epoch. A validating epoch before any
    validation was measured here adds the slot's ``hint_s`` (the previous slot's epoch) at most."""
    if validates is None:
        return steady_epoch_s(measured)
    train_s = steady_epoch_s([m - v for m, v in zip(measured, val_s, strict=True)])
    if not validates:
        return train_s
    validations = [v for v in val_s if v > 0]
    if validations:
        return train_s + steady_epoch_s(validations)
    return max(train_s, hint_s or 0.0)


def epoch_validates(trainer) -> bool | None:
    """Whether the epoch the trainer is about to run ends with a validation (None: not known)."""
    if trainer is None or trainer.check_val_every_n_epoch is None:  # None: validation counted in steps
        return None
    return bool(trainer.enable_validation) and (trainer.current_epoch + 1) % trainer.check_val_every_n_epoch == 0


class SlotStop(Callback):
    """Ends training at an epoch start when the next epoch would not finish before ``stop_at`` (a Unix time),
    or after ``max_epochs_this_slot`` epochs. ``epoch_s``: the expected epoch length before one is measured
    here (the previous slot's); then this slot's epochs say (``next_epoch_s``): the longest training part,
    plus the longest validation where the next epoch validates, leaving out the slot's first epoch once a
    second is measured: the first carries the one-off compile and CUDA-graph capture (97 s against 37 s for the
    paper arm's ViT+LSTM on an H100), which would otherwise cost a slot its last epoch."""

    def __init__(self, stop_at: float | None, max_epochs_this_slot: int | None, epoch_s: float | None = None):
        self.stop_at, self.max_epochs_this_slot, self.epoch_s = stop_at, max_epochs_this_slot, epoch_s
        self.hint_s = epoch_s
        self.trained, self._started = 0, None
        self.measured, self.val_s = [], []  # this slot's epochs: wall seconds, and the validation's in each
        self._validation = ValidationClock(lambda: time.time())  # late-bound: the tests set the clock

    def on_validation_start(self, trainer, pl_module) -> None:
        self._validation.start(trainer)

    def on_validation_end(self, trainer, pl_module) -> None:
        self._validation.stop()

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        now = time.time()
        if self._started is not None:
            self.trained += 1
            self.measured.append(now - self._started)
            self.val_s.append(self._validation.take())
            self.epoch_s = next_epoch_s(self.measured, self.val_s, epoch_validates(trainer), self.hint_s)
        reason = stop_reason(now, self.stop_at, self.epoch_s, self.trained, self.max_epochs_this_slot)
        if reason:
            raise SlotEnded(reason)
        self._started = now


def compact_moments(checkpoint: dict, dtype: str) -> dict:
    """Adam's moments in ``dtype`` (``fp32``: as they are; ``bf16``: half the bytes, fp32's exponent range, 8
    significant bits). ``torch.optim`` casts them back to the parameters' dtype when the run resumes."""
    import torch

    if dtype == "fp32":
        return checkpoint
    for opt in checkpoint.get("optimizer_states", []):
        for state in opt["state"].values():
            for key in MOMENTS:
                if key in state:
                    state[key] = state[key].to(torch.bfloat16)
    return checkpoint


def moved(path, old: str, new: str):
    if not isinstance(path, str) or not old:
        return path
    if path == old:
        return new
    return new + path[len(old):] if path.startswith(old + os.sep) else path


def relocate(checkpoint: dict, ckpt_dir: Path) -> dict:
    """Point the checkpoint callbacks' state at ``ckpt_dir``. ModelCheckpoint forgets its best score when the
    directory it saved from differs from its own, and would then take the next epoch as the best."""
    new = os.path.realpath(ckpt_dir)  # as ModelCheckpoint resolves its dirpath
    for state in checkpoint.get("callbacks", {}).values():
        old = state.get("dirpath") if isinstance(state, dict) else None
        if not isinstance(old, str):
            continue
        for key in ("dirpath", "best_model_path", "kth_best_model_path", "last_model_path"):
            if key in state:
                state[key] = moved(state[key], old, new)
        if isinstance(state.get("best_k_models"), dict):
            state["best_k_models"] = {moved(k, old, new): v for k, v in state["best_k_models"].items()}
    return checkpoint


def save_atomic(obj: dict, path: Path) -> None:
    import torch

    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def relocate_file(last: Path) -> None:
    import torch

    save_atomic(relocate(torch.load(last, map_location="cpu", weights_only=True), last.parent), last)


def epochs_done(run_dir: Path) -> int:
    """Epochs finished by the run's last.ckpt (0 without one); memory-mapped, so only the header is read."""
    import torch

    last = run_dir / "checkpoints" / "last.ckpt"
    if not last.exists():
        return 0
    return int(torch.load(last, map_location="cpu", weights_only=True, mmap=True)["epoch"]) + 1


def read_marker(run_dir: Path) -> dict:
    path = run_dir / MARKER
    try:
        marker = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise SystemExit(f"{path}: not a readable resume marker ({err})") from None
    for key in ("label", "preset", "dataset_hash", "epochs", "slots"):
        if key not in marker:
            raise SystemExit(f"{path}: field {key!r} missing; expected a marker written by scripts/gpu.py train")
    return marker


def set_metrics_aside(run_dir: Path) -> None:
    """Before a run resumes: its metrics so far into metrics.earlier.csv, which the packing joins again."""
    set_aside(run_dir, epochs_done(run_dir))


def travelling_bytes(root: Path, leave_out: Path | list[Path] | None = None) -> int:
    """What every device call sends besides what it carries: the working tree (tracked files and untracked ones
    git does not ignore) and the carried wheels (``.whl/``); without the files under ``leave_out`` (a folder or
    several: the carry, part of the tree, planned apart, and the carries that stay here)."""
    listed = subprocess.run(["git", "-C", str(root), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            capture_output=True)
    if listed.returncode != 0:  # the device tool sends a git checkout: so does the plan of what it sends
        raise SystemExit(f"{root}: not a git checkout (git ls-files: {listed.stderr.decode().strip()[:200]}); the "
                         "slot plan counts the working tree the device tool sends")
    listed = listed.stdout.split(b"\0")
    files = [root / os.fsdecode(f) for f in listed if f]
    for folder in [leave_out] if isinstance(leave_out, Path) else leave_out or []:
        files = [f for f in files if not f.resolve().is_relative_to(folder.resolve())]
    return sum(f.stat().st_size for f in files if f.is_file()) + tree_bytes(root / ".whl") * (root / ".whl").exists()


def wheels_reserve(root: Path) -> int:
    """Room a slot's plan keeps for ``.whl/``: none once the wheels are here (``travelling_bytes`` counts them),
    ``WHEELS_RESERVE`` before ``gpu.py wheels`` has fetched them, since every call carries them."""
    return 0 if (root / ".whl").exists() else WHEELS_RESERVE


def mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def copy_run(src: Path, dst: Path) -> None:
    """``src`` as ``dst`` (a stale ``dst`` replaced); nothing to do when they are the same folder."""
    if dst.exists() and dst.resolve() == src.resolve():
        return
    if dst.exists():
        shutil.rmtree(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(src, dst)


def slim(src: Path, half: bool = True) -> dict:
    """Checkpoint ``src`` without optimiser/loop state, its state dict only the network's weights, floating ones
    in fp16 (``half=False``: as they are)."""
    import torch

    from vitfly.zoo.checkpoint import NET_PREFIX, network_from_checkpoint_dict
    from vitfly.zoo.pretrained import fp16_state_dict

    obj = torch.load(src, map_location="cpu", weights_only=True)
    for key in DROPPED_KEYS:
        obj.pop(key, None)
    net = network_from_checkpoint_dict(obj, str(src))
    if half:
        obj["state_dict"] = {NET_PREFIX + k: v for k, v in fp16_state_dict(net, str(src)).items()}
    else:  # the network's tensors as stored, their dtypes kept
        obj["state_dict"] = {NET_PREFIX + k: obj["state_dict"][NET_PREFIX + k] for k in net.state_dict()}
    return obj


def returned_hash(run: Path) -> str | None:
    if (run / "done.json").exists():
        return (json.loads((run / "done.json").read_text()).get("trained_on") or {}).get("dataset_hash")
    if (run / MARKER).exists():
        return json.loads((run / MARKER).read_text()).get("dataset_hash")
    raise SystemExit(f"{run}: neither done.json nor {MARKER}; not a run packed by scripts/gpu.py train")


def copy_run_files(d: Path, dst: Path, epochs: int | None) -> None:
    """Metrics (earlier slots' rows joined, rows of an unfinished epoch dropped), split, cost, hparams."""
    from vitfly.training.metrics_csv import EARLIER_METRICS, merge_metrics

    merge_metrics([d / EARLIER_METRICS, d / "metrics.csv"], dst / "metrics.csv", epochs)
    for name in RUN_FILES[1:]:
        if (d / name).exists():
            shutil.copy(d / name, dst / name)
