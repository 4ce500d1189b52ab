"""Train the paper's networks side by side on one GPU machine inside one time-boxed command.

    python3 scripts/gpu.py study --config scripts/gpu_study.yaml --out DIR [--work /tmp/vitfly-study]
    python3 scripts/gpu.py unpack DIR --into runs/gpu_study        # here: end/, middle/, logs/

(``scripts/gpu_study.py ARGS``, the old command line, is ``scripts/gpu.py study ARGS``.)

Stages, each shrunk to fit ``deadline_s`` (the device tool kills a command after 10 minutes):

1. collect the spheres dataset (``vitfly collect``);
2. ``benchmarks/train_speed.py`` on the GPU (frames/s in fp32, bf16 and compiled);
3. every run of ``train.runs`` as its own ``vitfly fit`` process, all at once (small TBPTT batches leave an
   H100 mostly idle, so concurrent runs cost each other little), each capped by ``trainer.max_time``;
   a checkpoint every epoch;
4. evaluation speed of the batched policy on the GPU (``vitfly evaluate --device cuda``, trials/min);
5. each run's last epoch (and, for ``publish.middle_for``, its middle epoch) published as fp16
   safetensors with a manifest (``vitfly.zoo.save_pretrained``) and packed for the trip back.

DIR receives ``study.json`` (what ran, how long, frames/s, and the manifest of the pieces), ``run.log`` and
``study.tar.NNN`` (the weights, metrics.csv of every run, the benchmark table; ``scripts/gpu_pack.py``).
``scripts/gpu.py unpack`` unpacks ``end/``, ``middle/`` (weights directories: ``VITFLY_WEIGHTS_DIR``) and
``logs/``. On the device machine, ``scripts/gpu.py`` first installs the wheels it lacks (``.whl/``, carried).
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

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
REPORT = "study.json"  # what ran, how long, and the manifest of study.tar.NNN


class Clock:
    def __init__(self, deadline_s: float):
        self.start = time.monotonic()
        self.deadline = self.start + deadline_s

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def left(self) -> float:
        return self.deadline - time.monotonic()


def log(msg: str) -> None:
    print(f"[study {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def run_logged(cmd: list[str], logfile: Path, timeout_s: float) -> tuple[int | None, float]:
    """Run ``cmd`` with its output in ``logfile``; returns (exit code or None on timeout, seconds)."""
    t0 = time.monotonic()
    with open(logfile, "w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
        try:
            rc = proc.wait(timeout=max(1.0, timeout_s))
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
            proc.wait()
            rc = None
    return rc, time.monotonic() - t0


def device() -> str:
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"  # cpu: a dry run of the script anywhere


def vitfly(*args: str) -> list[str]:
    return [sys.executable, "-m", "vitfly.cli", *args]


def hms(seconds: float) -> str:
    s = max(60, int(seconds))
    return f"00:{s // 3600:02d}:{s % 3600 // 60:02d}:{s % 60:02d}"


def collect(cfg: dict, data: Path, logs: Path, clock: Clock) -> dict:
    d = cfg["data"]
    cmd = vitfly("collect", "--config", "configs/collect/spheres.yaml", "--out", str(data),
                 "--trajectories", str(d["trajectories"]), "--speeds", *map(str, d["speeds"]),
                 "--seed", str(d["seed"]), "--workers", str(d["workers"]), "--physics", d["physics"],
                 "--no-progress")
    rc, wall = run_logged(cmd, logs / "collect.log", clock.left() * 0.25)
    log(f"collect: rc {rc}, {wall:.0f} s: " + (logs / "collect.log").read_text().strip().splitlines()[0])
    if rc != 0:
        raise SystemExit(f"collect failed (rc {rc}); see {logs / 'collect.log'}")
    return {"rc": rc, "wall_s": wall}


def benchmark(cfg: dict, logs: Path, clock: Clock) -> dict:
    b = cfg["benchmark"]
    cmd = [sys.executable, "benchmarks/train_speed.py", "--models", *b["models"], "--modes", *b["modes"],
           "--batch", str(b["batch"]), "--steps", str(b["steps"]), "--iters", str(b["iters"]),
           "--warmup", str(b["warmup"]), "--device", device(), "--json", str(logs / "train_speed.json")]
    rc, wall = run_logged(cmd, logs / "train_speed.log", min(b["timeout_s"], clock.left() * 0.25))
    log(f"benchmark: rc {rc}, {wall:.0f} s")
    return {"rc": rc, "wall_s": wall}


def fit_command(name: str, run: dict, common: dict, data: Path, root: Path, max_time_s: float) -> list[str]:
    flags = {**common, **run.get("args", {}), "--data.data_path": str(data),
             "--trainer.default_root_dir": str(root / name), "--trainer.max_time": hms(max_time_s)}
    cmd = vitfly("fit", "--config", run["config"])
    for key, value in flags.items():
        cmd += [key, "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)]
    # a checkpoint every epoch beside best/last: the middle of the run is published too
    cmd += ["--trainer.callbacks+=ModelCheckpoint", "--trainer.callbacks.every_n_epochs=1",
            "--trainer.callbacks.save_top_k=-1", "--trainer.callbacks.filename=epoch{epoch:03d}",
            "--trainer.callbacks.auto_insert_metric_name=false"]
    return cmd


def train(cfg: dict, data: Path, work: Path, logs: Path, clock: Clock, eval_s: float) -> dict:
    """All runs at once; a run that fails early is started once more with ``train.fallback_args``."""
    t = cfg["train"]
    window = clock.left() - t["reserve_s"] - eval_s
    hard = time.monotonic() + window
    log(f"train: {len(t['runs'])} runs at once in {window:.0f} s")

    def launch(name: str, extra: dict) -> dict:
        max_time_s = hard - time.monotonic() - 45  # start-up, the epoch in flight and the last validation
        run = {**t["runs"][name], "args": {**t["runs"][name].get("args", {}), **extra}}
        cmd = fit_command(name, run, t["fit_args"], data, work / "runs", max_time_s)
        out = open(logs / f"fit_{name}.log", "a")
        out.write(" ".join(cmd) + "\n")
        out.flush()
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
        return {"proc": proc, "out": out, "t0": time.monotonic(), "retried": bool(extra)}

    live = {name: launch(name, {}) for name in t["runs"]}
    result = {}
    while live:
        time.sleep(2.0)
        for name, r in list(live.items()):
            rc = r["proc"].poll()
            if rc is None and time.monotonic() < hard:
                continue
            if rc is None:
                os.killpg(r["proc"].pid, 9)
                r["proc"].wait()
            r["out"].close()
            wall = time.monotonic() - r["t0"]
            del live[name]
            if rc not in (0, None) and not r["retried"] and hard - time.monotonic() > 0.5 * window:
                log(f"fit {name}: rc {rc} after {wall:.0f} s; once more with {t['fallback_args']}")
                shutil.rmtree(work / "runs" / name, ignore_errors=True)
                live[name] = launch(name, t["fallback_args"])
                continue
            result[name] = {"rc": rc, "wall_s": wall, "fallback": r["retried"]}
            log(f"fit {name}: rc {rc}, {wall:.0f} s" + (" (fallback)" if r["retried"] else ""))
    return result


def epoch_checkpoints(run_dir: Path) -> list[Path]:
    return sorted(run_dir.glob("version_*/checkpoints/epoch*.ckpt"))


def eval_speed(cfg: dict, work: Path, logs: Path, clock: Clock) -> dict:
    e = cfg["eval_cuda"]
    ckpts = sorted((work / "runs" / e["run"]).glob("version_*/checkpoints/last.ckpt"))
    if not ckpts or clock.left() < e["timeout_s"] + 40:
        return {"skipped": True}
    out = work / "eval_cuda"
    cmd = vitfly("evaluate", "--policy", str(ckpts[-1]), "--env", "spheres", "--speeds", *map(str, e["speeds"]),
                 "--trials", str(e["trials"]), "--num-envs", str(e["num_envs"]), "--workers", str(e["workers"]),
                 "--device", device(), "--physics", "native", "--out", str(out), "--no-gif", "--no-plots",
                 "--no-progress")
    rc, wall = run_logged(cmd, logs / "eval_cuda.log", e["timeout_s"])
    trials = out / "trials.jsonl"
    done = len(trials.read_text().splitlines()) if trials.exists() else 0
    log(f"eval {device()}: rc {rc}, {done} trials in {wall:.0f} s")
    return {"rc": rc, "wall_s": wall, "trials": done, "trials_per_min": 60.0 * done / wall}


def train_frames(data: Path, train_trajectories: list[int]) -> int:
    """Frames in one epoch of the training split."""
    from vitfly.datamodules.schema import open_trajectories

    with open_trajectories(data, check_values=False) as tf:
        return int(tf.lengths[train_trajectories].sum())


def publish(cfg: dict, data: Path, work: Path, pub: Path, fit: dict) -> dict:
    from vitfly.datamodules.provenance import dataset_fingerprint
    from vitfly.zoo.pretrained import save_pretrained

    fingerprint = dataset_fingerprint(data)
    budget = cfg["publish"]["max_mb"] * 1e6 - 2e6  # logs and the manifest
    published = {}
    snapshots = []
    for name in cfg["train"]["runs"]:
        epochs = epoch_checkpoints(work / "runs" / name)
        if epochs:
            snapshots.append(("end", name, epochs[-1], len(epochs)))
    for name in cfg["publish"]["middle_for"]:
        epochs = epoch_checkpoints(work / "runs" / name)
        if len(epochs) >= 2:
            snapshots.append(("middle", name, epochs[len(epochs) // 2 - 1], len(epochs)))
    used = 0.0
    for snap, name, ckpt, n_epochs in snapshots:
        split = json.loads(next((work / "runs" / name).glob("version_*/split.json")).read_text())
        flags = {**cfg["train"]["fit_args"], **cfg["train"]["runs"][name]["args"]}
        recipe = {k.lstrip("-"): v for k, v in flags.items()}
        epochs_in = int(ckpt.stem.removeprefix("epoch")) + 1
        fields = {"preset": "gpu-study", "recipe": recipe, "config": cfg["train"]["runs"][name]["config"],
                  "train_frames": epochs_in * train_frames(data, split["train"]),
                  "train_wall_s": round(fit.get(name, {}).get("wall_s", 0.0), 1), **fingerprint}
        try:
            path = save_pretrained(ckpt, name, fields, pub / snap)
        except Exception as err:  # one broken run must not lose the others
            log(f"publish {snap}/{name}: {err}")
            continue
        size = path.stat().st_size
        if used + size > budget:
            path.unlink()
            log(f"publish {snap}/{name}: left out ({size / 1e6:.1f} MB over the budget)")
            continue
        used += size
        published[f"{snap}/{name}"] = {"checkpoint": ckpt.name, "epochs_done": n_epochs, "mb": size / 1e6}
        log(f"publish {snap}/{name}: {ckpt.name} of {n_epochs} epochs, {size / 1e6:.1f} MB")
    return published


def pack(out: Path, pub: Path, work: Path, logs: Path) -> dict:
    """The published weights and the logs as ``out/study.tar.NNN`` (``scripts/gpu_pack.py``); the manifest."""
    from scripts.gpu_pack import pack as pack_pieces

    for metrics in (work / "runs").glob("*/version_*/metrics.csv"):
        shutil.copy(metrics, logs / f"metrics_{metrics.parent.parent.name}.csv")
    folders = [(folder.name, folder) for folder in (pub / "end", pub / "middle", logs) if folder.exists()]
    return pack_pieces(folders, out, "study", work)


def unpack(src: Path, into: Path) -> None:
    """Here: ``end/``, ``middle/`` (weights directories: ``VITFLY_WEIGHTS_DIR``) and ``logs/`` into ``into``."""
    from scripts.gpu_pack import unpack as unpack_pieces

    manifest = unpack_pieces(src, "study", into, REPORT)
    names = ", ".join(f"{c['name']}/" for c in manifest["contents"]) if manifest else "the pieces"
    print(f"{into}: {names} unpacked")


def add_commands(sub) -> dict:
    """``study`` on ``scripts/gpu.py``'s subparsers; returns name -> handler."""
    p = sub.add_parser("study", help="there: the shipped weights' study (scripts/gpu_study.yaml), packed")
    p.add_argument("--config", default="scripts/gpu_study.yaml")
    p.add_argument("--out", required=True, help="folder for what comes back (study.json, run.log, pieces)")
    p.add_argument("--work", default="/tmp/vitfly-study", help="dataset, runs and checkpoints (stay there)")
    p.add_argument("--skip", nargs="*", default=[], choices=["benchmark", "eval"], help="stages to skip")
    return {"study": study}


