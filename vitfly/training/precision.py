"""The Trainer's precision on the machine at hand: bf16 autocast on a CPU only where oneDNN has bf16 kernels.

The shipped ViT configs train under ``bf16-mixed``, which pays on a GPU and on CPUs with AVX512 (best with
AVX512-BF16 or AMX). A CPU without them (e.g. an AVX2-only AMD EPYC) emulates every bf16 matrix product: the
ViT+LSTM trained 12x slower than in fp32 there (``benchmarks/train_speed.py --modes fp32 bf16``,
docs/performance.md). So a CPU run asked for bf16 autocast trains in fp32 on such a CPU, and says so once.
``VITFLY_CPU_BF16=1`` keeps the emulated bf16 (to study its numerics, not for speed).
"""

from __future__ import annotations

import os
import sys

import torch
from lightning.pytorch.callbacks import Callback

BF16_AUTOCAST = ("bf16-mixed", "bf16")  # Lightning's names for bf16 autocast (bf16-true is left as asked)
FP32 = "32-true"
KEEP_ENV = "VITFLY_CPU_BF16"


def cpu_has_native_bf16() -> bool:
    """Whether oneDNN has bf16 kernels for this CPU (x86: AVX512 or newer, AMX; ARM: its bf16 instructions),
    the check torch's own CPU compiler makes before it uses bf16."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a torch without oneDNN
        return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())


def trains_on_cpu(accelerator: object) -> bool:
    """Whether a Trainer with this ``accelerator`` argument (None: Lightning's "auto") runs on the CPU."""
    if accelerator is None or accelerator == "auto":
        return not (torch.cuda.is_available() or torch.backends.mps.is_available())
    return accelerator == "cpu"


def usable_precision(precision: object, accelerator: object = None, who: str = "vitfly") -> tuple[object, list]:
    """``precision`` as the Trainer should get it here, and the callbacks to give it: ``32-true`` and a
    ``PrecisionNote`` (naming ``who``) for bf16 autocast on a CPU without bf16 kernels, else ``precision`` and
    none."""
    if str(precision) not in BF16_AUTOCAST or not trains_on_cpu(accelerator):
        return precision, []
    if os.environ.get(KEEP_ENV) == "1" or cpu_has_native_bf16():
        return precision, []
    note = (f"{who}: this CPU has no bf16 kernels (they need AVX512 or AMX), so precision {precision} would be "
            f"emulated, several times slower; running in fp32 ({FP32}) instead ({KEEP_ENV}=1 keeps bf16)")
    return FP32, [PrecisionNote(note)]


def trainer_precision(trainer_kwargs: dict, who: str = "vitfly") -> tuple[dict, list]:
    """``trainer_kwargs`` (a new dict) with its precision made usable here, and the callbacks to add
    (``usable_precision``)."""
    if "precision" not in trainer_kwargs:
        return dict(trainer_kwargs), []
    precision, callbacks = usable_precision(trainer_kwargs["precision"], trainer_kwargs.get("accelerator"), who)
    return {**trainer_kwargs, "precision": precision}, callbacks


class PrecisionNote(Callback):
    """Says once, on standard error, which precision runs instead of the one asked for. It speaks at ``setup``,
    once the data and the network are ready, so that a run refused before then prints its error alone."""

    def __init__(self, note: str) -> None:
        self.note = note

    def setup(self, trainer, pl_module, stage: str) -> None:
        if self.note and trainer.is_global_zero:
            print(self.note, file=sys.stderr)
        self.note = ""
