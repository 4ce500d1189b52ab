"""``torch.compile`` for the zoo's image encoders, with an eager fallback where the platform cannot compile.

``compile_encoder(net)`` compiles ``net.encode`` (the image encoder, where nearly all of a network's
arithmetic is) in place and returns the same network: parameter names, state dicts and the call
contract are unchanged, the recurrent head stays eager (its per-step matrix products are too small for
code generation to matter). The number of frames per call is marked dynamic, so the variable-length
last TBPTT chunk and a varying number of simulated drones do not each trigger a recompilation.

Where no compiler is available (no C++ compiler for the CPU backend, no Triton for CUDA) or the first
compilation fails, one warning is logged and the encoder runs eagerly.

``mode="reduce-overhead"`` records CUDA graphs of the compiled encoder (forward and backward): one graph
per distinct frame count, replayed with a single launch, which is what a launch-bound step (one trajectory
per optimiser step) needs. It is meant for static shapes (the policy's ``static_shapes`` with the
datamodule's ``time_bucket_steps``: a few frame counts, each recorded once). CUDA graphs exist only on
CUDA: on another device that mode runs the encoder eagerly (one warning), so a CUDA recipe still trains on
a CPU without minutes of compilation.
"""

from __future__ import annotations

import logging
import os
import shutil
import warnings
from collections.abc import Callable

import torch
from torch import nn

log = logging.getLogger(__name__)

_WARNED: set[str] = set()
# what a missing or broken toolchain raises at the first call (errors of the network itself propagate)
_COMPILE_ERRORS: tuple[type[BaseException], ...] = (torch._dynamo.exc.BackendCompilerFailed, OSError)
try:
    from torch._inductor.exc import InductorError

    _COMPILE_ERRORS += (InductorError,)
except ImportError:
    pass


def _warn_once(message: str) -> None:
    if message not in _WARNED:
        _WARNED.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def compiler_missing(device_type: str = "cpu") -> str | None:
    """Why ``torch.compile`` cannot generate code for ``device_type`` here (None: it can)."""
    if not hasattr(torch, "compile"):
        return "this PyTorch has no torch.compile"
    if device_type == "cuda":
        try:
            from torch.utils._triton import has_triton
        except ImportError:
            return "Triton is not installed"
        return None if has_triton() else "Triton is not installed"
    if device_type != "cpu":
        return f"no compiler backend for device {device_type!r}"
    candidates = [os.environ.get("CXX"), "g++", "clang++", "c++"]
    if not any(shutil.which(c) for c in candidates if c):
        return "no C++ compiler found (set CXX or install g++)"
    return None


CUDA_ONLY_MODES = ("reduce-overhead",)  # torch.compile modes that exist for their CUDA graphs


class _CompiledOrEager:
    """Calls the compiled function; on a compilation failure warns once and calls the eager one from then on.

    ``cuda_only``: off CUDA, call the eager function (one warning per device type).
    """

    def __init__(self, eager: Callable, compiled: Callable, name: str, cuda_only: bool = False,
                 generates_code: bool = True) -> None:
        self.eager = eager
        self.compiled = compiled
        self.name = name
        self.failed = False
        self.cuda_only = cuda_only
        self.generates_code = generates_code  # inductor needs a C++ compiler / Triton; aot_eager and eager do not

    def __call__(self, frames: torch.Tensor) -> torch.Tensor:
        if self.failed:
            return self.eager(frames)
        if self.cuda_only and frames.device.type != "cuda":
            _warn_once(f"torch.compile mode reduce-overhead (CUDA graphs) needs a CUDA device; {self.name} runs "
                       f"eagerly on {frames.device.type}")
            return self.eager(frames)
        reason = compiler_missing(frames.device.type) if self.generates_code else None
        if reason is not None:
            self._fall_back(reason)
            return self.eager(frames)
        # frames per call vary (last TBPTT chunk, padding removed, drones in flight): one graph for all counts
        torch._dynamo.maybe_mark_dynamic(frames, 0)
        try:
            return self.compiled(frames)
        except _COMPILE_ERRORS as err:
            self._fall_back(f"compilation failed ({type(err).__name__}: {str(err).splitlines()[0][:200]})")
            return self.eager(frames)

    def _fall_back(self, reason: str) -> None:
        self.failed = True
        _warn_once(f"torch.compile unavailable for {self.name}: {reason}; running it eagerly")


def compile_encoder(net: nn.Module, **compile_kwargs) -> nn.Module:
    """Compile ``net.encode`` in place (see the module docstring); returns ``net``. Idempotent.

    ``compile_kwargs`` go to ``torch.compile`` (e.g. ``mode="max-autotune"``; ``mode="reduce-overhead"``: CUDA
    graphs on CUDA, eager elsewhere).
    """
    encode = getattr(net, "encode", None)
    if encode is None:
        raise TypeError(f"{type(net).__name__} has no encode method to compile")
    if isinstance(encode, _CompiledOrEager):
        return net
    name = f"{type(net).__name__}.encode"
    cuda_only = compile_kwargs.get("mode") in CUDA_ONLY_MODES
    generates_code = compile_kwargs.get("backend", "inductor") == "inductor"
    net.encode = _CompiledOrEager(encode, torch.compile(encode, **compile_kwargs), name, cuda_only, generates_code)
    return net


def is_compiled(net: nn.Module) -> bool:
    """True when ``compile_encoder`` was applied to ``net`` (whether or not it fell back to eager)."""
    return isinstance(getattr(net, "encode", None), _CompiledOrEager)