def study(args: argparse.Namespace) -> int:
    cfg = yaml.safe_load(Path(args.config).read_text())
    clock = Clock(cfg["deadline_s"])
    out, work = Path(args.out), Path(args.work)
    logs, pub = work / "logs", work / "pub"
    for folder in (out, logs, pub):
        folder.mkdir(parents=True, exist_ok=True)
    data = work / "spheres.h5"
    study = {"config": cfg, "stages": {}}
    import torch

    study["device"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    study["torch"] = torch.__version__
    log(f"{study['device']}, torch {torch.__version__}, deadline {cfg['deadline_s']} s")

    def save() -> None:
        study["elapsed_s"] = round(clock.elapsed(), 1)
        (out / REPORT).write_text(json.dumps(study, indent=2, default=str) + "\n")

    try:
        study["stages"]["collect"] = collect(cfg, data, logs, clock)
        save()
        if "benchmark" not in args.skip:
            study["stages"]["benchmark"] = benchmark(cfg, logs, clock)
            save()
        eval_s = 0.0 if "eval" in args.skip else cfg["eval_cuda"]["timeout_s"] + 5
        study["stages"]["train"] = train(cfg, data, work, logs, clock, eval_s)
        save()
        if "eval" not in args.skip:
            study["stages"]["eval_cuda"] = eval_speed(cfg, work, logs, clock)
            save()
        study["published"] = publish(cfg, data, work, pub, study["stages"]["train"])
    finally:
        save()
        shutil.copy(out / "study.json", logs / "study.json")
        study["pack"] = pack(out, pub, work, logs)
        save()
        log(f"done in {clock.elapsed():.0f} s: {', '.join(p['file'] for p in study['pack']['pieces'])}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """The old command line: ``scripts/gpu_study.py ARGS`` is ``scripts/gpu.py study ARGS``.
    Handed over as a process: ``gpu.py`` imports this module, which so never imports it back."""
    args = sys.argv[1:] if argv is None else argv
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "gpu.py"), "study", *args]).returncode


if __name__ == "__main__":
    sys.exit(main())
