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

- ``--arm paper|vitfly``: each model as one arm of the paper-budget study trains it, with the batch, TBPTT
  chunks, precision, static shapes (``time_bucket_steps``) and compile mode of its preset in
  configs/reproduce.yaml (``paper``: one trajectory per optimiser step, padded to a 64-step bucket, CUDA
  graphs; ``paper_vitfly``: 64 trajectories in TBPTT chunks, compiled), on a synthetic batch of
  ``--steps`` real steps per trajectory (default 418, the mean flight of the laptop preset's data). In
  ``--modes``: ``recipe`` (the preset as it is), ``eager`` (no compilation), ``unpadded`` (no compilation,
  no padding, no static shapes: the default path), ``fp32`` / ``bf16`` (the recipe in that precision),
  ``contiguous`` (the recipe with its weights in the default memory layout, where it sets ``channels_last``),
  ``loop`` (the run as the preset trains it, on ``--data``: its TrainStage through ``vitfly.training.train_policy``,
  Lightning, the real flights, the learning-rate schedule and the logging, for ``--fit-batches`` training
  batches after ``--fit-skip`` ones; the step modes time the step alone, so ``recipe`` against ``loop`` in one
  run says what the loop around the step costs; the loop also validates ``--val-batches`` batches, and the
  progress line and ``--json`` give their seconds). Frames/s count real frames (not padding).

Every step-mode row also gives the model's arithmetic rate: FLOPs per frame of one optimiser step (forward
and backward) from ``torch.utils.flop_counter.FlopCounterMode``, counted once per model on the CPU in fp32 on
one 32-frame trajectory (every counted operation is per frame or per LSTM step, so the count per frame holds
for any batch: exactly for the encoders, within 1 % for the LSTMs), times the real frames/s: TFLOP/s, and its
share of the device's dense peak for the precision (``PEAK_TFLOPS``: NVIDIA's datasheets; bf16 runs against
the BF16 tensor-core peak, fp32 runs against the TF32 tensor-core peak, since cuDNN runs fp32 convolutions
in TF32 by default). On a CPU the share is n/a unless ``--peak-tflops`` gives the peak.

``--baseline-rev REV`` exports REV (``git archive``) to a temporary folder and runs the same
measurements against it (PYTHONPATH pointed there), alternating baseline and new sample by sample,
``--repeats`` times; the tables give medians, the spread (min-max over repeats) and new / baseline.
On a shared machine every number moves with the other load: compare only numbers from one run.

    .venv/bin/python benchmarks/train_speed.py [--models convnet vit_lstm] [--modes fp32 bf16 compiled]
    .venv/bin/python benchmarks/train_speed.py --fit --data data/speed40.h5 --models vit_lstm --baseline-rev 08f93e2
    .venv/bin/python benchmarks/train_speed.py --arm paper --modes recipe eager unpadded --iters 20 --warmup 5
    .venv/bin/python benchmarks/train_speed.py --arm vitfly --models convnet vit_lstm --batch 2 --steps 64  # CPU-sized
    python3 benchmarks/train_speed.py --arm paper --models vit_lstm --modes recipe loop --data data/reproduce_paper.h5 \
        --fit-batches 60 --fit-skip 20 --val-batches 4     # the step against the run that trains it
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
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BENCH_DIR = Path(__file__).resolve().parent
MODES = ("fp32", "bf16", "compiled", "compiled-bf16")
ALL_MODELS = ("convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18")
ARMS = {"paper": "paper", "vitfly": "paper_vitfly"}  # --arm -> its preset in configs/reproduce.yaml
ARM_MODES = ("recipe", "eager", "unpadded", "fp32", "bf16", "loop", "contiguous")
MEAN_FLIGHT_STEPS = 418  # the laptop preset's 200 expert flights: 83,681 frames
FLOP_COUNT_STEPS = 32  # frames of the trajectory the FLOPs are counted on
# NVIDIA datasheet figures, TFLOP/s: FP32 (CUDA cores, dense), TF32 and BF16 tensor cores as printed "with
# sparsity"; dense is half of those. Keys are matched against torch.cuda.get_device_name(), most specific first.
DATASHEET_TFLOPS = {
    "H100 PCIe": {"fp32": 51.0, "tf32_sparse": 756.0, "bf16_sparse": 1513.0},
    "H100 NVL": {"fp32": 60.0, "tf32_sparse": 835.0, "bf16_sparse": 1671.0},
    "H100": {"fp32": 67.0, "tf32_sparse": 989.0, "bf16_sparse": 1979.0},  # SXM5 ("NVIDIA H100 80GB HBM3")
    "H200 NVL": {"fp32": 60.0, "tf32_sparse": 835.0, "bf16_sparse": 1671.0},
    "H200": {"fp32": 67.0, "tf32_sparse": 989.0, "bf16_sparse": 1979.0},  # SXM
}


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

    one_batch = train_batch_fn(module, optimizer, data, autocast, dev)
    median_s, warmup_s = time_batches(one_batch, warmup, iters)
    return {"fps": batch * steps / median_s, "warmup_s": warmup_s}


