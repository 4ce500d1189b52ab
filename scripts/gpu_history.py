"""What this session's commits weigh when they are submitted, the carried resume states above all.

A session's commits are submitted together when it stops, and a submission has two limits: its commits packed
as git sends them (512 MiB) and their diffs added up as text (256 MiB, binary files as git's binary patches,
which hold a replaced file's old bytes beside its new ones). Each carry of three large runs' states adds about
60 MiB of new bytes and, replacing the last carry, about as much again in removed bytes: on 2026-11-30 a session
that committed the carry four times was refused whole, its GPU slot's training with it. So ``carry`` says what
the session's commits would weigh with the carry committed, and ``gpu.py history`` says it at any time.

The session's first commit is where the branch was made (the oldest entry of its reflog), unless an upstream
branch is set or ``--base`` names it.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DIFF_LIMIT = 256 * 2**20  # the diffs of a submission's commits, added up as text
PACK_LIMIT = 512 * 2**20  # a submission's commits packed as git sends them
WARN_SHARE = 0.75  # past this share of either limit, carry and history say so
BINARY_PATCH = 67 / 52  # git's binary patch: 66 base85 characters and a newline per 52 bytes that do not shrink


@dataclass
class Weight:
    """What the commits from ``base`` (exclusive) weigh."""

    base: str
    commits: int
    diff_bytes: int  # their patches as text, binary patches included (git diff-tree -p --binary)
    pack_bytes: int  # a pack of their objects (no deltas against objects outside it: an upper bound)

    def over(self) -> list[str]:
        """The limits this weight passes ``WARN_SHARE`` of, as words."""
        return [f"{what} {mib(value)} of {mib(limit)}" for what, value, limit in
                (("diffs", self.diff_bytes, DIFF_LIMIT), ("pack", self.pack_bytes, PACK_LIMIT))
                if value > WARN_SHARE * limit]


def mib(n: int) -> str:  # as scripts/gpu_slots.py's, which would bring Lightning into `gpu.py history`
    return f"{n / 2**20:.1f} MiB"


def git(root: Path, *args: str, env: dict | None = None) -> str:
    done = subprocess.run(["git", "-C", str(root), *args], capture_output=True,
                          env=None if env is None else {**os.environ, **env})
    if done.returncode:
        raise SystemExit(f"git {' '.join(args)}: {done.stderr.decode(errors='replace').strip()}")
    return done.stdout.decode()


def session_base(root: Path) -> str:
    """The commit this session's work starts from: the upstream branch's, else the one the branch was made at."""
    upstream = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", "-q", "@{upstream}"],
                              capture_output=True, text=True)
    if upstream.returncode == 0:
        return upstream.stdout.strip()
    branch = git(root, "symbolic-ref", "-q", "HEAD").strip()
    entries = git(root, "reflog", "show", "--format=%H", branch).split()
    if not entries:
        raise SystemExit(f"{root}: {branch} has no reflog to find where this session began; name it (--base REV)")
    return entries[-1]


def weight(root: Path, base: str, with_worktree: bool = False) -> Weight:
    """What the commits after ``base`` up to HEAD weigh; with ``with_worktree``, as if every change in the working
    tree (new, changed and deleted files that git does not ignore) were committed as well."""
    base = git(root, "rev-parse", "--verify", f"{base}^{{commit}}").strip()
    head = git(root, "rev-parse", "HEAD").strip()
    if with_worktree:
        head = worktree_commit(root, head)
    commits = git(root, "rev-list", "--reverse", f"{base}..{head}").split()
    # each commit's patch against its first parent, binary files as git's binary patches
    diff = sum(output_bytes(root, "diff-tree", "-p", "--binary", "--no-renames", "--root", "--first-parent", c)
               for c in commits)
    pack = output_bytes(root, "pack-objects", "--revs", "--stdout", "--window=0", "-q", stdin=f"{head}\n^{base}\n")
    return Weight(base, len(commits), diff, pack)


def output_bytes(root: Path, *args: str, stdin: str = "") -> int:
    """How many bytes ``git args`` writes, counted as they stream (a pack can be hundreds of MiB)."""
    proc = subprocess.Popen(["git", "-C", str(root), *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    proc.stdin.write(stdin.encode())
    proc.stdin.close()
    total = 0
    while chunk := proc.stdout.read(1 << 20):
        total += len(chunk)
    if proc.wait():
        raise SystemExit(f"git {' '.join(args)}: exit {proc.returncode}")
    return total


def worktree_commit(root: Path, head: str) -> str:
    """A commit object (no branch moves) of the working tree as ``git add -A`` would stage it on ``head``; ``head``
    itself when that changes nothing."""
    with tempfile.TemporaryDirectory() as tmp:
        env = {"GIT_INDEX_FILE": str(Path(tmp) / "index")}
        git(root, "read-tree", head, env=env)
        git(root, "add", "-A", env=env)
        tree = git(root, "write-tree", env=env).strip()
    if tree == git(root, "rev-parse", f"{head}^{{tree}}").strip():
        return head  # a clean tree: no commit to count
    return git(root, "commit-tree", tree, "-p", head, "-m", "the working tree, weighed").strip()


def report(root: Path, base: str | None = None, with_worktree: bool = True) -> Weight:
    """Print what the session's commits (and, with ``with_worktree``, the uncommitted changes) weigh."""
    w = weight(root, base or session_base(root), with_worktree)
    what = "commits and uncommitted changes" if with_worktree else "commits"
    commits = f"{w.commits} commit" + "s" * (w.commits != 1)
    print(f"  this session's {what} since {w.base[:12]} ({commits}), as a submission: diffs {mib(w.diff_bytes)}"
          f" of {mib(DIFF_LIMIT)}, pack {mib(w.pack_bytes)} of {mib(PACK_LIMIT)}")
    if w.over():
        print(f"  near or over the submission's limits ({', '.join(w.over())}): commit a carry once a session, at "
              "its end (every carry committed replaces the last one's states and counts both)")
    return w


