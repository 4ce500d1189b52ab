"""Travel light: the ``travel`` command of ``scripts/gpu.py``, which keeps the folders no slot reads out of what a
device call sends, so that the room goes to the runs' resume states.

The device tool sends the checkout's tracked files and the untracked ones git does not ignore, 64 MiB in all
with what a call carries. Of the working tree's 31 MiB, 25 are the shipped weights (``weights/``) and 4 the
docs' figures and tables (``docs/``): a slot trains networks from scratch or from their carried state and reads
neither. Left behind, they make room for more large runs' states (three ViT-class states with bf16 moments,
squeezed by ``scripts/gpu_squeeze.py``, are about 58 MiB):

    python3 scripts/gpu.py travel light   # here, right before the device call: weights/ and docs/ stay behind
    python3 scripts/gpu.py travel full    # here, right after it: back as they were
    python3 scripts/gpu.py travel         # which it is now, and what a call would send

``--leave PATH ...`` leaves more tracked folders behind: ``gpu.py status`` names the carried runs that do not go
to the slot (runs trained on a CPU, finished ones), so that they take no room and the slot does not resume them.

``light`` takes the folders out of git's index (their files stay on disk, unchanged) and has git ignore them
(``.git/info/exclude``), so the checkout sends the rest; ``full`` puts them back into the index from ``HEAD`` and
ends both. Nothing is committed either way. While light, a commit would delete the folders from the project:
``light`` refuses to start over staged changes, and installs a pre-commit hook that refuses every commit until
``full``. The slot plan (``gpu.py status``, ``gpu.py carry``) counts the working tree as it travels light.
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LIGHT = ("weights", "docs")  # tracked folders no slot reads: the shipped weights, the docs' figures and tables
BEGIN = "# vitfly: travelling light; `python3 scripts/gpu.py travel full` ends it"
END = "# vitfly: end of travelling light"
HOOK_TAG = "# vitfly travel light guard"
HOOK = f"""#!/bin/sh
{HOOK_TAG}: a commit now would delete {", ".join(f"{d}/" for d in LIGHT)} from the project
echo "travelling light ({", ".join(f"{d}/" for d in LIGHT)} out of git's index for a device call): first" \\
     "python3 scripts/gpu.py travel full, then commit" >&2
exit 1
"""


def git(root: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True)
    if check and done.returncode != 0:
        raise SystemExit(f"{root}: git {' '.join(args)}: {done.stderr.strip()[:300]}")
    return done


def git_path(root: Path, name: str) -> Path:
    """A path inside the checkout's git directory (``info/exclude``, ``hooks/pre-commit``), absolute."""
    path = Path(git(root, "rev-parse", "--git-path", name).stdout.strip())
    return path if path.is_absolute() else root / path


def exclude_lines(root: Path) -> list[str]:
    path = git_path(root, "info/exclude")
    return path.read_text().splitlines() if path.exists() else []


def light_block(lines: list[str]) -> tuple[int, int] | None:
    """Where ``light``'s lines sit in the exclude file: the indices of ``BEGIN`` and of ``END`` (or of the last
    line, if someone cut the end); None when the checkout travels full."""
    if BEGIN not in lines:
        return None
    return lines.index(BEGIN), lines.index(END) if END in lines else len(lines) - 1


def is_light(root: Path) -> bool:
    return light_block(exclude_lines(root)) is not None


def left_paths(root: Path) -> list[str]:
    """The folders travelling light leaves behind now (as ``light`` wrote them into the exclusion)."""
    lines = exclude_lines(root)
    block = light_block(lines)
    if block is None:
        return []
    return [line.strip("/") for line in lines[block[0] + 1 : block[1] + 1] if line.strip("/") and line != END]


def light_bytes(root: Path, leave: tuple[str, ...] | list[str] = ()) -> int:
    """What the ``LIGHT`` folders' and ``leave``'s tracked files weigh: what travelling light leaves behind."""
    listed = git(root, "ls-files", "-z", "--", *LIGHT, *leave).stdout.split("\0")
    return sum((root / f).stat().st_size for f in listed if f and (root / f).is_file())


