"""scripts/gpu_history.py: what a session's commits weigh as a submission, worked out by hand on a small repo."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from scripts.gpu_history import DIFF_LIMIT, Weight, session_base, weight  # noqa: E402

MIB = 2**20
# git's binary patch: the deflated bytes (random bytes do not shrink) in base85, a line of 66 characters and a
# newline for each 52 bytes
BASE85 = 67 / 52


@pytest.fixture
def repo(tmp_path):
    root = tmp_path / "repo"
    root.mkdir()
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t"}

    def git(*args):
        return subprocess.run(["git", "-C", str(root), *args], check=True, capture_output=True, text=True,
                              env=env).stdout.strip()

    git("init", "-q", "-b", "main")
    (root / "README").write_text("a repo\n")
    git("add", "README")
    git("commit", "-q", "-m", "first")
    return root, git


def test_a_replaced_state_counts_its_old_bytes_and_its_new(repo):
    """A 1 MiB state committed, then replaced by another: the first patch holds it once, the second the new bytes
    and the old (git's binary patches go both ways), so the diffs are about three times a state's base85 text;
    the pack holds the two states once each."""
    root, git = repo
    base = git("rev-parse", "HEAD")
    rng = np.random.default_rng(0)
    (root / "last.bin").write_bytes(rng.bytes(MIB))
    git("add", "last.bin")
    git("commit", "-q", "-m", "carry 1")
    assert session_base(root) == base  # where the branch began: its first commit here
    (root / "last.bin").write_bytes(rng.bytes(MIB))
    git("commit", "-q", "-am", "carry 2")
    w = weight(root, base)
    assert w.commits == 2
    assert w.diff_bytes == pytest.approx(3 * MIB * BASE85, rel=0.01)
    assert 2 * MIB < w.pack_bytes < 2 * MIB * 1.01
    # a third state not committed yet: weighed with the working tree, not without it
    (root / "last.bin").write_bytes(rng.bytes(MIB))
    assert weight(root, base).diff_bytes == w.diff_bytes
    assert weight(root, base, with_worktree=True).diff_bytes == pytest.approx(5 * MIB * BASE85, rel=0.01)
    assert git("status", "--porcelain") == "M last.bin"  # nothing staged or committed by the weighing
    assert git("rev-list", "--count", "HEAD") == "3"
    # a clean working tree adds no commit: the count is the commits' own
    git("checkout", "--", "last.bin")
    assert weight(root, base, with_worktree=True) == w


def test_the_warning_names_the_limit_passed():
    assert Weight("b", 4, int(0.8 * DIFF_LIMIT), 10 * MIB).over() == ["diffs 204.8 MiB of 256.0 MiB"]
    assert Weight("b", 1, MIB, MIB).over() == []


def test_the_slot_outlook_adds_the_states_out_and_in_as_binary_patches(repo, capsys):
    """A slot that replaces 60 MiB of carried states with 60 MiB more: 120 MiB of bytes as base85 patch text,
    154.6 MiB, under 75 % of the 256 MiB; with 100 MiB more of each it is not, and the outlook says to commit no
    other carry."""
    from scripts.gpu_history import slot_outlook

    root, _ = repo
    slot_outlook(root, 60 * MIB, 60 * MIB)
    out = capsys.readouterr().out
    assert "about 154.6 MiB of diffs" in out and "commit no other carry" not in out
    slot_outlook(root, 160 * MIB, 160 * MIB)
    assert "commit no other carry" in capsys.readouterr().out
