"""A ``vitfly evaluate`` sweep flown on the GPU machine, its trial records carried home and merged there.

There (the batched policy on the card, the simulator on the machine's 16 cores):

    python3 scripts/gpu.py evaluate --out $OUT -- --policy pretrained:vit_lstm --env spheres \\
        --speeds 3 5 7 --trials 100 --num-envs 16 --workers 14

Everything after ``--`` goes to ``vitfly evaluate`` as it is, but ``--out`` (the sweep is flown into
``--work``/eval) and ``--device`` (``cuda`` where there is one, unless given). A checkpoint policy travels with
the call (the device tool's ``carry``); ``pretrained:NAME`` is in the tree already. The sweep is stopped at
``--deadline-s``: its trials are appended one by one as they finish, so what was flown comes back (a later
slot flies the sweep from its start again unless its ``--work`` holds the records; merged here, each trial is
kept once). The records and reports (``trials*.jsonl``, ``summary.*``,
``paired.csv``; no plots or GIFs) and the log go into ``eval.tar.NNN``; ``gpu_evaluate.json`` says what ran and
holds the pieces' manifest.

Here:

    python3 scripts/gpu.py unpack DIR --into runs/eval/spheres

merges the returned records into the sweep directory as ``vitfly evaluate --merge`` does (records already there
are kept, a label flown with another setup is refused before anything is written) and writes its reports.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
REPORT = "gpu_evaluate.json"  # what ran, and the manifest of eval.tar.NNN
RECORD_SUFFIXES = (".jsonl", ".csv", ".md", ".json")  # records and reports; plots and GIFs stay there


def log(msg: str) -> None:
    print(f"[gpu-evaluate {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def evaluate_command(evaluate_args: list[str], sweep: Path, device: str) -> list[str]:
    args = [a for a in evaluate_args if a != "--"][:]
    if "--out" in args:
        raise SystemExit("evaluate: --out is set by scripts/gpu.py (the sweep is flown into --work/eval); "
                         "name what comes back with gpu.py's own --out, before '--'")
    if "--device" not in args:
        args += ["--device", device]
    if "--no-progress" not in args:
        args.append("--no-progress")
    return [sys.executable, "-m", "vitfly.cli", "evaluate", *args, "--out", str(sweep)]


def copy_records(sweep: Path, dst: Path) -> int:
    """The sweep's records and reports (not its plots or GIFs) into ``dst``; returns the trials among them."""
    from vitfly.eval.records import read_sweep

    dst.mkdir(parents=True, exist_ok=True)
    for path in sorted(sweep.iterdir()) if sweep.is_dir() else []:
        if path.is_file() and path.suffix in RECORD_SUFFIXES:
            shutil.copy(path, dst / path.name)
    return len(read_sweep(dst)) if any(dst.glob("trials*.jsonl")) else 0


def run_logged(cmd: list[str], logfile: Path, timeout_s: float) -> tuple[int | None, float]:
    """``cmd`` with its output in ``logfile``; (exit status, or None if killed at ``timeout_s``; seconds)."""
    t0 = time.monotonic()
    with open(logfile, "w") as out:
        out.write(" ".join(cmd) + "\n")
        out.flush()
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
        try:
            rc = proc.wait(timeout=max(1.0, timeout_s))
        except subprocess.TimeoutExpired:  # the trials finished so far are on disk, one record a line
            os.killpg(proc.pid, 9)
            proc.wait()
            rc = None
    return rc, time.monotonic() - t0


def evaluate(args: argparse.Namespace) -> int:
    from scripts.gpu_pack import fresh_dir, pack
    from scripts.gpu_study import device

    start = time.monotonic()
    out, work = Path(args.out), Path(args.work)
    out.mkdir(parents=True, exist_ok=True)
    (out / REPORT).unlink(missing_ok=True)
    sweep, stage, logs = work / "eval", fresh_dir(work / "stage"), fresh_dir(work / "logs")
    cmd = evaluate_command(args.evaluate_args, sweep, device())
    log(" ".join(cmd[2:]))
    rc, wall_s = run_logged(cmd, logs / "evaluate.log", args.deadline_s - args.reserve_s)
    trials = copy_records(sweep, stage / "eval")
    tail = (logs / "evaluate.log").read_text().strip().splitlines()[-3:]
    log(f"rc {rc}, {trials} trials in {wall_s:.0f} s; " + " | ".join(tail))
    report = {"command": cmd[2:], "rc": rc, "wall_s": round(wall_s, 1), "trials": trials, "device": device(),
              "log_tail": tail}
    shutil.copy(logs / "evaluate.log", stage / "evaluate.log")
    entries = [("eval", stage / "eval"), ("evaluate.log", stage / "evaluate.log")] if trials else \
        [("evaluate.log", stage / "evaluate.log")]
    report["pack"] = pack(entries, out, "eval", work, int(args.return_mib * 2**20))
    if report["pack"]["left_out"]:
        report["note"] = f"not returned: {report['pack']['left_out']} (the trip back holds {args.return_mib} MiB)"
    report["elapsed_s"] = round(time.monotonic() - start, 1)
    (out / REPORT).write_text(json.dumps(report, indent=1) + "\n")
    return 0 if trials and "eval" not in report["pack"]["left_out"] else 1


def unpack(src: Path, into: Path, plots: bool = True) -> int:
    """Here: the returned records merged into the sweep directory (or published folder) ``into`` and its reports
    written under their title; returns the number of new trials."""
    from scripts.gpu_pack import fresh_dir
    from scripts.gpu_pack import unpack as unpack_pieces
    from vitfly.eval.evaluation import merge_into, write_outputs
    from vitfly.eval.report import summary_title

    tmp = fresh_dir(into.parent / f".{into.name}.gpu_unpack")
    try:
        unpack_pieces(src, "eval", tmp, REPORT)
        if not (tmp / "eval").is_dir():
            raise SystemExit(f"{src}: no trial records came back; see evaluate.log in {src / REPORT}")
        into.mkdir(parents=True, exist_ok=True)
        new = merge_into(into, [tmp / "eval"])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    _, files = write_outputs(into, plots, title=summary_title(into))
    print(f"{into}: merged {new} new trials; wrote " + ", ".join(str(p) for p in files.values()))
    return new


def add_commands(sub) -> dict:
    """``evaluate`` on ``scripts/gpu.py``'s subparsers; returns name -> handler."""
    p = sub.add_parser("evaluate", help="there: a vitfly evaluate sweep on the card, its records packed",
                       description="there: `vitfly evaluate` with the arguments after '--', records packed")
    p.add_argument("--out", required=True, help="what comes back: eval.tar.NNN and gpu_evaluate.json")
    p.add_argument("--work", default="/tmp/vitfly-eval", help="the sweep directory and packing")
    p.add_argument("--deadline-s", type=float, default=560.0, help="the whole command, from its start")
    p.add_argument("--reserve-s", type=float, default=20.0, help="left after flying for packing")
    p.add_argument("--return-mib", type=float, default=105.0, help="what the pieces may hold (7 x 15 MiB)")
    p.add_argument("evaluate_args", nargs=argparse.REMAINDER, metavar="-- EVALUATE_ARGS",
                   help="vitfly evaluate's flags (--policy, --env, --speeds, --trials, --workers, ...)")
    return {"evaluate": evaluate}