def train_batch_fn(module, optimizer, data: dict, autocast, dev, clip: float | None = None):
    """One batch as the module trains it: uint8 depth to [0, 1], one optimiser step per TBPTT chunk (gradient
    norm clipped to ``clip`` when set), the recurrent state carried across chunks, detached."""
    import torch

    from vitfly.zoo.policy import detach_hidden

    def one_batch() -> None:
        chunk_batch = dict(data)
        chunk_batch["depth"] = chunk_batch["depth"].to(torch.float32).mul_(1.0 / 255.0)
        hidden = None
        for chunk in module.tbptt_chunks(chunk_batch):
            with autocast:
                loss, hidden = module.chunk_loss(chunk, hidden)
            optimizer.zero_grad()
            loss.backward()
            if clip:
                torch.nn.utils.clip_grad_norm_(module.parameters(), clip)
            optimizer.step()
            hidden = detach_hidden(hidden)
        if dev.type == "cuda":
            torch.cuda.synchronize()

    return one_batch


def time_batches(one_batch, warmup: int, iters: int) -> tuple[float, float]:
    """(median seconds per batch over ``iters`` timed calls, seconds of the ``warmup`` calls before them)."""
    start = time.perf_counter()
    for _ in range(warmup):
        one_batch()
    warmup_s = time.perf_counter() - start
    times = []
    for _ in range(iters):
        start = time.perf_counter()
        one_batch()
        times.append(time.perf_counter() - start)
    return statistics.median(times), warmup_s


def measure_arm(
    model: str, policy_kwargs: dict, batch: int, steps: int, bucket: int | None, precision: str, iters: int,
    warmup: int, device: str, threads: int | None = None, profile: bool = False,
) -> dict:
    """frames/s (real frames) of ``iters`` batches after ``warmup``, each trained as the arm's recipe trains it:
    one optimiser step per TBPTT chunk (one per batch when ``tbptt_steps`` is None), gradient clipping as set,
    the batch padded to the ``bucket`` as the datamodule pads it. ``profile``: also the operators' table of 3
    more batches (``torch.profiler``, the device's time first), where a step's time goes."""
    import torch

    clear_compile_counts()
    one_batch, padded = arm_batch_fn(model, policy_kwargs, batch, steps, bucket, precision, device, threads)
    median_s, warmup_s = time_batches(one_batch, warmup, iters)
    table = profile_table(one_batch, torch.device(device)) if profile else None
    return {"fps": batch * steps / median_s, "warmup_s": warmup_s, "padded": padded,
            **({"profile": table} if table else {}), **compile_counts()}


