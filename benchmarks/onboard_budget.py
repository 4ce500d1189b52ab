"""The onboard budget: per-tick latency of the full deployment path of every shipped network, against 33.3 ms.

One tick is what the robot runs between two frames at 30 Hz (``vitfly.eval.onboard_budget``): the sensor part
(the exact metric render through the D435 stereo model and the deployment normalisation to the network's
input) and the network part (batch 1, the recurrent state carried tick to tick, the command deployed). Each
shipped network (``weights/manifest.json``, ``pretrained:NAME``) gets ``--warmup`` untimed ticks, then
``--ticks`` timed ones, on one torch thread; mean, p50, p95, p99 per part, and their share of the period.
Times are elapsed (wall) time, the budget's measure; the process's CPU time is in the JSON beside them (on a
machine shared with other jobs it leaves out the waits for a core).

    .venv/bin/python benchmarks/onboard_budget.py --out runs/onboard_budget.json
    .venv/bin/python benchmarks/onboard_budget.py --models vit_lstm --sensor none      # the ideal camera

The frames: exact renders at the poses of an expert flight through ``--env``/``--preset``/``--seed`` at
``--speed`` (``--frames`` poses, cycled).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys

import torch

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.eval.latency import CLOCKS
from vitfly.eval.onboard_budget import PARTS, budget_ms, fits, flight_frames, summarise, time_deployment
from vitfly.sim.camera import CameraConfig
from vitfly.sim.sensor_models import StereoDepthSensor, sensor_flag_values, sensor_from_dict
from vitfly.zoo.pretrained import load_pretrained, read_manifest


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--models", nargs="+", help="shipped network names (default: every one in weights/manifest.json)")
    p.add_argument("--ticks", type=int, default=1000, help="timed ticks per model")
    p.add_argument("--warmup", type=int, default=100, help="untimed ticks before timing")
    p.add_argument("--frames", type=int, default=300, help="distinct poses rendered (cycled over the ticks)")
    p.add_argument("--env", default="course", help="scene family of the flight whose frames are used")
    p.add_argument("--preset", default="medium", help="scene preset")
    p.add_argument("--seed", type=int, default=0, help="scene seed")
    p.add_argument("--speed", type=float, default=5.0, help="desired speed of the flight, m/s")
    p.add_argument("--sensor", nargs="+", default=["d435"], metavar="MODEL|FIELD=VALUE",
                   help="sensor model and its settings (vitfly.sim.sensor_models), or none for the ideal camera")
    p.add_argument("--control-hz", type=float, default=30.0, help="control rate; the budget is its period")
    p.add_argument("--threads", type=int, default=1, help="torch threads (the paper's onboard setting: 1)")
    p.add_argument("--out", help="write the results as JSON here")
    return p.parse_args(argv)


def _fmt_row(name: str, part: str, s: dict) -> str:
    return (f"| {name} | {part} | {s['mean_ms']:.2f} | {s['p50_ms']:.2f} | {s['p95_ms']:.2f} | {s['p99_ms']:.2f} "
            f"| {100 * s['mean_share']:.0f} % | {100 * s['p99_share']:.0f} % |")


def run(args: argparse.Namespace, log=print) -> dict:
    if args.threads < 1:
        raise VitflyError(f"--threads must be >= 1, got {args.threads}")
    period = budget_ms(args.control_hz)
    shipped = sorted(read_manifest()["models"])
    models = args.models or shipped
    unknown = [m for m in models if m not in shipped]
    if unknown:
        raise VitflyError(f"--models: {unknown[0]!r} is not shipped; weights/manifest.json holds {', '.join(shipped)}")
    try:
        sensor_cfg = sensor_from_dict(sensor_flag_values(args.sensor))
    except ValueError as err:
        raise VitflyError(str(err)) from None
    camera = CameraConfig()
    sensor = None if sensor_cfg is None else StereoDepthSensor(sensor_cfg, camera)
    torch.set_num_threads(args.threads)
    log(f"rendering {args.frames} frames: expert flight, {args.env}/{args.preset} seed {args.seed}, {args.speed:g} m/s")
    frames = flight_frames(args.env, args.preset, args.seed, args.speed, args.frames, camera, args.control_hz)
    results = []
    for name in models:
        net = load_pretrained(name)

        def progress(done: int, total: int, name=name) -> None:
            log(f"  {name}: {done}/{total} ticks ({args.warmup} warm-up)")

        log(f"timing {name} ({args.warmup} warm-up + {args.ticks} timed ticks, {args.threads} thread(s))")
        times = time_deployment(net, frames, sensor, args.ticks, args.warmup, camera.max_range_m, progress)
        summary = {part: {clock: summarise(times[part][clock], period) for clock in CLOCKS} for part in PARTS}
        results.append({"model": name, "fits": fits(summary["total"]["wall"]), "summary": summary})
    payload = {
        "budget_ms": period, "control_hz": args.control_hz, "ticks": args.ticks, "warmup": args.warmup,
        "threads": args.threads, "frames": len(frames),
        "flight": {"env": args.env, "preset": args.preset, "seed": args.seed, "speed_mps": args.speed},
        "sensor": None if sensor_cfg is None else sensor_cfg.model, "sensor_args": args.sensor,
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                    "torch": torch.__version__, "python": platform.python_version()},
        "results": results,
    }
    log(f"\nper tick, ms (wall clock), budget {period:.1f} ms ({args.control_hz:g} Hz), "
        f"sensor {payload['sensor'] or 'ideal camera'}, {args.threads} thread(s), {args.ticks} ticks")
    log("| model | part | mean | p50 | p95 | p99 | mean / budget | p99 / budget |")
    log("|---|---|---:|---:|---:|---:|---:|---:|")
    for r in results:
        for part in PARTS:
            log(_fmt_row(r["model"], part, r["summary"][part]["wall"]))
    log("\nthe same ticks on the process's CPU clock (leaves out waits for a core), ms")
    log("| model | part | mean | p50 | p95 | p99 | mean / budget | p99 / budget |")
    log("|---|---|---:|---:|---:|---:|---:|---:|")
    for r in results:
        for part in PARTS:
            log(_fmt_row(r["model"], part, r["summary"][part]["cpu"]))
    for r in results:
        log(f"{r['model']}: fits the budget (wall p99 <= {period:.1f} ms): {'yes' if r['fits'] else 'no'}")
    if args.out:
        write_text(args.out, json.dumps(payload, indent=1) + "\n")
        log(f"wrote {args.out}")
    return payload


def main(argv: list[str] | None = None) -> int:
    try:
        run(parse_args(argv), log=lambda s: print(s, flush=True))
    except VitflyError as err:
        print(f"onboard_budget: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
