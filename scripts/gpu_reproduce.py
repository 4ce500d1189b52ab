"""Train runs of a ``vitfly reproduce`` preset on one GPU machine inside one time-boxed command, then carry them home.

There (the device machine, 16 cores and one GPU; its 10-minute command limit):

    python3 scripts/gpu_reproduce.py train --preset laptop --out DIR --expect-data-hash HASH \\
        --runs vit_lstm-state resnet18-state convnet-nostate ...

1. the preset's dataset, collected there with many workers (the collector is deterministic: the file is
   byte-identical to one collected anywhere else with the same settings; ``--expect-data-hash`` refuses to
   train on anything else, so the runs belong to the dataset the rest of the preset used);
2. every run as its own process, all at once (small TBPTT batches leave a GPU mostly idle), through the same
   code as ``vitfly reproduce``'s train stage (recipe, preset overrides, done.json), stopped at the deadline;
3. each finished run packed for the trip back (the device tool returns 8 files of 16 MiB): metrics, split,
   cost, done.json and the best checkpoint without optimiser state, its network weights in fp16 (as the
   shipped weights). A run stopped at the deadline is named in DIR/gpu_reproduce.json and not returned.

Here (the machine that goes on with the preset):

    python3 scripts/gpu_reproduce.py unpack --preset laptop DIR

puts the runs under the preset's ``train/`` with done.json naming the local checkpoint (a run that already
has a done.json here is left alone); ``vitfly reproduce --preset laptop`` then skips them as done and goes on.
A returned run has no ``last.ckpt``: a later change of its settings trains it again from the start.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DROPPED_KEYS = ("optimizer_states", "lr_schedulers", "callbacks", "loops")  # resume state, not the network


def log(msg: str) -> None:
    print(f"[gpu-reproduce {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def load_cfg(args: argparse.Namespace):
    from vitfly.workflows.reproduce_config import load_reproduce_config

    return load_reproduce_config(args.config, args.preset, {"out": args.run_dir, "data": args.data})


def parse_label(label: str) -> tuple[str, bool]:
    model, _, kind = label.rpartition("-")
    if kind not in ("state", "nostate") or not model:
        raise SystemExit(f"--runs: {label!r}: expected MODEL-state or MODEL-nostate")
    return model, kind == "state"


def train_one(args: argparse.Namespace) -> int:
    """One run, exactly as ``vitfly reproduce``'s train stage trains it (child process of ``train``)."""
    from vitfly.workflows.pipeline import stage_train
    from vitfly.workflows.reproduce import _add_cost
    from vitfly.workflows.reproduce_config import train_callbacks, train_stage

    cfg = load_cfg(args)
    model, use_state = parse_label(args.train_one)
    stage, callbacks = train_callbacks(train_stage(cfg, model, use_state), cfg, "reproduce config")
    train_dir = cfg.train_dir(model, use_state)
    t0 = time.perf_counter()
    stage_train(stage, cfg.data, train_dir, args.threads, progress=False, callbacks=callbacks)
    _add_cost(train_dir, time.perf_counter() - t0)
    return 0


def slim_checkpoint(src: Path, dst: Path) -> dict:
    """``src`` without optimiser/loop state, its state dict only the network's weights, floating ones in fp16."""
    import torch

    from vitfly.zoo.checkpoint import NET_PREFIX, network_from_checkpoint_dict
    from vitfly.zoo.pretrained import fp16_state_dict

    obj = torch.load(src, map_location="cpu", weights_only=True)
    for key in DROPPED_KEYS:
        obj.pop(key, None)
    net = network_from_checkpoint_dict(obj, str(src))
    obj["state_dict"] = {NET_PREFIX + k: v for k, v in fp16_state_dict(net, str(src)).items()}
    torch.save(obj, dst)
    return {"epoch": int(obj.get("epoch", -1)), "global_step": int(obj.get("global_step", -1))}