def slot_outlook(root: Path, out_bytes: int, home_bytes: int, w: Weight | None = None) -> None:
    """Print what committing a slot's carry once it is home adds to the session's diffs: the carried states it
    replaces (``out_bytes``, in git's history now) and the states expected home (``home_bytes``), both as binary
    patches; and whether that still fits beside what the session has (its commits and uncommitted changes: ``w``
    where ``report`` has just weighed them)."""
    planned = int(BINARY_PATCH * (out_bytes + home_bytes))
    try:
        w = w or weight(root, session_base(root), with_worktree=True)
    except SystemExit as err:  # not a git checkout with a history: nothing to weigh against
        print(f"  the slot's carry, committed when it is home: about {mib(planned)} of diffs ({err})")
        return
    total = w.diff_bytes + planned
    print(f"  the slot's carry, committed once when it is home: about {mib(planned)} of diffs (the states it replaces "
          f"and the new ones), {mib(total)} of the submission's {mib(DIFF_LIMIT)} with this session's "
          f"{mib(w.diff_bytes)} so far (python3 scripts/gpu.py history)")
    if total > WARN_SHARE * DIFF_LIMIT:
        print("  too close to the limit: commit no other carry this session (the CPU runs' progress stays "
              "uncommitted), or the whole submission is refused")


def add_commands(sub) -> dict:
    h = sub.add_parser("history", help="here: what this session's commits weigh as a submission, carries included")
    h.add_argument("--base", help="the commit the session began at (default: where the branch was made)")
    h.add_argument("--committed", action="store_true", help="the commits alone, not the uncommitted changes")

    def history(args) -> int:
        report(ROOT, args.base, with_worktree=not args.committed)
        return 0

    return {"history": history}