def arm_batch_fn(model: str, policy_kwargs: dict, batch: int, steps: int, bucket: int | None, precision: str,
                 device: str, threads: int | None = None):
    """(one training batch as the arm trains it, as a call; the padded batch's shape): ``measure_arm``'s set-up,
    also run by benchmarks/card_sharing.py's processes."""
    import torch

    if threads:
        torch.set_num_threads(threads)
    from vitfly.zoo.policy import create_policy

    torch.manual_seed(0)
    module = create_policy(model, **policy_kwargs).to(device)
    if policy_kwargs.get("channels_last"):  # as PolicyModule.setup does in a Lightning run
        from vitfly.zoo.policy import wants_channels_last

        if wants_channels_last(policy_kwargs["channels_last"], device):
            module.net.to(memory_format=torch.channels_last)
    module.train()
    optimizer = module.configure_optimizers()
    data = synthetic_batch(batch, steps, device)
    if bucket:
        from vitfly.datamodules.dataset import pad_to_bucket

        data = pad_to_bucket(data, bucket, batch)
    dev = torch.device(device)
    autocast = torch.autocast(dev.type, dtype=torch.bfloat16) if precision == "bf16" else contextlib.nullcontext()
    clip = policy_kwargs.get("gradient_clip_val")
    return train_batch_fn(module, optimizer, data, autocast, dev, clip), list(data["mask"].shape)


def clear_compile_counts() -> None:
    """Zero dynamo's process-wide counters, so that a measurement counts only its own graphs (a test process
    has compiled others before it)."""
    from torch._dynamo.utils import counters

    counters.clear()


def compile_counts() -> dict:
    """Graphs compiled since ``clear_compile_counts``, and how often inductor fell back from CUDA graphs
    (its reasons are on stderr)."""
    from torch._dynamo.utils import counters

    return {"graphs": int(counters["stats"]["unique_graphs"]),
            "cudagraph_skips": int(counters["inductor"]["cudagraph_skips"])}


def measure_loop(model: str, arm: str, data: str, batches: int, skip: int, val_batches: int, device: str) -> dict:
    """frames/s (real frames) of ``arm``'s run of ``model`` as it trains: the preset's TrainStage through
    ``train_policy`` for one epoch cut to ``batches`` training batches, over those after the first ``skip``
    (start-up, compilation and CUDA-graph recording); with ``val_batches`` validation batches, timed by the
    run's own ``time/val_s``."""
    import csv

    from fit_timer import FitTimer

    from vitfly.training import train_policy
    from vitfly.workflows.reproduce_config import load_reproduce_config, split_callbacks, train_stage

    stage, _ = split_callbacks(train_stage(load_reproduce_config(ROOT / "configs" / "reproduce.yaml", ARMS[arm]),
                                           model, True))
    trainer_kwargs = {**stage.trainer_kwargs, "accelerator": "gpu" if device.startswith("cuda") else "cpu",
                      "devices": 1, "limit_train_batches": batches, "limit_val_batches": val_batches,
                      "num_sanity_val_steps": 0, "max_time": None,
                      "check_val_every_n_epoch": 1}  # its one epoch validates, whatever the preset's rate: timed here
    timer = FitTimer()
    clear_compile_counts()
    with tempfile.TemporaryDirectory() as out:
        train_policy(data, model, out, max_epochs=1, batch_size=stage.batch_size, val_fraction=stage.val_fraction,
                     seed=stage.seed, policy_kwargs=stage.policy_kwargs, data_kwargs=stage.data_kwargs,
                     trainer_kwargs=trainer_kwargs, progress_bar=False, callbacks=[timer], select="last")
        with open(Path(out) / "metrics.csv") as f:
            val_s = next(float(r["time/val_s"]) for r in csv.DictReader(f) if r.get("time/val_s"))
    rate = batch_rate(timer.batches, skip)
    return {"fps": rate["fps"], "warmup_s": rate["warmup_s"], "padded": [stage.batch_size, "flights"],
            "val_s": val_s, **compile_counts()}


