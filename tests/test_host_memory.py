"""vitfly.host_memory: freed blocks stay in the process, so touching a reused block faults no page in."""

from __future__ import annotations

import ctypes
import os
import platform
import subprocess
import sys
import textwrap

import pytest

from vitfly import host_memory

BLOCK_BYTES = 64 << 20  # above glibc's largest dynamic mmap threshold (32 MiB): mapped afresh by default
PAGES = BLOCK_BYTES // 4096

# malloc, touch and free a block, then count the minor page faults of touching a second one of the same size
# (plain malloc: numpy and torch may ask the kernel for huge pages, which would hide the faults)
CHILD = textwrap.dedent(f"""
    import ctypes, resource
    {{setup}}
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    def touch():
        block = libc.malloc({BLOCK_BYTES})
        ctypes.memset(block, 1, {BLOCK_BYTES})
        return block
    libc.free(touch())
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    kept = touch()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
""")

glibc_only = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's allocator only"
)
# mallinfo2 came with glibc 2.33 (Debian 11's 2.31 lacks it; an image built FROM an older base skips that test)
with_mallinfo2 = pytest.mark.skipif(
    platform.libc_ver()[0] != "glibc" or not hasattr(ctypes.CDLL(None), "mallinfo2"), reason="glibc >= 2.33"
)


# malloc a 1.25 GiB block without touching it (no page is faulted in) and print the bytes glibc mapped on their
# own for it (mallinfo2's hblkhd, glibc >= 2.33): above vitfly's former 1 GiB mmap threshold
BIG_BYTES = 5 << 28
BIG_CHILD = textwrap.dedent(f"""
    import ctypes
    {{setup}}
    class Mallinfo2(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in
                    "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.mallinfo2.restype = Mallinfo2
    before = libc.mallinfo2().hblkhd  # blocks mapped while Python started
    block = libc.malloc({BIG_BYTES})
    assert block
    print(libc.mallinfo2().hblkhd - before)
""")
# the setup lines of a child: vitfly's setting, or glibc as it comes
KEEP = "from vitfly.host_memory import keep_freed_memory; assert keep_freed_memory()"
# under VITFLY_MALLOC=default
AS_GLIBC_COMES = "from vitfly.host_memory import keep_freed_memory; assert not keep_freed_memory()"
OWN_KNOBS = ("VITFLY_MALLOC", "GLIBC_TUNABLES", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_MAX_")


def run_child(child: str, setup: str, **env: str) -> int:
    clean = {k: v for k, v in os.environ.items() if k not in OWN_KNOBS}
    out = subprocess.run([sys.executable, "-c", child.format(setup=setup)], env={**clean, **env},
                         capture_output=True, text=True, check=True).stdout
    return int(out.split()[-1])


def faults_of_reuse(setup: str, **env: str) -> int:
    return run_child(CHILD, setup, **env)


@glibc_only
def test_a_freed_block_is_reused_without_page_faults():
    kept = faults_of_reuse(KEEP)
    mapped_afresh = faults_of_reuse(AS_GLIBC_COMES, VITFLY_MALLOC="default")
    # glibc as it comes maps the second block afresh: a fault per 4 KiB page (per 2 MiB page under the
    # kernel's THP 'always'); kept, the freed block is reused and its pages are already there
    assert mapped_afresh > PAGES // 1000  # 2 MiB pages where the kernel's THP is 'always'
    assert kept < PAGES // 100
    assert kept * 10 < mapped_afresh


@glibc_only
@with_mallinfo2
def test_a_block_of_gigabytes_comes_from_the_heap():
    assert run_child(BIG_CHILD, AS_GLIBC_COMES, VITFLY_MALLOC="default") >= BIG_BYTES  # its own mapping
    assert run_child(BIG_CHILD, KEEP) == 0  # none mapped on its own: freed, it stays in the heap


@glibc_only
def test_the_cli_keeps_freed_memory():
    setup = "from vitfly.cli import main; main(['configs'])"
    assert faults_of_reuse(setup) < PAGES // 100


def test_why_not(monkeypatch):
    for key in OWN_KNOBS:
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setattr(platform, "system", lambda: "Linux")
    monkeypatch.setattr(platform, "libc_ver", lambda: ("glibc", "2.36"))
    assert host_memory.why_not() is None
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.pthread.rseq=0")  # tunables of other parts: vitfly's still apply
    assert host_memory.why_not() is None
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.mmap_threshold=65536")
    assert host_memory.why_not() == "the environment sets glibc's malloc options"
    monkeypatch.delenv("GLIBC_TUNABLES")
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "0")
    assert host_memory.why_not() == "the environment sets glibc's malloc options"
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")
    monkeypatch.setenv("MALLOC_MMAP_MAX_", "65536")
    assert host_memory.why_not() == "the environment sets glibc's malloc options"
    monkeypatch.delenv("MALLOC_MMAP_MAX_")
    monkeypatch.setenv("VITFLY_MALLOC", "Default")
    assert host_memory.why_not() == "VITFLY_MALLOC=default"
    monkeypatch.delenv("VITFLY_MALLOC")
    monkeypatch.setattr(platform, "libc_ver", lambda: ("", ""))  # musl (Alpine) reports no glibc
    assert host_memory.why_not() == "not glibc on Linux"
    monkeypatch.setattr(platform, "system", lambda: "Darwin")
    assert host_memory.why_not() == "not glibc on Linux"
