"""scripts/gpu_travel.py on a real git checkout: travelling light leaves weights/ and docs/ out of what a device
call sends, refuses commits while it lasts, and travelling full puts the checkout back exactly as it was."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from scripts import gpu_travel  # noqa: E402
from scripts.gpu_slots import travelling_bytes  # noqa: E402


def git(repo: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                          capture_output=True, text=True, check=check)


@pytest.fixture
def checkout(tmp_path):
    """code.py 100 bytes, weights/w.safetensors 5000, docs/a.md 700 and docs/fig/p.png 2000, committed; a local
    exclusion of its own (a line the round trip must keep); docs/a.md then changed without staging."""
    repo = tmp_path / "repo"
    (repo / "weights").mkdir(parents=True)
    (repo / "docs" / "fig").mkdir(parents=True)
    (repo / "code.py").write_bytes(b"c" * 100)
    (repo / "weights" / "w.safetensors").write_bytes(b"w" * 5000)
    (repo / "docs" / "a.md").write_bytes(b"d" * 700)
    (repo / "docs" / "fig" / "p.png").write_bytes(b"p" * 2000)
    git(repo, "init", "-q")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "start")
    (repo / ".git" / "info").mkdir(exist_ok=True)
    (repo / ".git" / "info" / "exclude").write_text("/scratch/\n")
    (repo / "docs" / "a.md").write_bytes(b"e" * 650)  # an edit in progress: unstaged, kept through the round trip
    return repo


def test_light_sends_neither_weights_nor_docs_and_full_restores_the_checkout(checkout):
    before_status = git(checkout, "status", "--porcelain").stdout
    assert before_status == " M docs/a.md\n"
    assert travelling_bytes(checkout) == 100 + 5000 + 650 + 2000
    assert gpu_travel.light_bytes(checkout) == 5000 + 650 + 2000

    gpu_travel.light(checkout)
    assert gpu_travel.is_light(checkout)
    assert travelling_bytes(checkout) == 100  # the code alone travels
    assert git(checkout, "ls-files").stdout.split() == ["code.py"]
    assert (checkout / "weights" / "w.safetensors").read_bytes() == b"w" * 5000  # the files stay on disk
    gpu_travel.light(checkout)  # a second time changes nothing
    assert travelling_bytes(checkout) == 100

    # a commit now would delete the folders from the project: the guard refuses it, whatever is staged
    refused = git(checkout, "commit", "-qam", "oops", check=False)
    assert refused.returncode != 0 and "travel full" in refused.stderr
    assert git(checkout, "rev-list", "--count", "HEAD").stdout.strip() == "1"

    gpu_travel.full(checkout)
    assert not gpu_travel.is_light(checkout)
    assert git(checkout, "status", "--porcelain").stdout == before_status
    assert (checkout / ".git" / "info" / "exclude").read_text() == "/scratch/\n"
    assert not (checkout / ".git" / "hooks" / "pre-commit").exists()
    assert travelling_bytes(checkout) == 100 + 5000 + 650 + 2000
    gpu_travel.full(checkout)  # nothing to undo: says so, changes nothing
    assert git(checkout, "status", "--porcelain").stdout == before_status
    git(checkout, "commit", "-qam", "the edit")  # commits work again
    assert git(checkout, "ls-files").stdout.split() == ["code.py", "docs/a.md", "docs/fig/p.png",
                                                         "weights/w.safetensors"]


def test_light_refuses_staged_changes_and_a_hook_of_the_checkouts_own(checkout):
    git(checkout, "add", "docs/a.md")
    with pytest.raises(SystemExit, match="staged changes"):
        gpu_travel.light(checkout)
    assert not gpu_travel.is_light(checkout)
    git(checkout, "reset", "-q")
    hook = checkout / ".git" / "hooks" / "pre-commit"
    hook.parent.mkdir(exist_ok=True)
    hook.write_text("#!/bin/sh\nexit 0\n")
    with pytest.raises(SystemExit, match="pre-commit hook of this checkout's own"):
        gpu_travel.light(checkout)
    assert not gpu_travel.is_light(checkout) and hook.read_text() == "#!/bin/sh\nexit 0\n"
    assert git(checkout, "status", "--porcelain").stdout == " M docs/a.md\n"


def test_the_travel_command_says_what_a_call_sends(checkout, capsys):
    gpu = __import__("scripts.gpu", fromlist=["main"])
    assert gpu.main(["travel", "--root", str(checkout)]) == 0
    out = capsys.readouterr().out
    assert "travelling full: a device call sends 0.0 MiB" in out and "light it would send 0.0 MiB" in out
    assert gpu.main(["travel", "light", "--root", str(checkout)]) == 0
    assert "travelling light" in capsys.readouterr().out and gpu_travel.is_light(checkout)
    assert gpu.main(["travel", "full", "--root", str(checkout)]) == 0
    assert "travelling full" in capsys.readouterr().out and not gpu_travel.is_light(checkout)


def test_light_leaves_more_folders_when_asked_and_full_brings_them_back(checkout):
    """``--leave``: a carried run's folder (tracked, 400 bytes) stays here too; a path outside the checkout is
    refused before anything changes."""
    (checkout / "carry" / "run").mkdir(parents=True)
    (checkout / "carry" / "run" / "state.bin").write_bytes(b"s" * 400)
    git(checkout, "add", "carry")
    git(checkout, "commit", "-qm", "carry")
    with pytest.raises(SystemExit, match="not a folder inside"):
        gpu_travel.light(checkout, ["../elsewhere"])
    assert not gpu_travel.is_light(checkout)
    gpu_travel.light(checkout, ["carry/run"])
    assert gpu_travel.left_paths(checkout) == ["weights", "docs", "carry/run"]
    assert travelling_bytes(checkout) == 100
    gpu_travel.full(checkout)
    assert git(checkout, "status", "--porcelain").stdout == " M docs/a.md\n"
    assert travelling_bytes(checkout) == 100 + 5000 + 650 + 2000 + 400
