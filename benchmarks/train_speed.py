"""Training throughput per model (frames/s), optionally side by side with an older revision in one run.

Two measurements, each run in a fresh subprocess per sample so that both revisions are timed alike:

- ``step`` (default): one optimiser step per TBPTT chunk on a synthetic batch (B trajectories x T steps,
  uint8 depth converted as the datamodule does, paper eq. 1, backward, the module's own Adam), outside
  Lightning, in each of ``--modes``: ``fp32``, ``bf16`` (CPU/CUDA autocast, as Lightning's
  ``bf16-mixed``), ``compiled`` (``compile_encoder``, fp32) and ``compiled-bf16``. Reports the median
  frames/s of ``--iters`` steps after ``--warmup`` steps, and the warm-up time (compilation included).
- ``--fit``: ``vitfly fit --config configs/fit/<model>.yaml`` as shipped by each revision, on ``--data``,
  for ``--fit-batches`` training batches without validation; frames/s over the batches after the first
  ``--fit-skip`` (which carry start-up and compilation), data loading included.

``--baseline-rev REV`` exports REV (``git archive``) to a temporary folder and runs the same
measurements against it (PYTHONPATH pointed there), alternating baseline and new sample by sample,
``--repeats`` times; the tables give medians, the spread (min-max over repeats) and new / baseline.
On a shared machine every number moves with the other load: compare only numbers from one run.

    .venv/bin/python benchmarks/train_speed.py [--models convnet vit_lstm] [--modes fp32 bf16 compiled]
    .venv/bin/python benchmarks/train_speed.py --fit --data data/speed40.h5 --models vit_lstm --baseline-rev 08f93e2
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BENCH_DIR = Path(__file__).resolve().parent
MODES = ("fp32", "bf16", "compiled", "compiled-bf16")
ALL_MODELS = ("convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18")


# -- measured in a subprocess (imports whichever vitfly PYTHONPATH points at) -----------------------


def synthetic_batch(batch: int, steps: int, device):
    import torch

    g = torch.Generator().manual_seed(0)
    data = {
        "depth": torch.randint(0, 256, (batch, steps, 1, 60, 90), generator=g, dtype=torch.uint8),
        "desired_speed": torch.full((batch, steps, 1), 5.0),
        "quat": torch.nn.functional.normalize(torch.randn(batch, steps, 4, generator=g), dim=-1),
        "velocity_cmd": torch.randn(batch, steps, 3, generator=g) + torch.tensor([5.0, 0.0, 0.0]),
        "mask": torch.ones(batch, steps, dtype=torch.bool),
    }
    return {k: v.to(device) for k, v in data.items()}


def measure_steps(
    model: str, mode: str, batch: int, steps: int, iters: int, warmup: int, device: str, threads: int | None = None
) -> dict:
    """frames/s of ``iters`` optimiser steps (one batch of one chunk each) after ``warmup`` steps."""
    import torch

    if threads:
        torch.set_num_threads(threads)
    from vitfly.zoo.policy import create_policy

    torch.manual_seed(0)
    kwargs = {"compile": True} if mode.startswith("compiled") else {}
    module = create_policy(model, tbptt_steps=steps, **kwargs).to(device)
    module.train()
    optimizer = module.configure_optimizers()
    data = synthetic_batch(batch, steps, device)
    dev = torch.device(device)
    autocast = torch.autocast(dev.type, dtype=torch.bfloat16) if mode.endswith("bf16") else contextlib.nullcontext()

    def one_batch() -> None:
        chunk_batch = dict(data)
        chunk_batch["depth"] = chunk_batch["depth"].to(torch.float32).mul_(1.0 / 255.0)
        hidden = None
        for chunk in module.tbptt_chunks(chunk_batch):
            with autocast:
                loss, hidden = module.chunk_loss(chunk, hidden)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            hidden = None if hidden is None else tuple(h.detach() for h in hidden)
        if dev.type == "cuda":
            torch.cuda.synchronize()

    start = time.perf_counter()
    for _ in range(warmup):
        one_batch()
    warmup_s = time.perf_counter() - start
    times = []
    for _ in range(iters):
        start = time.perf_counter()
        one_batch()
        times.append(time.perf_counter() - start)
    return {"fps": batch * steps / statistics.median(times), "warmup_s": warmup_s}


def measure_fit(model: str, root: str, data: str, batches: int, skip: int) -> dict:
    """frames/s of ``vitfly fit`` with ``root``'s configs/fit/<model>.yaml over batches skip+1..batches."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "timer.json"
        cmd = [
            sys.executable, "-m", "vitfly.cli", "fit", "--config", f"{root}/configs/fit/{model}.yaml",
            "--data.data_path", data, "--trainer.max_epochs", "1", "--trainer.limit_train_batches", str(batches),
            "--trainer.limit_val_batches", "0", "--trainer.default_root_dir", tmp,
            "--trainer.enable_progress_bar", "false", "--trainer.callbacks+=fit_timer.FitTimer",
        ]  # fmt: skip
        env = {**os.environ, "VITFLY_FIT_TIMER_OUT": str(out)}
        proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
        if proc.returncode != 0 or not out.exists():
            raise RuntimeError(f"vitfly fit failed in {root} (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
        rows = json.loads(out.read_text())
    if len(rows) <= skip:
        raise RuntimeError(f"only {len(rows)} training batches ran; need more than --fit-skip {skip}")
    t0 = rows[skip - 1][0] if skip else 0.0
    frames = sum(n for _, n in rows[skip:])
    return {"fps": frames / (rows[-1][0] - t0), "warmup_s": t0, "frames": frames}


def worker_main(argv: list[str]) -> None:
    spec = json.loads(argv[0])
    kind = spec.pop("kind")
    result = measure_steps(**spec) if kind == "step" else measure_fit(**spec)
    print("RESULT " + json.dumps(result), flush=True)


# -- the driver ---------------------------------------------------------------------------------------


def export_revision(rev: str, dest: Path) -> Path:
    """The tree of git revision ``rev`` unpacked into ``dest`` (no worktree, nothing added to .git)."""
    archive = dest / "tree.tar"
    subprocess.run(["git", "archive", "--format=tar", "-o", str(archive), rev], cwd=ROOT, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(dest / "tree", filter="data")
    return dest / "tree"


def run_sample(code_root: Path, spec: dict) -> dict:
    env = {**os.environ, "PYTHONPATH": f"{code_root}{os.pathsep}{BENCH_DIR}"}
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
        cwd=code_root, env=env, capture_output=True, text=True,
    )  # fmt: skip
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    raise RuntimeError(f"measurement {spec} in {code_root} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")


def spread(values: list[float]) -> str:
    return f"{min(values):,.0f}-{max(values):,.0f}" if len(values) > 1 else "-"


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--worker":
        worker_main(sys.argv[2:])
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(ALL_MODELS))
    parser.add_argument("--modes", nargs="+", choices=MODES, default=["fp32", "bf16", "compiled"])
    parser.add_argument("--batch", type=int, default=4, help="trajectories per batch (step mode)")
    parser.add_argument("--steps", type=int, default=64, help="time steps per TBPTT chunk (step mode)")
    parser.add_argument("--iters", type=int, default=3, help="timed optimiser steps per sample (median)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed steps first (compilation happens here)")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: cuda when present)")
    parser.add_argument("--threads", type=int, default=None, help="CPU intra-op threads in step mode (default: all)")
    parser.add_argument("--fit", action="store_true", help="time `vitfly fit` with the shipped configs instead")
    parser.add_argument("--data", help="dataset for --fit")
    parser.add_argument("--fit-batches", type=int, default=4, help="training batches per --fit sample")
    parser.add_argument("--fit-skip", type=int, default=1, help="first batches left out of the --fit rate")
    parser.add_argument("--baseline-rev", help="git revision to measure side by side (e.g. 08f93e2)")
    parser.add_argument("--repeats", type=int, default=1, help="samples per model/mode (alternating revisions)")
    parser.add_argument("--json", help="also write every sample to this JSON file")
    args = parser.parse_args()
    if args.fit and not args.data:
        parser.error("--fit needs --data (a vitfly HDF5 dataset)")
    import torch

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    data = str(Path(args.data).resolve()) if args.data else None
    with tempfile.TemporaryDirectory(prefix="vitfly-baseline-") as tmp:
        sides = {"new": ROOT}
        if args.baseline_rev:
            sides = {"baseline": export_revision(args.baseline_rev, Path(tmp)), "new": ROOT}
        modes = ["fit"] if args.fit else args.modes
        samples: list[dict] = []
        for r in range(args.repeats):
            for model in args.models:
                for mode in modes:
                    order = list(sides) if r % 2 == 0 else list(reversed(sides))
                    for side in order:
                        if side == "baseline" and mode != "fp32" and mode != "fit":
                            continue  # today's fp32 is the reference for every new mode
                        if args.fit:
                            spec = {"kind": "fit", "model": model, "root": str(sides[side]), "data": data,
                                    "batches": args.fit_batches, "skip": args.fit_skip}  # fmt: skip
                        else:
                            spec = {"kind": "step", "model": model, "mode": mode, "batch": args.batch,
                                    "steps": args.steps, "iters": args.iters, "warmup": args.warmup,
                                    "device": device, "threads": args.threads}  # fmt: skip
                        result = run_sample(sides[side], spec)
                        samples.append({"repeat": r, "model": model, "mode": mode, "side": side, **result})
                        print(f"  [{r}] {model} {mode} {side}: {result['fps']:,.1f} frames/s "
                              f"(warm-up {result['warmup_s']:.1f} s)", file=sys.stderr, flush=True)  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(samples, indent=1))
    what = "vitfly fit, shipped configs" if args.fit else f"{args.batch} x {args.steps} frames per optimiser step"
    threads = args.threads or torch.get_num_threads()
    print(f"\n{device}, {threads} threads, {what}; medians of {args.repeats} samples (spread)")
    header = "| model | mode | frames/s | spread | warm-up s |"
    if "baseline" in sides:
        header += f" baseline {args.baseline_rev} frames/s | spread | new / baseline | paired ratios |"
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for model in args.models:
        base = [s["fps"] for s in samples if s["model"] == model and s["side"] == "baseline"]
        for mode in modes:
            new = [s["fps"] for s in samples if (s["model"], s["mode"], s["side"]) == (model, mode, "new")]
            warm = [s["warmup_s"] for s in samples if (s["model"], s["mode"], s["side"]) == (model, mode, "new")]
            med = statistics.median
            row = f"| {model} | {mode} | {med(new):,.0f} | {spread(new)} | {med(warm):.1f} |"
            if base:
                ratio = statistics.median(new) / statistics.median(base)
                # each repeat's new sample against the baseline sample taken next to it
                by_repeat = {s["repeat"]: s["fps"] for s in samples if s["model"] == model and s["side"] == "baseline"}
                paired = [
                    s["fps"] / by_repeat[s["repeat"]]
                    for s in samples
                    if (s["model"], s["mode"], s["side"]) == (model, mode, "new") and s["repeat"] in by_repeat
                ]
                pairs = ", ".join(f"{p:.2f}x" for p in paired)
                row += f" {statistics.median(base):,.0f} | {spread(base)} | {ratio:.2f}x | {pairs} |"
            print(row)


if __name__ == "__main__":
    main()
