"""Simulator speed, every physics back end side by side in one run (one core).

    .venv/bin/python benchmarks/sim_speed.py                           # all, both back ends (where installed)
    .venv/bin/python benchmarks/sim_speed.py --physics native --skip-collect --json out.json

Per back end (``--physics``, default: pybullet where installed, and native):

1. Back end alone, expert flight (the targets of issue 12): the velocity commands of expert trials
   (60 m at 5 m/s in spheres/medium, 30 Hz) replayed through ``Fleet.track`` (the cascaded
   controller and the rigid body at 240 Hz), once with one scene and once with 16 lockstep scenes
   in one fleet (the native back end steps all 16 in one array operation). Real-time factor =
   simulated s / CPU s of this process, best of ``--repeats`` (the back ends taking turns). The
   replayed flights are compared between back ends against ``vitfly.sim.physics.parity.PARITY_TOLERANCE``.
2. End to end: the real-time factor of one expert trial with the depth camera (every frame rendered
   and kept, as `collect` does), median over ``--trials`` scenes; and closed-loop evaluation trials
   per minute with 16 lockstep scenes (``vitfly.eval.sweep.fly_batch``: expert policy, contact
   tests, metrics, the trials.jsonl write), with outcome and path agreement between back ends. The
   back ends take turns here too, trial by trial and batch by batch.
   The expert, camera and bookkeeping cost the same on every back end, so these gain less.
3. Depth frames per second (the camera alone) and collection frames per second with ``--workers``
   1 and 2 (`vitfly collect`'s library call, HDF5 writes included).
4. The batched torch engine (``vitfly.sim.batched``) beside the numpy engine in the same run: env-steps
   per second (30 Hz ticks, every tick's 90 x 60 depth image rendered) of the expert flying
   ``--batched-scenes`` spheres/medium scenes in lockstep (``--batched-seconds`` simulated seconds each),
   the numpy engine (native back end) on the first ``--numpy-scenes`` of them; CPU time and wall clock,
   each engine's best of ``--batched-repeats`` runs (taking turns), after one untimed warm-up run.
   ``--device cuda --batched-scenes 4096`` runs the batched engine on a GPU; ``--only-batched`` skips 1-3.

    .venv/bin/python benchmarks/sim_speed.py --only-batched --dtype float64 float32 --compile
    .venv/bin/python benchmarks/sim_speed.py --only-batched --device cuda --batched-scenes 4096 --numpy-scenes 64
"""

from __future__ import annotations

import os

# one core: must be set before numpy is imported
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from vitfly.eval import records  # noqa: E402
from vitfly.eval.config import SweepConfig  # noqa: E402
from vitfly.eval.policy_source import PolicySource  # noqa: E402
from vitfly.eval.sweep import fly_batch, make_batches, plan_trials  # noqa: E402
from vitfly.sim import DepthCamera, ExpertPolicy, RolloutConfig, make_scene, run_episodes  # noqa: E402
from vitfly.sim.collect import CollectConfig, collect  # noqa: E402
from vitfly.sim.controller import ControllerGains  # noqa: E402
from vitfly.sim.physics import make_fleet, pybullet_available  # noqa: E402
from vitfly.sim.physics.parity import PARITY_TOLERANCE, state_array, state_gaps, within_tolerance  # noqa: E402
from vitfly.sim.quadrotor import quat_wxyz_to_matrix  # noqa: E402

SUBSTEPS = 8  # 240 Hz physics per 30 Hz tick


def expert_commands(num_scenes: int, speed: float, physics: str) -> np.ndarray:
    """(ticks, scenes, 3) velocity commands (m/s) of expert trials; finished trials hover (zeros)."""
    scenes = [make_scene("spheres", "medium", 30_000 + i) for i in range(num_scenes)]
    logs = [r.log.command for r in run_episodes(scenes, [speed] * num_scenes, ExpertPolicy(),
                                                RolloutConfig(physics=physics))]
    out = np.zeros((max(len(c) for c in logs), num_scenes, 3))
    for i, c in enumerate(logs):
        out[: len(c), i] = c
    return out


