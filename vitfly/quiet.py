"""Keep third-party banners off vitfly's output; vitfly's own messages, warnings and errors still show.

- :func:`silence_fds` points the process's C-level stdout and stderr (file descriptors 1 and 2) at
  /dev/null for the length of a ``with`` block. pybullet prints ``pybullet build time: ...`` from C
  when it is imported, which ``contextlib.redirect_stdout`` cannot catch (it only swaps the Python
  object ``sys.stdout``).
- :func:`quiet_third_party`, called once when the ``vitfly`` command starts, drops Lightning's
  informational lines (cloud-product tips, "GPU available: False", the mixed-precision line, "Seed
  set to 0") by raising the level of the loggers they come from to WARNING, and filters a short list
  of known third-party warnings by message, category and module. Every other warning still prints.

``VITFLY_VERBOSE=1`` turns both off, for debugging a dependency.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import sys
import warnings
from collections.abc import Iterator

VERBOSE_ENV = "VITFLY_VERBOSE"

# Lightning's info lines all go through these loggers (Lightning gives its package loggers a handler
# of their own at INFO, so they print without any logging set-up). WARNING keeps its warnings and errors.
INFO_LOGGERS = (
    "lightning.pytorch.utilities.rank_zero",  # rank_zero_info: tips, "GPU/TPU available", AMP, "fit stopped"
    "lightning.fabric.utilities.rank_zero",
    "lightning.fabric.utilities.seed",  # "Seed set to 0"
    "lightning.fabric.utilities.distributed",  # "Initializing distributed: GLOBAL_RANK ..." on every rank
    "lightning.pytorch.accelerators.cuda",  # "LOCAL_RANK: 0 - CUDA_VISIBLE_DEVICES: [...]"
    # the same modules under the standalone package names, where those are what gets imported
    "lightning_fabric.utilities.rank_zero",
    "lightning_fabric.utilities.seed",
    "lightning_fabric.utilities.distributed",
    "pytorch_lightning.utilities.rank_zero",
    "pytorch_lightning.accelerators.cuda",
)

_LIGHTNING_MODULES = r"(lightning|pytorch_lightning|lightning_fabric)(\.|$)"

# (message regex, category, module regex): warnings vitfly's own commands trigger by design, or that
# concern Lightning's internals rather than anything the user can change. Categories are the builtin
# parents (Lightning's PossibleUserWarning is a UserWarning) so that starting the CLI imports nothing.
NOISY_WARNINGS: tuple[tuple[str, type[Warning], str], ...] = (
    # the model summary estimates sizes in fp32 under bf16-mixed, which every shipped fit config uses
    (r"Precision .* is not supported by the model summary", UserWarning, _LIGHTNING_MODULES),
    # torch deprecated the LeafSpec class Lightning still checks for; nothing for a user to do
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning, _LIGHTNING_MODULES),
    # short runs (the tiny presets, limit_train_batches) have fewer batches than the logging interval
    (r"The number of training batches \(\d+\) is smaller than the logging interval", UserWarning,
     _LIGHTNING_MODULES),
    # vitfly streams in-process by default: benchmarks/loader_headroom.py measured it at >= 10x what a
    # training step consumes (docs/datasets.md), so few workers are a choice, not a bottleneck
    (r"The '\w+' does not have many workers", UserWarning, _LIGHTNING_MODULES),
)


def verbose() -> bool:
    """True when ``VITFLY_VERBOSE`` asks for third-party output as it comes."""
    return os.environ.get(VERBOSE_ENV, "").strip().lower() not in ("", "0", "false", "no")


def _flush_c_stdio() -> None:
    """Flush C's stdio buffers, so that text a library printf'd inside the block cannot reach the
    restored descriptor when the buffer is flushed later (at exit, or when it fills)."""
    if os.name != "posix":
        return
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):
        pass  # no libc symbols to reach: nothing buffered that we could flush either


def _flush_python_streams() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(AttributeError, OSError, ValueError):
            stream.flush()


@contextlib.contextmanager
def silence_fds(*fds: int) -> Iterator[None]:
    """Send everything written to ``fds`` (default: 1 and 2) to /dev/null inside the block.

    The descriptors are restored on leaving, also when the block raises (the exception, and its
    traceback, print afterwards as usual). A descriptor that is not open is left alone. The
    redirection is process-wide: other threads' output to these descriptors is silenced too, so keep
    the block short (an import, a connect).
    """
    fds = fds or (1, 2)
    if verbose():
        yield
        return
    _flush_python_streams()  # what Python printed before the block belongs outside it
    devnull = os.open(os.devnull, os.O_WRONLY)
    saved: list[tuple[int, int]] = []
    try:
        for fd in fds:
            try:
                copy = os.dup(fd)
            except OSError:
                continue  # not open (a daemon without stderr): nothing to silence
            saved.append((fd, copy))
            os.dup2(devnull, fd)
        yield
    finally:
        _flush_python_streams()
        _flush_c_stdio()
        for fd, copy in reversed(saved):
            os.dup2(copy, fd)
            os.close(copy)
        os.close(devnull)


def quiet_third_party() -> None:
    """Drop Lightning's info lines and the known noisy third-party warnings (idempotent).

    Only the loggers in :data:`INFO_LOGGERS` and the warnings in :data:`NOISY_WARNINGS` are touched;
    warnings from vitfly and any other warning keep the default behaviour.
    """
    if verbose():
        return
    for name in INFO_LOGGERS:
        logging.getLogger(name).setLevel(logging.WARNING)
    for message, category, module in NOISY_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)