def pack(cfg, labels: list[str], out: Path, work: Path) -> list[str]:
    """The finished runs, slimmed, as ``out/runs.tar.NNN`` pieces; returns the labels packed."""
    import torch

    from scripts.gpu_study import write_pieces

    stage_dir = work / "pack"
    shutil.rmtree(stage_dir, ignore_errors=True)
    packed = []
    for label in labels:
        model, use_state = parse_label(label)
        d = cfg.train_dir(model, use_state)
        marker = d / "done.json"
        if not marker.exists():
            continue
        done = json.loads(marker.read_text())
        dst = stage_dir / label
        (dst / "checkpoints").mkdir(parents=True)
        best = slim_checkpoint(Path(done["checkpoint"]), dst / "checkpoints" / "best.ckpt")
        last = torch.load(d / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
        done["checkpoint"] = "checkpoints/best.ckpt"  # made absolute by unpack
        done["trained_on"] = {"device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
                              "weights": "fp16", "best_epoch": best["epoch"] + 1,
                              "epochs": int(last.get("epoch", -1)) + 1, "steps": int(last.get("global_step", -1))}
        (dst / "done.json").write_text(json.dumps(done) + "\n")
        for name in ("metrics.csv", "split.json", "cost.json", "hparams.yaml"):
            if (d / name).exists():
                shutil.copy(d / name, dst / name)
        packed.append(label)
    tar_path = work / "runs.tar"
    with tarfile.open(tar_path, "w") as tar:
        for label in packed:
            tar.add(stage_dir / label, arcname=label)
    write_pieces(tar_path, out)
    return packed


def train(args: argparse.Namespace) -> int:
    from vitfly.datamodules.provenance import dataset_fingerprint
    from vitfly.workflows.pipeline import stage_collect

    start = time.monotonic()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    cfg = load_cfg(args)
    labels = list(args.runs)
    for label in labels:
        parse_label(label)
    report: dict = {"preset": args.preset, "runs": {}}

    t0 = time.monotonic()
    stage_collect(cfg.collect_config, {**cfg.collect, "workers": args.collect_workers}, cfg.data, progress=False)
    report["data"] = {**dataset_fingerprint(cfg.data), "collect_s": round(time.monotonic() - t0, 1)}
    log(f"data {cfg.data}: {report['data']}")
    if args.expect_data_hash and report["data"]["dataset_hash"] != args.expect_data_hash:
        report["error"] = f"dataset_hash {report['data']['dataset_hash']} != expected {args.expect_data_hash}"
        (out / "gpu_reproduce.json").write_text(json.dumps(report, indent=1) + "\n")
        log(report["error"] + ": nothing trained")
        return 1

    procs = {}
    for label in labels:
        cmd = [sys.executable, __file__, "train-one", "--config", args.config, "--preset", args.preset,
               "--threads", str(args.threads), label]
        cmd += ["--run-dir", args.run_dir] if args.run_dir else []
        cmd += ["--data", args.data] if args.data else []
        logfile = open(work / f"{label}.log", "w")
        procs[label] = subprocess.Popen(cmd, stdout=logfile, stderr=subprocess.STDOUT, cwd=ROOT,
                                        start_new_session=True)
    train_deadline = start + args.deadline_s - args.reserve_s
    while any(p.poll() is None for p in procs.values()) and time.monotonic() < train_deadline:
        time.sleep(2)
    for label, p in procs.items():
        if p.poll() is None:
            os.killpg(p.pid, 9)
            p.wait()
            report["runs"][label] = {"rc": None, "note": "stopped at the deadline, not returned"}
        else:
            report["runs"][label] = {"rc": p.returncode}
        log(f"{label}: {report['runs'][label]}; log tail: "
            + " | ".join((work / f"{label}.log").read_text().strip().splitlines()[-2:]))
    packed = pack(cfg, labels, out, work)
    for label in packed:
        report["runs"][label]["packed"] = True
    report["elapsed_s"] = round(time.monotonic() - start, 1)
    (out / "gpu_reproduce.json").write_text(json.dumps(report, indent=1) + "\n")
    log(f"packed {len(packed)}/{len(labels)} runs in {report['elapsed_s']} s")
    return 0 if len(packed) == len(labels) else 1


def unpack(args: argparse.Namespace) -> int:
    cfg = load_cfg(args)
    src = Path(args.dir)
    pieces = sorted(src.glob("runs.tar.[0-9][0-9][0-9]"))
    if not pieces:
        raise SystemExit(f"{src}: no runs.tar.NNN pieces")
    tmp = cfg.out_dir / "train" / ".gpu_unpack"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    tar_path = tmp / "runs.tar"
    with open(tar_path, "wb") as f:
        for piece in pieces:
            f.write(piece.read_bytes())
    with tarfile.open(tar_path) as tar:
        tar.extractall(tmp, filter="data")
    tar_path.unlink()
    for run in sorted(p for p in tmp.iterdir() if p.is_dir()):
        model, use_state = parse_label(run.name)
        dst = cfg.train_dir(model, use_state)
        if (dst / "done.json").exists():
            print(f"{dst}: has a done.json; left alone")
            continue
        if dst.exists():  # an unfinished local attempt: the finished run replaces it
            print(f"{dst}: unfinished here; replaced by the returned run")
            shutil.rmtree(dst)
        shutil.move(str(run), dst)
        done = json.loads((dst / "done.json").read_text())
        done["checkpoint"] = str((dst / done["checkpoint"]).resolve())
        (dst / "done.json").write_text(json.dumps(done) + "\n")
        print(f"{dst}: {done['trained_on']}")
    shutil.rmtree(tmp)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("train", "train-one", "unpack"):
        p = sub.add_parser(name)
        p.add_argument("--config", default="configs/reproduce.yaml")
        p.add_argument("--preset", required=True)
        p.add_argument("--run-dir", help="the preset's run directory (vitfly reproduce --out)")
        p.add_argument("--data", help="the preset's dataset (vitfly reproduce --data)")
    t = sub.choices["train"]
    t.add_argument("--out", required=True, help="what comes back: runs.tar.NNN and gpu_reproduce.json")
    t.add_argument("--work", default="/tmp/vitfly-gpu-reproduce", help="logs and packing")
    t.add_argument("--runs", nargs="+", required=True, help="MODEL-state / MODEL-nostate labels")
    t.add_argument("--expect-data-hash", help="the dataset_hash the collected file must have")
    t.add_argument("--collect-workers", type=int, default=14)
    t.add_argument("--threads", type=int, default=2, help="torch threads per run")
    t.add_argument("--deadline-s", type=float, default=560.0, help="the whole command, from its start")
    t.add_argument("--reserve-s", type=float, default=40.0, help="left after training for packing")
    one = sub.choices["train-one"]
    one.add_argument("--threads", type=int, default=2)
    one.add_argument("train_one", metavar="LABEL")
    sub.choices["unpack"].add_argument("dir", help="the folder holding runs.tar.NNN")
    args = parser.parse_args()
    return {"train": train, "train-one": train_one, "unpack": unpack}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
