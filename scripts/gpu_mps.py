"""The runs of a slot share the card through NVIDIA's Multi-Process Service (MPS) where the machine has it.

Without MPS, processes on one GPU take turns: each has its own context, and the card runs one context's kernels
at a time, switching between them. The paper arm's runs step one trajectory at a time, so their kernels fill a
few of the card's multiprocessors (about 10 TFLOP/s of an H200's 790, docs/performance.md); side by side, in
turns, three such runs keep the card busier than one but never run a kernel at the same time. Through an MPS
server their kernels run side by side on the multiprocessors.

``SharedCard`` starts a private MPS control daemon for the slot: its pipe and log folders in a fresh temporary
folder, so only the processes given its environment (the slot's runs) connect to it; the card's settings,
compute mode included, stay as they are. A CUDA client is then started through it once (``PROBE``); only if that
works are the runs given the daemon's environment, otherwise the daemon is told to quit and the runs share the
card as before. The daemon quits when the block ends. What happened goes into the slot's report
(``gpu_reproduce.json``: ``mps``), beside the runs' epoch times that say whether it paid. A check that failed is
written down in ``memo`` (the slot's work folder, which a warm machine keeps between calls), so that a follow-on
call on the same machine does not spend its device time finding out again (a client that hangs costs
``timeout_s``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

CONTROL = "nvidia-cuda-mps-control"
# a CUDA context made and a kernel run through the server (the server starts with its first client)
PROBE = "import torch; x = torch.ones(4, device='cuda') * 2; torch.cuda.synchronize(); assert float(x.sum()) == 8"


class SharedCard:
    """``with SharedCard(runs, wanted) as card:`` the slot's ``runs`` processes, started inside the block, share
    the card through a private MPS daemon when ``card.info["mps"]`` is true (its environment is in ``os.environ``
    for the block's children); ``card.info["note"]`` says why not otherwise. ``probe`` is the Python code a
    client runs through the daemon before any run does."""

    def __init__(self, runs: int, wanted: bool = True, probe: str = PROBE, timeout_s: float = 45.0,
                 memo: Path | None = None) -> None:
        self.runs, self.wanted, self.probe, self.timeout_s, self.memo = runs, wanted, probe, timeout_s, memo
        self.info: dict = {"mps": False}
        self.exe: str | None = None
        self.env: dict[str, str] = {}
        self.folder: Path | None = None
        self.saved: dict[str, str | None] = {}

    def __enter__(self) -> SharedCard:
        if not self.wanted:
            return self._without("--no-mps")
        if self.runs < 2:
            return self._without("one run: nothing to share the card with")
        earlier = self._earlier_failure()
        if earlier is not None:
            return self._without(f"the MPS check failed in an earlier call on this machine ({earlier})")
        self.exe = shutil.which(CONTROL)
        if self.exe is None:
            return self._without(f"{CONTROL} not found (no NVIDIA driver utilities here)")
        self.folder = Path(tempfile.mkdtemp(prefix="vitfly-mps-"))  # short: the daemon's socket path is limited
        self.env = {"CUDA_MPS_PIPE_DIRECTORY": str(self.folder / "pipe"),
                    "CUDA_MPS_LOG_DIRECTORY": str(self.folder / "log")}
        for path in self.env.values():
            Path(path).mkdir()
        started = self._control(["-d"])
        if started.returncode != 0:
            self._forget()
            return self._failed(f"{CONTROL} -d exited {started.returncode}: {last_line(started)}")
        try:
            client = subprocess.run([sys.executable, "-c", self.probe], env={**os.environ, **self.env},
                                    capture_output=True, text=True, timeout=self.timeout_s)
            failed = None if client.returncode == 0 else f"exited {client.returncode}: {last_line(client)}"
        except subprocess.TimeoutExpired:
            failed = f"no answer in {self.timeout_s:.0f} s"
        if failed:
            log = Path(self.env["CUDA_MPS_LOG_DIRECTORY"]) / "control.log"
            said = log.read_text(errors="replace").strip().splitlines()[-1:] if log.exists() else []
            failed += f"; control.log: {said[0]}" if said else ""
            self._quit()
            return self._failed(f"a CUDA client could not start through the MPS daemon ({failed}); the daemon quit")
        self.saved = {k: os.environ.get(k) for k in self.env}
        os.environ.update(self.env)
        servers = self._control([], "get_server_list\n").stdout.split()
        self.info = {"mps": True, "runs": self.runs, "servers": servers, "folder": str(self.folder)}
        return self

    def __exit__(self, *exc) -> None:
        for key, value in self.saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        self.saved = {}
        if self.exe is not None and self.folder is not None:
            self._quit()

    def _without(self, why: str) -> SharedCard:
        self.info = {"mps": False, "note": why}
        return self

    def _failed(self, why: str) -> SharedCard:
        """No MPS, for a reason a later call on this machine would meet again: written to ``memo``."""
        if self.memo is not None:
            self.memo.parent.mkdir(parents=True, exist_ok=True)
            self.memo.write_text(json.dumps({"note": why}) + "\n")
        return self._without(why)

    def _earlier_failure(self) -> str | None:
        """The note of a check that failed in an earlier call (``memo``), or None."""
        if self.memo is None or not self.memo.exists():
            return None
        try:
            return str(json.loads(self.memo.read_text())["note"])
        except (ValueError, KeyError, TypeError):
            return None  # unreadable: check again

    def _control(self, args: list[str], stdin: str | None = None) -> subprocess.CompletedProcess:
        assert self.exe is not None
        try:
            return subprocess.run([self.exe, *args], input=stdin, env={**os.environ, **self.env},
                                  capture_output=True, text=True, timeout=30)
        except subprocess.TimeoutExpired as e:
            return subprocess.CompletedProcess(e.cmd, 124, "", f"no answer in {e.timeout:.0f} s")

    def _quit(self) -> None:
        quit_ = self._control([], "quit\n")
        if quit_.returncode != 0:
            print(f"[gpu] {CONTROL} quit exited {quit_.returncode}: {last_line(quit_)}", flush=True)
        self._forget()

    def _forget(self) -> None:
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
        self.folder = None


def last_line(done: subprocess.CompletedProcess) -> str:
    lines = (done.stderr or done.stdout or "").strip().splitlines()
    return lines[-1] if lines else "(nothing printed)"
