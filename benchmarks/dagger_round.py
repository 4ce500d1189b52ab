"""One DAgger round on each simulator engine, side by side in one run: the seconds `vitfly dagger` spends
flying a round that mixes a student with the expert.

    .venv/bin/python benchmarks/dagger_round.py                       # CPU: 32 flights, every engine setting
    python3 benchmarks/dagger_round.py --device cuda --flights 588 --json $OUT/dagger_round.json   # a GPU

Each setting runs the ``tiny`` preset's round 0 (``run_dagger(..., stop_after="r0.collect")``) with
``--flights`` flights in one lockstep batch, the shipped ``--student`` mixed with the expert at beta 0.5,
into a fresh folder: the numpy engine, then the batched engine eagerly in float64, compiled in float64 and
compiled in float32 (``--settings`` picks some). Its seconds include the process's compiles, as a user's first
round would. ``--device`` is where the batched engine and the student run (the numpy engine's student too).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

SETTINGS = {"numpy": {}, "batched": {"sim": "batched"},
            "compiled": {"sim": "batched", "sim_compile": True},
            "compiled-float32": {"sim": "batched", "sim_compile": True, "sim_dtype": "float32"}}


def fly_round(setting: str, flights: int, student: str, device: str, out: Path) -> dict:
    from vitfly.workflows.dagger import run_dagger
    from vitfly.workflows.dagger_config import load_dagger_config

    engine = dict(SETTINGS[setting])
    if engine:
        engine["sim_device"] = device
    cfg = load_dagger_config("dagger", "tiny", {
        "out": str(out), "threads": 1, "schedule": {"beta0": 0.5}, "train": {"init_checkpoint": student},
        "data": {"expert_trajectories": flights, "num_envs": flights, "collect": engine},
        "evaluate": {"device": device}})
    t0 = time.perf_counter()
    run_dagger(cfg, stop_after="r0.collect", progress=False)
    manifest = json.loads((out / "manifests" / "r0.collect.json").read_text())["result"]
    return {"setting": setting, "seconds": round(time.perf_counter() - t0, 1), "flights": flights,
            "frames": manifest["round_frames"], "expert_tick_share": manifest["expert_tick_share"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flights", type=int, default=32, help="flights in the round, all in one batch")
    parser.add_argument("--student", default="pretrained:convnet", help="the student mixed with the expert")
    parser.add_argument("--device", default="cpu", help="the batched engine's and the student's device")
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS))
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for setting in args.settings:
            rows.append(fly_round(setting, args.flights, args.student, args.device, Path(tmp) / setting))
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1) + "\n")
    base = rows[0]["seconds"]
    print(f"| engine ({args.flights} flights, {args.student}, beta 0.5) | seconds | time / {rows[0]['setting']} "
          "| frames | expert share |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['setting']} | {r['seconds']} | {r['seconds'] / base:.2f}x | {r['frames']} | "
              f"{r['expert_tick_share']:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
