"""Work on the project's GPU machine: one entry point for what runs there and for bringing its results home.

    wheels          here   the pure-Python wheels the machine lacks, into .whl/ (carry it)
    train           there  a `vitfly reproduce` preset's data collected, named runs trained until the deadline
                           -> runs.tar.NNN, gpu_reproduce.json; --go-on: a follow-on call on the warm machine
                           goes on from the first call's runs there
    status          here   every run of a preset (done, unfinished k/N, not started); the next slot (carry, runs)
    carry           here   status, and every run that trained here into carry/PRESET/ (commit it: runs outlive
                           the session there, and the next slot resumes from it)
    restore         here   carry/PRESET/ back into the preset's train/ (a new checkout goes on from it)
    travel light    here   right before a device call: weights/ and docs/ left out of what it sends (room for
                           the runs' states); `travel full` right after it puts them back
    history         here   what this session's commits (and uncommitted changes) weigh as a submission: a
                           carry committed more than once a session can pass its limits (carry prints it too)
    study           there  the shipped weights' study (scripts/gpu_study.yaml) -> study.tar.NNN, study.json, run.log
    evaluate        there  `vitfly evaluate` with the flags after `--`, the policy on the card
                           -> eval.tar.NNN, gpu_evaluate.json
    pipeline        there  `vitfly pipeline` end to end (scripts/gpu_machine.yaml)
                           -> pipeline.tar.NNN, gpu_pipeline.json, run.log
    unpack DIR      here   whatever DIR holds: runs into the preset's train/ (--preset), a study or a pipeline
                           into --into, evaluation records merged into the sweep directory --into

Every command that runs there first installs the carried wheels (``scripts/gpu_machine.py``) and packs what
it returns the one way ``scripts/gpu_pack.py`` does: a tar split into pieces of at most 15 MiB (the device tool
returns 8 files of 16 MiB), its manifest (pieces, SHA-256, contents) inside the command's report JSON; ``unpack``
joins the pieces, checks them against that manifest and extracts them with the same safe member check. One job
a file: ``gpu_reproduce.py`` (train, status, the runs' unpack; ``gpu_slots.py``: resume states;
``gpu_plan.py``: the next slot; ``gpu_carry.py``: carry and restore; ``gpu_preset.py``: a preset's runs and data;
``gpu_travel.py``: travel light; ``gpu_history.py``: a submission's weight; ``gpu_squeeze.py``: resume
states squeezed for the trip, both ways),
``gpu_study.py``, ``gpu_evaluate.py``, ``gpu_machine.py`` (wheels, setup, pipeline). The old command lines
keep working: ``scripts/gpu_reproduce.py ARGS`` is ``scripts/gpu.py ARGS``, ``scripts/gpu_study.py ARGS`` is
``scripts/gpu.py study ARGS``, ``scripts/gpu_machine.sh fetch|run DIR`` is ``wheels`` / ``pipeline --out DIR``.
Docs: docs/reproduce.md, "Work on a GPU machine".
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

THERE = ("train", "train-one", "study", "evaluate", "pipeline")  # commands that run on the GPU machine
PIECES = {"runs": "a preset's runs", "study": "a study", "eval": "evaluation records", "pipeline": "a pipeline"}


def unpack(args: argparse.Namespace) -> int:
    """Whatever ``args.dir`` holds, unpacked here by its own rules."""
    from scripts.gpu_pack import pieces_of

    src = Path(args.dir)
    found = [name for name in PIECES if pieces_of(src, name)]
    if len(found) != 1:
        what = ", ".join(f"{n}.tar.NNN ({PIECES[n]})" for n in PIECES)
        raise SystemExit(f"{src}: expected the pieces of one of {what}; found "
                         + (" and ".join(found) if found else "none"))
    kind = found[0]
    if kind == "runs":
        from scripts.gpu_reproduce import unpack as unpack_runs

        if not args.preset:
            raise SystemExit(f"{src}: runs of a preset; name it (--preset)")
        return unpack_runs(args)
    if not args.into:
        raise SystemExit(f"{src}: {PIECES[kind]}; name the folder to unpack into (--into)")
    into = Path(args.into)
    if kind == "eval":
        from scripts.gpu_evaluate import unpack as unpack_eval

        unpack_eval(src, into, plots=not args.no_plots)
    elif kind == "study":
        from scripts.gpu_study import unpack as unpack_study

        unpack_study(src, into)
    else:
        from scripts.gpu_machine import unpack as unpack_pipeline

        unpack_pipeline(src, into)
    return 0


def parser() -> tuple[argparse.ArgumentParser, dict]:
    from scripts import gpu_evaluate, gpu_history, gpu_machine, gpu_reproduce, gpu_study, gpu_travel

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0], prog="scripts/gpu.py")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    handlers = {**gpu_machine.add_commands(sub), **gpu_reproduce.add_commands(sub), **gpu_study.add_commands(sub),
                **gpu_evaluate.add_commands(sub), **gpu_travel.add_commands(sub), **gpu_history.add_commands(sub)}
    u = sub.add_parser("unpack", help="here: what a command there brought back (DIR), by what it holds")
    gpu_reproduce.preset_flags(u, required=False)
    u.add_argument("--into", help="a study's or pipeline's folder, or the sweep directory records merge into")
    u.add_argument("--no-plots", action="store_true", help="merged records: reports without the plots")
    u.add_argument("dir", help="the folder holding the pieces (NAME.tar.NNN) and the report")
    handlers["unpack"] = unpack
    return p, handlers


def main(argv: list[str] | None = None) -> int:
    from vitfly.errors import VitflyError

    p, handlers = parser()
    args = p.parse_args(argv)
    if args.command in THERE:
        from scripts.gpu_machine import prepare

        prepare()
    try:
        return handlers[args.command](args)
    except VitflyError as err:
        raise SystemExit(str(err)) from None


if __name__ == "__main__":
    sys.exit(main())
