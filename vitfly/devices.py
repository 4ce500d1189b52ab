"""Torch device names checked against this machine, with one error line that says what to fix."""

from __future__ import annotations

from vitfly.errors import VitflyError


def check_torch_device(device: str, source: str) -> None:
    """VitflyError unless ``device`` ("cpu", "cuda", "cuda:N") names a device this machine has.

    ``source`` names where the value came from (``"--device"``, ``"config: field 'sim_device'"``); the message
    reads "<source> is '<device>'; ...".
    """
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        kind = None  # not a device name at all: the same message as a device of another kind
    if kind not in ("cpu", "cuda"):
        raise VitflyError(f"{source} is {device!r}; expected cpu, cuda or cuda:N")
    where = torch.device(device)
    if where.type == "cuda":
        if not torch.cuda.is_available():
            raise VitflyError(f"{source} is {device!r} but torch sees no CUDA device here; use cpu")
        if where.index is not None and where.index >= torch.cuda.device_count():
            raise VitflyError(f"{source} is {device!r} but only {torch.cuda.device_count()} CUDA device(s) exist")
