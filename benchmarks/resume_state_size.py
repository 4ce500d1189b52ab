"""Bytes of an unfinished run's resume state per network: what ``scripts/gpu_reproduce.py`` brings home from one
GPU slot and carries to the next (the device tool sends the working tree and the carry, 64 MiB together).

    python benchmarks/resume_state_size.py [--models convnet vit_lstm ...] [--data data/reproduce_tiny.h5]

Trains each network for one epoch of the ``tiny`` preset (its data collected if missing), packs the run as an
unfinished one with the Adam moments in fp32 (an exact resume) and in bf16, and prints a Markdown table: the
parameter count, ``last.ckpt`` (fp32 weights, moments, loop and generator state) as it is and as it travels,
squeezed (``scripts/gpu_squeeze.py``), the best checkpoint so far (fp16 weights) and the whole run folder as it
travels. The plain sizes depend only on the network; the squeezed ones on the trained values too (one epoch
here: ``benchmarks/carry_compression.py`` reads states trained longer).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def measure(cfg, model: str, tmp: Path) -> dict:
    from scripts.gpu_reproduce import stage_unfinished
    from scripts.gpu_slots import tree_bytes
    from scripts.gpu_squeeze import plain_bytes, squeezed
    from vitfly.workflows.pipeline import stage_train
    from vitfly.workflows.reproduce_config import train_stage
    from vitfly.zoo import create_model

    stage = dataclasses.replace(train_stage(cfg, model, True), max_epochs=1)
    run = tmp / model
    stage_train(stage, cfg.data, run, 1, progress=False)
    (run / "done.json").unlink()  # packed as a run stopped after its first epoch
    row = {"model": model, "params": sum(p.numel() for p in create_model(model).parameters())}
    for moments in ("fp32", "bf16"):
        dst = tmp / f"{model}-{moments}"
        stage_unfinished(run, dst, {"label": f"{model}-state", "epochs": 1, "slots": []}, moments)
        last, best = (squeezed(dst / "checkpoints" / name) for name in ("last.ckpt", "best.ckpt"))
        row[moments] = {"last": plain_bytes(last), "squeezed": last.stat().st_size, "folder": tree_bytes(dst)}
        row["best"] = plain_bytes(best)
    return row


def main() -> int:
    from scripts.gpu_slots import CARRY_BYTES
    from vitfly.workflows.pipeline import stage_collect
    from vitfly.workflows.reproduce_config import load_reproduce_config

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", nargs="+", default=["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm",
                                                        "resnet18"])
    parser.add_argument("--data", default="data/reproduce_tiny.h5")
    args = parser.parse_args()
    cfg = load_reproduce_config(ROOT / "configs" / "reproduce.yaml", "tiny", {"data": args.data})
    stage_collect(cfg.collect_config, cfg.collect, cfg.data, progress=False)
    mib = 2**20
    print("| network | parameters | last.ckpt, fp32 moments | squeezed: fp32 / bf16 moments | best (fp16) | "
          "folder as it travels, fp32 moments | the same, bf16 moments | per 64 MiB carry (fp32 / bf16) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    tmp = Path(tempfile.mkdtemp(prefix="resume-size-"))
    try:
        for model in args.models:
            r = measure(cfg, model, tmp)
            fp32, bf16 = r["fp32"]["folder"], r["bf16"]["folder"]
            squeezed = " / ".join(f"{r[m]['squeezed'] / r[m]['last']:.3f}" for m in ("fp32", "bf16"))
            print(f"| {model} | {r['params']:,} | {r['fp32']['last'] / mib:.1f} MiB | {squeezed} of the bytes | "
                  f"{r['best'] / mib:.1f} MiB | {fp32 / mib:.1f} MiB | {bf16 / mib:.1f} MiB | "
                  f"{CARRY_BYTES // fp32} / {CARRY_BYTES // bf16} |", flush=True)
    finally:
        shutil.rmtree(tmp)
    return 0


if __name__ == "__main__":
    sys.exit(main())