def replay(backends: list[str], commands: np.ndarray, repeats: int) -> dict[str, tuple[float, np.ndarray]]:
    """Per back end: the best CPU seconds to fly ``commands`` through it, and the (ticks, N, 13) states flown.

    The back ends take turns, repeat by repeat, so that a change in the machine's load hits them alike.
    """
    ticks, n, _ = commands.shape
    gains = ControllerGains()
    rows = [[tuple(c) for c in tick.tolist()] for tick in commands]
    best = dict.fromkeys(backends, float("inf"))
    history = {b: np.zeros((ticks, n, 13)) for b in backends}
    for rep in range(repeats + 1):  # the first records the states flown, untimed
        for physics in backends:
            with make_fleet(physics, n) as fleet:
                fleet.reset(np.tile([0.0, 0.0, 3.5], (n, 1)))
                states = fleet.states()
                start = time.process_time()
                for t in range(ticks):
                    for _ in range(SUBSTEPS):
                        states = fleet.track(rows[t], states, gains)
                    if rep == 0:
                        history[physics][t] = state_array(states)
                cpu = time.process_time() - start
            if rep > 0:
                best[physics] = min(best[physics], cpu)
    return {b: (best[b], history[b]) for b in backends}


def trial_rtf(trials: int, speed: float, backends: list[str]) -> dict[str, tuple[list, list, list]]:
    """Per back end: real-time factors of whole expert trials with the camera, by wall clock and by CPU
    time, and the results (the back ends take turns, trial by trial)."""
    out: dict = {b: ([], [], []) for b in backends}
    for physics in backends:  # warm-up
        run_episodes([make_scene("spheres", "medium", 999)], [speed], ExpertPolicy(), RolloutConfig(physics=physics))
    for i in range(trials):
        scene = make_scene("spheres", "medium", 20_000 + i)
        for physics in backends:
            cfg = RolloutConfig(record_depth=True, physics=physics)
            start, start_cpu = time.perf_counter(), time.process_time()
            res = run_episodes([scene], [speed], ExpertPolicy(), cfg)[0]
            wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
            wall_rtf, cpu_rtf, results = out[physics]
            wall_rtf.append(res.summary.duration_s / wall)
            cpu_rtf.append(res.summary.duration_s / cpu)
            results.append(res)
    return out


def evaluation(backends: list[str], trials: int, num_envs: int, speed: float, workdir: Path) -> dict[str, dict]:
    """Per back end: expert evaluation through the code behind `vitfly evaluate`, ``num_envs`` lockstep
    scenes (the back ends take turns, batch by batch)."""
    policy = PolicySource("expert", None, "eager", "cpu", 1).build()
    cfgs = {b: SweepConfig(policy="expert", env=["spheres"], speeds=[speed], trials=trials, seed=0,
                           num_envs=num_envs, out=str(workdir / b), gif=False, plots=False, physics=b).validate()
            for b in backends}
    wall, cpu = dict.fromkeys(backends, 0.0), dict.fromkeys(backends, 0.0)
    for batch in make_batches(plan_trials(cfgs[backends[0]]), num_envs):
        for physics, cfg in cfgs.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            fly_batch(batch, policy, cfg, Path(cfg.out) / records.TRIALS_FILE)
            wall[physics] += time.perf_counter() - start
            cpu[physics] += time.process_time() - start_cpu
    out = {}
    for physics, cfg in cfgs.items():
        flown = sorted(records.read_records(Path(cfg.out) / records.TRIALS_FILE), key=lambda r: r.trial)
        out[physics] = {"trials": len(flown), "wall_s": wall[physics], "cpu_s": cpu[physics],
                        "trials_per_min_cpu": 60.0 * len(flown) / cpu[physics],
                        "trials_per_min_wall": 60.0 * len(flown) / wall[physics], "records": flown}
    return out