def checked_leave(root: Path, leave: tuple[str, ...] | list[str]) -> list[str]:
    """``leave`` as folders relative to the checkout, each inside it (one line naming a path that is not)."""
    out = []
    for path in leave:
        full_path = (root / path).resolve()
        if not full_path.is_relative_to(root.resolve()) or full_path == root.resolve():
            raise SystemExit(f"--leave {path}: not a folder inside {root}")
        out.append(full_path.relative_to(root.resolve()).as_posix())
    return out


def light(root: Path, leave: tuple[str, ...] | list[str] = ()) -> None:
    """``LIGHT`` and ``leave`` out of the index and ignored, the commit guard installed; nothing else changes."""
    if is_light(root):
        print(f"{root}: already travelling light, leaving {', '.join(left_paths(root))} here")
        return
    paths = list(dict.fromkeys([*LIGHT, *checked_leave(root, leave)]))
    if git(root, "diff", "--cached", "--quiet", check=False).returncode != 0:
        raise SystemExit(f"{root}: staged changes in git's index; commit or unstage them before travelling light "
                         "(it changes the index, and `travel full` restores it from HEAD)")
    hook = git_path(root, "hooks/pre-commit")
    if hook.exists() and HOOK_TAG not in hook.read_text():
        raise SystemExit(f"{hook}: a pre-commit hook of this checkout's own; travelling light needs that place "
                         "for its guard (a commit while light would delete the folders it leaves behind)")
    tracked = [d for d in paths if git(root, "ls-files", "--", d).stdout.strip()]
    if not tracked:
        raise SystemExit(f"{root}: none of {', '.join(paths)} is tracked here; nothing to leave behind")
    exclude = git_path(root, "info/exclude")
    exclude.parent.mkdir(parents=True, exist_ok=True)
    kept = exclude_lines(root)
    exclude.write_text("\n".join([*kept, BEGIN, *(f"/{d}/" for d in paths), END]) + "\n")  # marks it light first
    try:
        hook.parent.mkdir(parents=True, exist_ok=True)
        hook.write_text(HOOK)
        hook.chmod(0o755)
        git(root, "rm", "-r", "-q", "--cached", "--", *tracked)
    except BaseException:  # half light is worse than either: back to full
        full(root)
        raise


def full(root: Path) -> None:
    """Back as before ``light``: the folders in the index as ``HEAD`` has them, the exclusion and guard gone."""
    if not is_light(root):
        print(f"{root}: travelling full already")
        return
    git(root, "reset", "-q", "--", *left_paths(root))
    lines = exclude_lines(root)
    start, end = light_block(lines)
    git_path(root, "info/exclude").write_text("".join(f"{line}\n" for line in lines[:start] + lines[end + 1:]))
    hook = git_path(root, "hooks/pre-commit")
    if hook.exists() and HOOK_TAG in hook.read_text():
        hook.unlink()


def travel(args: argparse.Namespace) -> int:
    from scripts.gpu_slots import CARRY_BYTES, mib, travelling_bytes

    root = Path(args.root)
    if args.leave and args.mode != "light":
        raise SystemExit("--leave goes with `travel light`")
    if args.mode == "light":
        light(root, args.leave)
    elif args.mode == "full":
        full(root)
    sends = travelling_bytes(root)
    if is_light(root):
        print(f"travelling light: a device call sends {mib(sends)} of its {mib(CARRY_BYTES)} "
              f"({', '.join(left_paths(root))} stay here); after the call: python3 scripts/gpu.py travel full")
    else:
        over = " (over: the device tool would refuse the call)" if sends > CARRY_BYTES else ""
        print(f"travelling full: a device call sends {mib(sends)} of its {mib(CARRY_BYTES)}{over}; light it would "
              f"send {mib(sends - light_bytes(root))} (python3 scripts/gpu.py travel light, right before the call)")
    return 0


def add_commands(sub) -> dict:
    t = sub.add_parser("travel", help="here: leave weights/ and docs/ out of what a device call sends (light), or "
                                      "send them again (full); without a mode, which it is now")
    t.add_argument("mode", nargs="?", choices=("light", "full"))
    t.add_argument("--leave", nargs="+", default=[], metavar="PATH",
                   help="light: more tracked folders to leave here (status names the carried runs of no slot)")
    t.add_argument("--root", default=str(ROOT), help="the checkout (default: this one)")
    return {"travel": travel}
