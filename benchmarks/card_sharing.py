"""Several training processes on one GPU: taking turns, or sharing it through MPS, side by side in one run.

A GPU slot trains its runs as separate processes (``scripts/gpu.py train``). By default their contexts take
turns on the card; through an MPS server (``scripts/gpu_mps.py``) their kernels run side by side. This
benchmark says which pays for an arm's step, as the slot would run it: first one process alone, then
``--processes`` at once taking turns, then the same number through a private MPS daemon (where the machine
has one and a CUDA client starts through it; otherwise that phase is left out and the output says why).

Each process builds one model's training step as ``--arm`` trains it (``benchmarks/train_speed.py``'s set-up:
the preset's batch, padding, precision and compile mode, a synthetic batch of ``--steps`` real steps per
trajectory), runs ``--warmup`` batches (compilation and CUDA-graph capture happen there), waits until every
process of its phase is warm, and then counts the batches it finishes in the same ``--window-s`` seconds. A
phase's rate is the sum of its processes' real frames/s; each phase is also given as a ratio to the process
alone, so ``shared / turns`` says what MPS adds on this card. On a shared machine compare only numbers of one run.

    python3 benchmarks/card_sharing.py --arm paper --model vit_lstm --processes 3 --window-s 20 --json $OUT/sharing.json
    .venv/bin/python benchmarks/card_sharing.py --arm paper --model convnet --mode unpadded --steps 64 \\
        --processes 2 --window-s 3 --device cpu --threads 1       # CPU-sized: the machinery, no MPS phase
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BENCH_DIR = Path(__file__).resolve().parent
for path in (ROOT, BENCH_DIR):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from train_speed import ARM_MODES, ARMS, arm_batch_fn, arm_settings  # noqa: E402

from scripts.gpu_mps import SharedCard  # noqa: E402

READY_TIMEOUT_S = 600.0  # a compiled ViT's warm-up took 14-40 s on the H100 and H200


def worker(spec: dict) -> dict:
    """One process of a phase: warm up, say so, wait for the start, then count batches for ``window_s``."""
    one_batch, padded = arm_batch_fn(spec["model"], spec["policy_kwargs"], spec["batch"], spec["steps"],
                                     spec["bucket"], spec["precision"], spec["device"], spec["threads"])
    start = time.perf_counter()
    for _ in range(spec["warmup"]):
        one_batch()
    warmup_s = time.perf_counter() - start
    folder = Path(spec["folder"])
    (folder / f"ready.{spec['rank']}").touch()
    while not (folder / "go").exists():
        time.sleep(0.005)
    start, batches = time.perf_counter(), 0
    while time.perf_counter() - start < spec["window_s"]:
        one_batch()
        batches += 1
    seconds = time.perf_counter() - start
    frames = spec["batch"] * spec["steps"] * batches  # real frames, not padding
    return {"batches": batches, "seconds": seconds, "fps": frames / seconds, "warmup_s": warmup_s,
            "padded": padded}


def run_phase(spec: dict, processes: int) -> list[dict]:
    """``processes`` workers started at once (with this process's environment: MPS's when it is set), timed
    over one common window; their results in rank order."""
    with tempfile.TemporaryDirectory(prefix="vitfly-sharing-") as folder:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(BENCH_DIR)])}
        procs = []
        for rank in range(processes):
            one = json.dumps({**spec, "rank": rank, "folder": folder})
            procs.append(subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker", one],
                                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env))
        deadline = time.monotonic() + READY_TIMEOUT_S
        while len(list(Path(folder).glob("ready.*"))) < processes:
            failed = [p for p in procs if p.poll() not in (None, 0)]
            if failed or time.monotonic() > deadline:
                for p in procs:
                    p.kill()
                why = failed[0].communicate()[1][-2000:] if failed else f"not warm in {READY_TIMEOUT_S:.0f} s"
                raise SystemExit(f"card_sharing: a process of the phase failed: {why}")
            time.sleep(0.05)
        (Path(folder) / "go").touch()
        results = []
        for p in procs:
            out, err = p.communicate()
            lines = [line for line in out.splitlines() if line.startswith("RESULT ")]
            if p.returncode != 0 or not lines:
                raise SystemExit(f"card_sharing: a process exited {p.returncode}: {err[-2000:]}")
            results.append(json.loads(lines[-1][len("RESULT "):]))
    return results


def phase_row(name: str, results: list[dict], alone_fps: float | None) -> dict:
    total = sum(r["fps"] for r in results)
    return {"phase": name, "processes": len(results), "fps_each": [round(r["fps"], 1) for r in results],
            "fps_total": round(total, 1), "vs_alone": round(total / alone_fps, 3) if alone_fps else 1.0,
            "warmup_s": [round(r["warmup_s"], 1) for r in results]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arm", choices=sorted(ARMS), default="paper")
    parser.add_argument("--model", default="vit_lstm")
    parser.add_argument("--mode", choices=[m for m in ARM_MODES if m != "loop"], default="recipe",
                        help="the arm's step as train_speed.py's --modes sets it up")
    parser.add_argument("--processes", type=int, default=3, help="processes of the turns and shared phases")
    parser.add_argument("--steps", type=int, default=418, help="real steps per synthetic trajectory")
    parser.add_argument("--warmup", type=int, default=5, help="untimed batches per process first")
    parser.add_argument("--window-s", type=float, default=20.0, help="the common timed window of a phase")
    parser.add_argument("--device", default=None, help="cuda (default when present) or cpu")
    parser.add_argument("--threads", type=int, default=2, help="torch threads per process (the slot's runs: 2)")
    parser.add_argument("--json", help="also write the phases to this file")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        print("RESULT " + json.dumps(worker(json.loads(args.worker))), flush=True)
        return 0
    if args.processes < 2:
        parser.error("--processes: at least 2 (one process alone is always measured)")
    if args.device is None:
        import torch

        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    spec = {"model": args.model, **arm_settings(args.arm, args.model, args.mode), "steps": args.steps,
            "warmup": args.warmup, "window_s": args.window_s, "device": args.device, "threads": args.threads}
    print(f"{args.arm} arm, {args.model} ({args.mode}): batch {spec['batch']} x {args.steps} steps, "
          f"{spec['precision']}, bucket {spec['bucket']}, on {args.device}; a {args.window_s:.0f} s window per phase",
          flush=True)
    rows, notes = [], {}
    alone = phase_row("alone", run_phase(spec, 1), None)
    rows.append(alone)
    rows.append(phase_row("turns", run_phase(spec, args.processes), alone["fps_total"]))
    with SharedCard(args.processes, wanted=args.device.startswith("cuda")) as card:
        notes["mps"] = card.info if args.device.startswith("cuda") else {"mps": False, "note": "not a CUDA device"}
        if card.info["mps"]:
            rows.append(phase_row("shared (MPS)", run_phase(spec, args.processes), alone["fps_total"]))
    turns = rows[1]["fps_total"]
    print("\n| phase | processes | frames/s each | frames/s in all | vs one alone |\n|---|---:|---|---:|---:|")
    for r in rows:
        print(f"| {r['phase']} | {r['processes']} | {', '.join(f'{f:,.0f}' for f in r['fps_each'])} | "
              f"{r['fps_total']:,.0f} | {r['vs_alone']:.2f}x |")
    if card.info["mps"]:
        print(f"\nshared / turns: {rows[2]['fps_total'] / turns:.2f}x")
    else:
        print(f"\nno MPS phase: {notes['mps']['note']}")
    if args.json:
        Path(args.json).write_text(json.dumps({"arm": args.arm, "model": args.model, "mode": args.mode,
                                               "settings": spec, "phases": rows, **notes}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