def depth_fps(results) -> float:
    camera = DepthCamera()
    frames = 0
    start = time.perf_counter()
    for res in results:
        rot = quat_wxyz_to_matrix(res.log.quat)
        for pos, r in zip(res.log.position, rot, strict=True):
            camera.render(res.scene, pos, r)
            frames += 1
    return frames / (time.perf_counter() - start)


def collect_fps(workers: int, trajectories: int, physics: str) -> tuple[float, int, float]:
    cfg = CollectConfig(trajectories=trajectories, workers=workers, seed=5, speeds=(3.0, 7.0), physics=physics)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        summary = collect(cfg, Path(tmp) / "bench.h5", progress=False)
        wall = time.perf_counter() - start
    return summary.frames / wall, summary.frames, wall


class _DepthExpert(ExpertPolicy):
    """The expert, with every tick's depth image rendered (as a learned policy would need it)."""

    needs_depth = True


def batched_speed(args) -> dict:
    """Env-steps per second of the expert with depth rendered: numpy engine vs the batched engine."""
    import torch

    from vitfly.sim.batched.policies import as_batched_policy
    from vitfly.sim.batched.rollout import BatchedSettings, run_batched
    from vitfly.sim.rollout import TaskConfig

    def depth_expert(compiled: bool):
        """The batched expert (its kernels compiled with the engine's), rendering every tick as collect does."""
        policy = as_batched_policy(ExpertPolicy(), compile=compiled)
        policy.needs_depth = True
        return policy

    torch.set_num_threads(args.threads)
    task = TaskConfig(timeout_s=args.batched_seconds, timeout_speed_factor=0.0)
    cfg = RolloutConfig(physics="native", task=task)
    scenes = [make_scene("spheres", "medium", 30_000 + i) for i in range(args.batched_scenes)]
    speeds = [args.speed] * len(scenes)
    out: dict = {"scenes": len(scenes), "simulated_s": args.batched_seconds, "threads": args.threads,
                 "device": args.device}

    def timed(run) -> tuple[float, float, int]:
        start, start_cpu = time.perf_counter(), time.process_time()
        results = run()
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
        return wall, cpu, sum(len(r.log) for r in results)

    n_np = min(args.numpy_scenes, len(scenes))
    runs = {"numpy": lambda: run_episodes(scenes[:n_np], speeds[:n_np], _DepthExpert(), cfg)}
    warmup = {}
    for dtype_name in args.dtype:
        for compiled in sorted({False, args.compile}):
            key = f"{dtype_name}{'_compiled' if compiled else ''}"
            settings = BatchedSettings(device=args.device, dtype=getattr(torch, dtype_name), compile=compiled)
            runs[key] = lambda s=settings, c=compiled: run_batched(scenes, speeds, depth_expert(c), cfg, settings=s)
            # warm-up: the timed run once, untimed, so that every compile (first call, then the sizes
            # the batch takes as episodes end) happens here; its seconds are reported beside
            start = time.perf_counter()
            runs[key]()
            warmup[key] = time.perf_counter() - start
            print(f"   (warm-up of batched {key}: {warmup[key]:.1f} s)", flush=True)
    # the engines take turns, repeat by repeat, and each one's best (least CPU time) counts
    best: dict = {}
    for _ in range(args.batched_repeats):
        for key, run in runs.items():
            wall, cpu, steps = timed(run)
            if key not in best or cpu < best[key][1]:
                best[key] = (wall, cpu, steps)
    wall, cpu, steps = best["numpy"]
    out["numpy"] = {"scenes": n_np, "env_steps": steps, "wall_s": wall, "cpu_s": cpu,
                    "steps_per_s_wall": steps / wall, "steps_per_s_cpu": steps / cpu}
    print(f"4. expert with depth, spheres/medium, {args.batched_seconds:g} s episodes, env-steps/s "
          f"(CPU time / wall clock), torch threads {args.threads}, best of {args.batched_repeats}")
    print(f"   numpy engine, {n_np} scenes: {steps / cpu:8.0f} / {steps / wall:8.0f}", flush=True)
    for key, warm in warmup.items():
        wall, cpu, steps = best[key]
        row = out[key] = {"env_steps": steps, "wall_s": wall, "cpu_s": cpu, "warmup_s": warm,
                          "steps_per_s_wall": steps / wall, "steps_per_s_cpu": steps / cpu,
                          "ratio_cpu": (steps / cpu) / out["numpy"]["steps_per_s_cpu"],
                          "ratio_wall": (steps / wall) / out["numpy"]["steps_per_s_wall"]}
        print(f"   batched {args.device} {key:18s} {len(scenes)} scenes: {row['steps_per_s_cpu']:8.0f} / "
              f"{row['steps_per_s_wall']:8.0f}  ({row['ratio_cpu']:.2f}x / {row['ratio_wall']:.2f}x numpy; "
              f"warm-up {warm:.1f} s)", flush=True)
    return out