def profile_table(one_batch, dev, batches: int = 3, rows: int = 30) -> str:
    """``torch.profiler``'s operator table over ``batches`` calls of ``one_batch``, sorted by device time (CPU
    time off CUDA): the launch-bound share shows as CPU time far above the kernels' time."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(batches):
            one_batch()
    sort = "cuda_time_total" if dev.type == "cuda" else "cpu_time_total"
    return prof.key_averages().table(sort_by=sort, row_limit=rows)


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
    return batch_rate(rows, skip)


def batch_rate(rows: list[list[float]], skip: int) -> dict:
    """frames/s over FitTimer's rows ([seconds at batch end, real frames]) after the first ``skip`` batches,
    the seconds before them (start-up, compilation) and the frames counted."""
    if len(rows) <= skip:
        raise RuntimeError(f"only {len(rows)} training batches ran; need more than --fit-skip {skip}")
    t0 = rows[skip - 1][0] if skip else 0.0
    frames = sum(n for _, n in rows[skip:])
    return {"fps": frames / (rows[-1][0] - t0), "warmup_s": t0, "frames": frames}


def worker_main(argv: list[str]) -> None:
    spec = json.loads(argv[0])
    try:  # the allocator as vitfly's training sets it (VITFLY_MALLOC=default: as glibc comes)
        from vitfly.host_memory import keep_freed_memory
    except ImportError:  # a revision from before it (--baseline-rev) trains as it did
        pass
    else:
        keep_freed_memory()
    kind = spec.pop("kind")
    measure = {"step": measure_steps, "arm": measure_arm, "fit": measure_fit, "loop": measure_loop}[kind]
    result = measure(**spec)
    print("RESULT " + json.dumps(result), flush=True)


# -- the driver ---------------------------------------------------------------------------------------


def export_revision(rev: str, dest: Path) -> Path:
    """The tree of git revision ``rev`` unpacked into ``dest`` (no worktree, nothing added to .git)."""
    archive = dest / "tree.tar"
    subprocess.run(["git", "archive", "--format=tar", "-o", str(archive), rev], cwd=ROOT, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(dest / "tree", filter="data")
    return dest / "tree"


def write_json(path: str, device_name: str, samples: list[dict], peaks: dict | None, settings: dict,
               complete: bool) -> None:
    """Every sample so far (``complete``: the run ended, peaks and FLOPs added), replaced atomically."""
    tmp = Path(path).with_suffix(".partial")
    tmp.write_text(json.dumps({"device": device_name, "complete": complete, "samples": samples, "peaks": peaks,
                               "settings": {f"{m} {mode}": v for (m, mode), v in settings.items()}}, indent=1))
    os.replace(tmp, path)


def run_sample(code_root: Path, spec: dict) -> dict:
    env = {**os.environ, "PYTHONPATH": f"{code_root}{os.pathsep}{BENCH_DIR}"}
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
        cwd=code_root, env=env, capture_output=True, text=True,
    )  # fmt: skip
    for line in dict.fromkeys(proc.stderr.splitlines()):  # inductor says why it ran without CUDA graphs
        if "skipping cudagraphs" in line:
            print(f"  {spec['model']}: {line.strip()}", file=sys.stderr)
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    raise RuntimeError(f"measurement {spec} in {code_root} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")


def arm_settings(arm: str, model: str, mode: str) -> dict:
    """The batch, PolicyModule arguments, bucket and precision with which ``arm`` trains ``model``: its preset's
    recipe and overrides (``vitfly.workflows.reproduce_config.train_stage``), changed as ``mode`` says."""
    from vitfly.workflows.reproduce_config import load_reproduce_config, train_stage

    cwd = os.getcwd()
    os.chdir(ROOT)  # the presets name their recipes relative to the repository
    try:
        stage = train_stage(load_reproduce_config(ROOT / "configs" / "reproduce.yaml", ARMS[arm]), model, True)
    finally:
        os.chdir(cwd)
    kept = ("tbptt_steps", "avoid_weight", "gradient_clip_val", "static_shapes", "compile")
    policy = {k: stage.policy_kwargs[k] for k in kept if k in stage.policy_kwargs}
    if stage.policy_kwargs.get("channels_last"):  # only where set: a --baseline-rev before it knows no such argument
        policy["channels_last"] = stage.policy_kwargs["channels_last"]
    bucket = stage.data_kwargs.get("time_bucket_steps")
    precision = "bf16" if "bf16" in str(stage.trainer_kwargs.get("precision", "")) else "fp32"
    if mode in ("eager", "unpadded"):
        policy["compile"] = False
    if mode == "unpadded":
        policy["static_shapes"], bucket = False, None
    if mode in ("fp32", "bf16"):
        precision = mode
    if mode == "contiguous":  # the recipe with its weights in the default layout
        policy.pop("channels_last", None)
    return {"batch": stage.batch_size, "policy_kwargs": policy, "bucket": bucket, "precision": precision}


def flops_per_frame(model: str) -> float:
    """FLOPs of one optimiser step's forward and backward per frame (see the module docstring), fp32, CPU."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from vitfly.zoo.policy import create_policy

    module = create_policy(model, tbptt_steps=None, cpu_threads=None)
    module.train()
    batch = synthetic_batch(1, FLOP_COUNT_STEPS, "cpu")
    batch["depth"] = batch["depth"].to(torch.float32) / 255.0
    (chunk,) = list(module.tbptt_chunks(batch))
    # oneDNN's fused LSTM is invisible to the counter; the plain implementation is counted product by product
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "TF32 on top of oneDNN is for Intel GPUs", from toggling the flags
        with torch.backends.mkldnn.flags(enabled=False), FlopCounterMode(display=False) as counter:
            loss, _ = module.chunk_loss(chunk)
            loss.backward()
    return counter.get_total_flops() / FLOP_COUNT_STEPS


