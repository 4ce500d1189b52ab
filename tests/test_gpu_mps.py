"""scripts/gpu_mps.py: a slot's runs share the card through a private MPS daemon only where a CUDA client
starts through it; everywhere else they run as before, and the daemon never outlives the block.

This machine has no NVIDIA driver: the daemon here is a stand-in for ``nvidia-cuda-mps-control`` (a shell
script that writes down how it was called, and answers ``get_server_list``), and the probe a CUDA client runs
through it is real: it fails on this CPU, which is the case that must leave the runs untouched.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from scripts.gpu_mps import CONTROL, SharedCard  # noqa: E402

PIPE = "CUDA_MPS_PIPE_DIRECTORY"


def stand_in(folder: Path, start_rc: int = 0) -> Path:
    """An ``nvidia-cuda-mps-control`` that logs each call (arguments, pipe folder, commands on stdin) to
    ``folder/calls`` and exits ``start_rc`` when asked to start as a daemon."""
    folder.mkdir(exist_ok=True)
    calls = folder / "calls"
    script = folder / CONTROL
    script.write_text(f"""#!/bin/sh
if [ "$1" = "-d" ]; then
    echo "start $CUDA_MPS_PIPE_DIRECTORY" >> {calls}
    [ {start_rc} -eq 0 ] || echo "An instance of this daemon is already running" >&2
    exit {start_rc}
fi
read command
echo "$command $CUDA_MPS_PIPE_DIRECTORY" >> {calls}
[ "$command" = "get_server_list" ] && echo 4242
exit 0
""")
    script.chmod(0o755)
    return calls


def with_path(monkeypatch, folder: Path) -> None:
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ['PATH']}")


def test_without_the_daemon_or_with_one_run_nothing_changes(tmp_path, monkeypatch):
    monkeypatch.delenv(PIPE, raising=False)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))  # a machine without the NVIDIA tools
    with SharedCard(3) as card:
        assert PIPE not in os.environ
    assert card.info == {"mps": False, "note": f"{CONTROL} not found (no NVIDIA driver utilities here)"}

    calls = stand_in(tmp_path / "bin")
    with_path(monkeypatch, tmp_path / "bin")
    with SharedCard(1) as card:
        pass
    with SharedCard(3, wanted=False) as off:
        pass
    assert card.info["note"] == "one run: nothing to share the card with" and off.info["note"] == "--no-mps"
    assert not calls.exists()  # the daemon was never asked


def test_a_client_that_cannot_start_through_the_daemon_leaves_the_runs_as_they_were(tmp_path, monkeypatch):
    """The real probe on this CPU: torch finds no CUDA device, so the daemon is told to quit at once."""
    monkeypatch.delenv(PIPE, raising=False)
    calls = stand_in(tmp_path / "bin")
    with_path(monkeypatch, tmp_path / "bin")
    with SharedCard(3, timeout_s=300) as card:
        assert PIPE not in os.environ
    assert card.info["mps"] is False
    assert card.info["note"].startswith("a CUDA client could not start through the MPS daemon (exited 1: ")
    assert card.info["note"].endswith("); the daemon quit")
    (start, pipe), (quit_, pipe_again) = [line.split() for line in calls.read_text().splitlines()]
    assert (start, quit_) == ("start", "quit") and pipe == pipe_again
    assert not Path(pipe).parent.exists()  # its private folder removed


def test_a_daemon_that_does_not_start_is_named_with_its_words(tmp_path, monkeypatch):
    stand_in(tmp_path / "bin", start_rc=1)
    with_path(monkeypatch, tmp_path / "bin")
    with SharedCard(2) as card:
        pass
    assert card.info == {"mps": False, "note": f"{CONTROL} -d exited 1: An instance of this daemon is already running"}


def test_runs_started_in_the_block_connect_to_the_private_daemon_which_quits_at_its_end(tmp_path, monkeypatch):
    """A probe that succeeds here stands for a GPU machine's: the block's children see the daemon's pipe
    folder (a private, fresh one), the environment is given back after the block, and the daemon quits."""
    monkeypatch.setenv(PIPE, "/somewhere/else")  # a value of the caller's, given back after the block
    calls = stand_in(tmp_path / "bin")
    with_path(monkeypatch, tmp_path / "bin")
    probe = f"import os; assert os.environ['{PIPE}'] != '/somewhere/else'"
    with SharedCard(3, probe=probe) as card:
        seen = subprocess.run([sys.executable, "-c", f"import os; print(os.environ['{PIPE}'])"],
                              capture_output=True, text=True, check=True).stdout.strip()
        assert Path(seen).is_dir() and Path(seen).name == "pipe"
        assert card.info == {"mps": True, "runs": 3, "servers": ["4242"], "folder": str(Path(seen).parent)}
    assert os.environ[PIPE] == "/somewhere/else"
    assert calls.read_text().splitlines() == [f"start {seen}", f"get_server_list {seen}", f"quit {seen}"]
    assert not Path(seen).exists()


def test_a_check_that_failed_is_not_paid_for_again_in_a_follow_on_call(tmp_path, monkeypatch):
    """The first call's failed check is written down in the work folder a warm machine keeps; the follow-on call
    reads it and leaves the daemon alone (a client that hangs would cost it the probe's timeout again)."""
    monkeypatch.delenv(PIPE, raising=False)
    calls = stand_in(tmp_path / "bin")
    with_path(monkeypatch, tmp_path / "bin")
    memo = tmp_path / "work" / "mps_check.json"
    with SharedCard(3, memo=memo) as first:
        pass
    assert first.info["mps"] is False and memo.exists()
    asked = calls.read_text()
    with SharedCard(3, memo=memo) as again:
        assert PIPE not in os.environ
    assert again.info == {"mps": False, "note": f"the MPS check failed in an earlier call on this machine "
                                                f"({first.info['note']})"}
    assert calls.read_text() == asked  # the daemon was not asked again
    memo.write_text("not json")  # an unreadable note: check again
    with SharedCard(3, memo=memo) as third:
        pass
    assert third.info["note"] == first.info["note"] and calls.read_text() != asked


def test_a_daemon_that_works_leaves_no_note(tmp_path, monkeypatch):
    stand_in(tmp_path / "bin")
    with_path(monkeypatch, tmp_path / "bin")
    memo = tmp_path / "mps_check.json"
    with SharedCard(2, probe="pass", memo=memo) as card:
        assert card.info["mps"] is True
    assert not memo.exists()
