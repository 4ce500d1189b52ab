"""Keep freed memory in the process for reuse (glibc on Linux), so that CPU training stops faulting pages in.

glibc's ``malloc`` serves every block above its mmap threshold (128 KiB, rising to at most 32 MiB) with a
fresh ``mmap`` and gives it back to the kernel on ``free``; it also hands the heap's free top back above its
trim threshold. A training step on a CPU allocates and frees the same large activations every step (one
418-frame trajectory through UNet+LSTM makes feature maps of hundreds of MiB), so every step the kernel maps
them, zero-fills each 4 KiB page on first touch and unmaps them again: about 160,000 page faults a second and
nearly half of the CPU's time in the kernel, measured. vitfly turns glibc's ``mmap`` off for ``malloc``
(every block comes from the heap, whatever its size) and never trims the heap, so freed blocks stay there and
the next step reuses them: a vitfly-arm step of 64 trajectories holds several GiB of activations, more than
any threshold keeps (one set through ``mallopt`` is an ``int``, below 2 GiB). ``benchmarks/cpu_allocator.py``
measures the difference per model.

The price: a process keeps its peak heap instead of returning it, which suits a process that trains or flies
until it ends. Nothing changes where the C library is not glibc, where the user set glibc's own knobs
(``GLIBC_TUNABLES`` naming malloc, or ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` /
``MALLOC_MMAP_MAX_``), or with ``VITFLY_MALLOC=default``.
"""

from __future__ import annotations

import ctypes
import os
import platform

OPT_OUT = "VITFLY_MALLOC"  # =default: leave glibc's allocator as it is
_M_TRIM_THRESHOLD = -1  # mallopt parameters, glibc's <malloc.h>
_M_MMAP_MAX = -4
_NEVER = -1  # M_TRIM_THRESHOLD -1: never trim (mallopt(3))
_ENV_KNOBS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_MAX_")
_applied: bool | None = None  # the outcome of the first call (the setting is process-wide, made once)


def why_not() -> str | None:
    """Why the allocator is left as it is here, or None where :func:`keep_freed_memory` changes it."""
    if os.environ.get(OPT_OUT, "").strip().lower() == "default":
        return f"{OPT_OUT}=default"
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return "not glibc on Linux"
    if "malloc" in os.environ.get("GLIBC_TUNABLES", "") or any(k in os.environ for k in _ENV_KNOBS):
        return "the environment sets glibc's malloc options"
    return None


def keep_freed_memory() -> bool:
    """Serve every block of this process (and of children it forks from now on) from glibc's heap and never
    trim it; True where that is set. Safe to call more than once."""
    global _applied
    if _applied is None:
        _applied = False
        if why_not() is None:
            libc = ctypes.CDLL(None)  # the process's own symbols: glibc's mallopt among them
            # mallopt returns 1 on success; a refused value leaves that setting as it was
            mmap_ok = libc.mallopt(_M_MMAP_MAX, 0)  # no block mapped on its own, so none unmapped on free
            trim_ok = libc.mallopt(_M_TRIM_THRESHOLD, _NEVER)
            _applied = mmap_ok == 1 and trim_ok == 1
    return _applied
