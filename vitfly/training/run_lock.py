"""One training process per run folder.

``train_policy`` holds an exclusive ``flock`` on ``<run folder>/train.lock`` while it trains, so a second process
started on the same run (a second ``vitfly reproduce`` on the same study, a second terminal) is told which
process has it (:class:`RunBusy`, one line) instead of training the same run beside it: two processes writing one
``last.ckpt`` would each resume from the other's epochs and leave a run that neither trained.

The kernel drops the lock when its process ends, however it ends, so a killed training never blocks the next one;
the file is removed on a clean exit. The lock is advisory and local: folders on a network file system shared by
several machines are not covered.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

from vitfly.errors import VitflyError

LOCK_NAME = "train.lock"


def who_holds(holder: dict) -> str:
    """The holding process as the messages name it: "pid 123 on HOST, since TIME", or "another process" while it
    has not yet written who it is."""
    if "pid" not in holder:
        return "another process"
    since = f", since {holder['since']}" if "since" in holder else ""
    return f"pid {holder['pid']} on {holder.get('host', '?')}{since}"


class RunBusy(VitflyError):
    """Another live process is training this run folder."""

    def __init__(self, run_dir: Path, holder: dict):
        self.who = who_holds(holder)
        super().__init__(f"{run_dir}: {self.who}, is training this run; wait for it to end (or stop it) and "
                         "run again: it resumes from its last checkpoint")
        self.run_dir = Path(run_dir)
        self.holder = holder


def _holder(fd: int) -> dict:
    """What the holding process wrote into the lock file ({} while it has not yet written it)."""
    with contextlib.suppress(OSError, ValueError):
        return json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    return {}


def _other_rank() -> bool:
    """True in the processes Lightning starts for DDP ranks other than 0: they run the caller's code again, inside
    the training that rank 0 holds the lock for."""
    return any(os.environ.get(name, "0") != "0" for name in ("LOCAL_RANK", "NODE_RANK", "RANK"))


@contextlib.contextmanager
def run_lock(run_dir: str | os.PathLike) -> Iterator[None]:
    """Hold ``run_dir``'s training lock inside the block; :class:`RunBusy` at once if a live process holds it."""
    run_dir = Path(run_dir)
    if _other_rank():
        yield
        return
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK_NAME
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise RunBusy(run_dir, holder) from None
        # the previous holder removes the file as it lets go: if it did so between our open and our flock, we
        # hold a lock on a file no one else will open; take the one at the path instead
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                  "since": time.strftime("%Y-%m-%d %H:%M:%S")}).encode(), 0)
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)  # before letting go, so that a process that opened it sees it gone and opens anew
        os.close(fd)


def training_now(run_dir: str | os.PathLike) -> dict | None:
    """The record of the live process training ``run_dir`` ({} if it has not yet written one), or None if none
    does. Read-only: the lock is tried and let go at once, and no file is created."""
    try:
        fd = os.open(Path(run_dir) / LOCK_NAME, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _holder(fd)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)