def fmt_gaps(gaps: dict) -> str:
    return ", ".join(f"{k} {v:.1e}" for k, v in gaps.items())


def outcome(record) -> tuple:
    """What two back ends must agree on for a trial: success (the paper's and the strict), why it ended, and the
    physics engine's contact count."""
    return record.success_paper, record.success_strict, record.end_reason, record.extra["physics_collisions"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default_physics = ["pybullet", "native"] if pybullet_available() else ["native"]
    parser.add_argument("--physics", nargs="+", choices=("pybullet", "native"), default=default_physics,
                        help="back ends to measure side by side (the first is the reference for agreement)")
    parser.add_argument("--trials", type=int, default=5, help="expert trials with the camera, per back end")
    parser.add_argument("--speed", type=float, default=5.0, help="desired speed of every flight, m/s")
    parser.add_argument("--lockstep", type=int, default=16, help="scenes stepped together")
    parser.add_argument("--eval-trials", type=int, default=32, help="evaluation trials per back end")
    parser.add_argument("--repeats", type=int, default=5, help="replays per back end (best CPU time counts)")
    parser.add_argument("--collect-trajectories", type=int, default=8, help="trajectories per collect run")
    parser.add_argument("--skip-collect", action="store_true")
    parser.add_argument("--json", help="also write the numbers here")
    parser.add_argument("--only-batched", action="store_true", help="only part 4, the batched engine")
    parser.add_argument("--skip-batched", action="store_true", help="skip part 4")
    parser.add_argument("--batched-scenes", type=int, default=64, help="lockstep scenes of the batched engine")
    parser.add_argument("--numpy-scenes", type=int, default=64, help="of those, flown by the numpy engine too")
    parser.add_argument("--batched-seconds", type=float, default=4.0, help="simulated seconds per episode")
    parser.add_argument("--batched-repeats", type=int, default=3,
                        help="timed runs per engine in part 4, taking turns (best CPU time counts)")
    parser.add_argument("--device", default="cpu", help="the batched engine's device: cpu, cuda, cuda:1, ...")
    parser.add_argument("--dtype", nargs="+", choices=("float64", "float32"), default=["float64", "float32"])
    parser.add_argument("--compile", action="store_true", help="also time the batched engine with torch.compile")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the batched engine")
    args = parser.parse_args()
    ref = args.physics[0]
    if args.only_batched:
        out = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs",
               "batched": batched_speed(args)}
        if args.json:
            Path(args.json).write_text(json.dumps(out, indent=2, default=str))
        return

    out: dict = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs",
                 "python": platform.python_version(), "physics": args.physics, "tolerance": PARITY_TOLERANCE}
    commands = {1: expert_commands(1, args.speed, ref), args.lockstep: expert_commands(args.lockstep, args.speed, ref)}
    print(f"1. back end alone: expert velocity commands ({args.speed:g} m/s, spheres/medium) through the controller "
          f"and the rigid body at 240 Hz, CPU time, best of {args.repeats}")
    flown: dict = {}
    for n, cmds in commands.items():
        sim_s = cmds.shape[0] * SUBSTEPS / 240.0
        replays = replay(args.physics, cmds, args.repeats)
        for physics in args.physics:
            cpu, history = replays[physics]
            flown[(physics, n)] = history
            row = out.setdefault("backend_alone", {}).setdefault(f"{n}_scenes", {})
            row[physics] = {"sim_s": sim_s, "cpu_s": cpu, "rtf": sim_s / cpu, "drone_s_per_s": n * sim_s / cpu}
            line = f"   {n:2d} scene(s), {physics:8s}: real-time factor {sim_s / cpu:7.1f}"
            if physics != ref:
                ratio = row[ref]["cpu_s"] / cpu
                gaps = state_gaps(flown[(ref, n)], history)
                row[physics].update(speedup=ratio, gaps=gaps, within_tolerance=within_tolerance(gaps))
                line += f"  ({ratio:.2f}x {ref}; gaps to {ref}: {fmt_gaps(gaps)})"
            print(line, flush=True)

    print(f"2. end to end, {args.trials} expert trials with the camera (median), and {args.eval_trials} evaluation "
          f"trials with {args.lockstep} lockstep scenes")
    trials = trial_rtf(args.trials, args.speed, args.physics)
    results, ref_records = trials[ref][2], []
    with tempfile.TemporaryDirectory(prefix="vitfly-sim-speed-") as tmp:
        evaluations = evaluation(args.physics, args.eval_trials, args.lockstep, args.speed, Path(tmp))
        for physics in args.physics:
            wall_rtf, cpu_rtf, res = trials[physics]
            ev = evaluations[physics]
            row = out.setdefault("end_to_end", {})[physics] = {
                "trial_rtf_wall_median": float(np.median(wall_rtf)), "trial_rtf_cpu_median": float(np.median(cpu_rtf)),
                "trial_success": f"{sum(r.summary.success for r in res)}/{len(res)}",
                **{k: v for k, v in ev.items() if k != "records"}}
            line = (f"   {physics:8s}: trial real-time factor {row['trial_rtf_cpu_median']:6.1f} (CPU), "
                    f"{row['trial_rtf_wall_median']:6.1f} (wall); evaluation {row['trials_per_min_cpu']:6.1f} "
                    f"trials/min (CPU), {row['trials_per_min_wall']:6.1f} (wall)")
            if physics != ref:
                base = out["end_to_end"][ref]
                mine, theirs = ev["records"], ref_records
                same = sum(outcome(a) == outcome(b) for a, b in zip(mine, theirs, strict=True))
                path_gap = max(float(np.abs(np.asarray(a.path["position"]) - np.asarray(b.path["position"])).max())
                               for a, b in zip(mine, theirs, strict=True) if len(a.path["time"]) == len(b.path["time"]))
                row.update(trial_rtf_speedup=row["trial_rtf_cpu_median"] / base["trial_rtf_cpu_median"],
                           eval_speedup=row["trials_per_min_cpu"] / base["trials_per_min_cpu"],
                           same_outcome=f"{same}/{len(mine)}", max_path_gap_m=path_gap)
                line += (f"  ({row['trial_rtf_speedup']:.2f}x and {row['eval_speedup']:.2f}x {ref}; same outcome "
                         f"{same}/{len(mine)}, paths within {path_gap:.0e} m as stored, 0.1 mm rounding)")
            else:
                ref_records = ev["records"]
            print(line, flush=True)

    out["depth_fps"] = depth_fps(results)
    print(f"3. depth frames per second (60x90, camera alone): {out['depth_fps']:.0f}")
    if not args.skip_collect:
        for physics in args.physics:
            for workers in (1, 2):
                fps, frames, wall = collect_fps(workers, args.collect_trajectories, physics)
                out.setdefault("collect_fps", {})[f"{physics}_workers{workers}"] = fps
                print(f"   collect, {physics}, --workers {workers}: {fps:.0f} frames/s ({frames} frames in "
                      f"{wall:.1f} s, {args.collect_trajectories} trajectories, HDF5 writes included)", flush=True)
    if not args.skip_batched:
        out["batched"] = batched_speed(args)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2, default=str))


if __name__ == "__main__":
    main()