def peak_tflops(device_name: str, precision: str) -> tuple[float, str] | None:
    """(dense peak TFLOP/s, what it is) of a known GPU for ``precision`` (bf16 or fp32); None if unknown."""
    for key, sheet in DATASHEET_TFLOPS.items():
        if key in device_name:
            if precision == "bf16":
                return sheet["bf16_sparse"] / 2, f"{key} dense BF16 tensor cores"
            return sheet["tf32_sparse"] / 2, f"{key} dense TF32 tensor cores"
    return None


def spread(values: list[float]) -> str:
    return f"{min(values):,.0f}-{max(values):,.0f}" if len(values) > 1 else "-"


def arm_models(arm: str) -> list[str]:
    from vitfly.workflows.reproduce_config import load_reproduce_config

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        return list(load_reproduce_config(ROOT / "configs" / "reproduce.yaml", ARMS[arm]).train.models)
    finally:
        os.chdir(cwd)


def rate_cells(fps: float, flops: float, peak: tuple[float, str] | None) -> str:
    """``| GFLOP/frame | TFLOP/s | share of peak |`` for ``fps`` real frames/s of ``flops`` FLOPs each."""
    tflops = fps * flops / 1e12
    share = f"{100 * tflops / peak[0]:.2f} %" if peak else "n/a"
    return f" {flops / 1e9:.4g} | {tflops:.4g} | {share} |"


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--worker":
        worker_main(sys.argv[2:])
        return
    sys.path.insert(0, str(ROOT))  # the driver reads this revision's presets and counts FLOPs with its networks
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=None, help="default: every model (with --arm: the arm's)")
    parser.add_argument("--modes", nargs="+", default=None,
                        help=f"step mode: {', '.join(MODES)} (default: fp32 bf16 compiled); with --arm: "
                             f"{', '.join(ARM_MODES)} (default: recipe)")
    parser.add_argument("--arm", choices=sorted(ARMS), help="train each model as this arm of the paper-budget "
                        "study does (configs/reproduce.yaml presets paper / paper_vitfly)")
    parser.add_argument("--batch", type=int, default=None,
                        help="trajectories per batch (step mode: 4; --arm: the arm's, 1 or 64)")
    parser.add_argument("--steps", type=int, default=None, help="step mode: time steps per TBPTT chunk (64); "
                        f"--arm: real time steps per trajectory ({MEAN_FLIGHT_STEPS}, chunked as the arm does)")
    parser.add_argument("--iters", type=int, default=3, help="timed optimiser steps per sample (median)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed steps first (compilation happens here)")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: cuda when present)")
    parser.add_argument("--threads", type=int, default=None, help="CPU intra-op threads in step mode (default: all)")
    parser.add_argument("--fit", action="store_true", help="time `vitfly fit` with the shipped configs instead")
    parser.add_argument("--data", help="dataset for --fit")
    parser.add_argument("--fit-batches", type=int, default=4, help="training batches per --fit sample")
    parser.add_argument("--fit-skip", type=int, default=1, help="first batches left out of the --fit rate")
    parser.add_argument("--val-batches", type=int, default=0, help="--arm's loop mode: validation batches timed")
    parser.add_argument("--baseline-rev", help="git revision to measure side by side (e.g. 08f93e2)")
    parser.add_argument("--repeats", type=int, default=1, help="samples per model/mode (alternating revisions)")
    parser.add_argument("--peak-tflops", type=float, default=None,
                        help="the device's peak TFLOP/s for the share column (default: NVIDIA's datasheet for a "
                             "known GPU, n/a otherwise)")
    parser.add_argument("--json", help="also write every sample to this JSON file")
    parser.add_argument("--profile", help="--arm: also append each sample's torch.profiler table to this file")
    args = parser.parse_args()
    if (args.fit or "loop" in (args.modes or [])) and not args.data:
        parser.error("--fit and the loop mode need --data (a vitfly HDF5 dataset)")
    if args.arm and (args.fit or args.baseline_rev):
        parser.error("--arm times optimiser steps of this revision; it takes neither --fit nor --baseline-rev")
    choices = ARM_MODES if args.arm else MODES
    modes = args.modes or (["recipe"] if args.arm else ["fp32", "bf16", "compiled"])
    bad = [m for m in modes if m not in choices]
    if bad and not args.fit:
        parser.error(f"--modes: {bad[0]!r} is not one of {', '.join(choices)}")
    models = args.models or (arm_models(args.arm) if args.arm else list(ALL_MODELS))
    import torch

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    device_name = torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "cpu"
    data = str(Path(args.data).resolve()) if args.data else None
    settings = {(m, mode): arm_settings(args.arm, m, mode) for m in models for mode in modes} if args.arm else {}
    with tempfile.TemporaryDirectory(prefix="vitfly-baseline-") as tmp:
        sides = {"new": ROOT}
        if args.baseline_rev:
            sides = {"baseline": export_revision(args.baseline_rev, Path(tmp)), "new": ROOT}
        modes = ["fit"] if args.fit else modes
        samples: list[dict] = []
        for r in range(args.repeats):
            for model in models:
                for mode in modes:
                    order = list(sides) if r % 2 == 0 else list(reversed(sides))
                    for side in order:
                        if side == "baseline" and mode != "fp32" and mode != "fit":
                            continue  # today's fp32 is the reference for every new mode
                        if args.fit:
                            spec = {"kind": "fit", "model": model, "root": str(sides[side]), "data": data,
                                    "batches": args.fit_batches, "skip": args.fit_skip}  # fmt: skip
                        elif mode == "loop":
                            spec = {"kind": "loop", "model": model, "arm": args.arm, "data": data,
                                    "batches": args.fit_batches, "skip": args.fit_skip,
                                    "val_batches": args.val_batches, "device": device}  # fmt: skip
                        elif args.arm:
                            arm = settings[(model, mode)]
                            spec = {"kind": "arm", "model": model, "policy_kwargs": arm["policy_kwargs"],
                                    "batch": args.batch or arm["batch"], "steps": args.steps or MEAN_FLIGHT_STEPS,
                                    "bucket": arm["bucket"], "precision": arm["precision"], "iters": args.iters,
                                    "warmup": args.warmup, "device": device, "threads": args.threads,
                                    "profile": bool(args.profile)}  # fmt: skip
                        else:
                            spec = {"kind": "step", "model": model, "mode": mode, "batch": args.batch or 4,
                                    "steps": args.steps or 64, "iters": args.iters, "warmup": args.warmup,
                                    "device": device, "threads": args.threads}  # fmt: skip
                        result = run_sample(sides[side], spec)
                        if "profile" in result:  # one file for every sample: the device tool returns 8 files
                            with open(args.profile, "a") as fh:
                                fh.write(f"== {model} {mode} ({device_name})\n{result.pop('profile')}\n\n")
                        samples.append({"repeat": r, "model": model, "mode": mode, "side": side, **result})
                        graphs = (f", {result['graphs']} graphs, {result['cudagraph_skips']} CUDA-graph skips"
                                  if "graphs" in result else "")
                        graphs += f", validation {result['val_s']:.2f} s" if "val_s" in result else ""
                        print(f"  [{r}] {model} {mode} {side}: {result['fps']:,.1f} frames/s "
                              f"(warm-up {result['warmup_s']:.1f} s{graphs})", file=sys.stderr, flush=True)  # fmt: skip
                        if args.json:  # what finished survives a timeout
                            write_json(args.json, device_name, samples, None, settings, complete=False)
    flops = {} if args.fit else {m: flops_per_frame(m) for m in models}
    precisions = {(m, mode): (settings[(m, mode)]["precision"] if args.arm else
                              ("bf16" if mode.endswith("bf16") else "fp32")) for m in models for mode in modes}
    peaks = {p: ((args.peak_tflops, "--peak-tflops") if args.peak_tflops else peak_tflops(device_name, p))
             for p in ("fp32", "bf16")}
    for sample in samples:
        if sample["model"] in flops:
            sample["flops_per_frame"] = flops[sample["model"]]
            sample["precision"] = precisions[(sample["model"], sample["mode"])]
    if args.json:
        write_json(args.json, device_name, samples, peaks, settings, complete=True)
    threads = args.threads or torch.get_num_threads()
    if args.fit:
        what = "vitfly fit, shipped configs"
    elif args.arm:
        what = (f"the {args.arm} arm (preset {ARMS[args.arm]}), {args.steps or MEAN_FLIGHT_STEPS} real steps per "
                "trajectory; frames/s count real frames")
    else:
        what = f"{args.batch or 4} x {args.steps or 64} frames per optimiser step"
    print(f"\n{device_name}, {threads} threads, {what}; medians of {args.repeats} samples (spread)")
    header = "| model | mode | frames/s | spread | warm-up s |"
    if args.arm:
        header = ("| model | arm | mode | precision | batch x steps (padded) | compiled graphs | frames/s | spread | "
                  "warm-up s |")
    if not args.fit:
        header += " GFLOP/frame | TFLOP/s | share of peak |"
    if "baseline" in sides:
        header += f" baseline {args.baseline_rev} frames/s | spread | new / baseline | paired ratios |"
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for model in models:
        base = [s["fps"] for s in samples if s["model"] == model and s["side"] == "baseline"]
        for mode in modes:
            new = [s["fps"] for s in samples if (s["model"], s["mode"], s["side"]) == (model, mode, "new")]
            warm = [s["warmup_s"] for s in samples if (s["model"], s["mode"], s["side"]) == (model, mode, "new")]
            med = statistics.median
            if args.arm:
                arm = settings[(model, mode)]
                first = next(s for s in samples if (s["model"], s["mode"]) == (model, mode))
                padded, graphs = first["padded"], first["graphs"]
                compiled = f"{graphs} ({first['cudagraph_skips']} CUDA-graph skips)" if graphs else "none (eager)"
                row = (f"| {model} | {args.arm} | {mode} | {arm['precision']} | {padded[0]} x {padded[1]} | "
                       f"{compiled} | {med(new):,.0f} | {spread(new)} | {med(warm):.1f} |")
            else:
                row = f"| {model} | {mode} | {med(new):,.0f} | {spread(new)} | {med(warm):.1f} |"
            if not args.fit:
                row += rate_cells(med(new), flops[model], peaks[precisions[(model, mode)]])
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
    if not args.fit:
        used = "; ".join(f"{p}: {peak[0]:,.1f} TFLOP/s ({peak[1]})" for p, peak in peaks.items() if peak)
        print(f"\nFLOPs per frame: forward and backward of one optimiser step, counted on the CPU "
              f"(torch.utils.flop_counter). Peaks: {used or 'n/a (no datasheet entry for this device; --peak-tflops)'}")


if __name__ == "__main__":
    main()
