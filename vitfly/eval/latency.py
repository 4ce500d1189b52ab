"""Inference latency of the model zoo, the way the paper's Table I measures it.

Batch 1, one control tick per call, recurrent state carried from call to call (as in flight), a warm-up,
then ``iters`` individually timed calls (``time.perf_counter``; CUDA synchronised after every call);
median and 90th percentile in milliseconds. Back ends: ``eager`` (the PyTorch module under
``torch.inference_mode``), ``compiled`` (the same with its encoder through ``torch.compile``),
``onnxruntime`` (an ONNX export with a fixed batch of 1, checked against eager before anything is timed)
and ``onnxruntime-int8`` (the same with its large products in int8 and, in the ViTs, the mix-FFNs as int8
convolutions calibrated on recorded expert flights; ``vitfly.deploy.quantize``). ``prepare_original``
times the original project's networks the same way, imported from a checkout
(``vitfly.eval.original_networks``); ``time_interleaved`` times several steps side by side on both clocks.
"""

from __future__ import annotations

import gc
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from vitfly.devices import check_torch_device
from vitfly.errors import VitflyError
from vitfly.eval.config import BACKENDS  # "onnxruntime-int8": large products in int8 (vitfly.deploy.quantize)
from vitfly.zoo import create_model


def backend_precision(backend: str) -> str:
    """The ONNX export precision of an ONNX Runtime back end ("fp32" or "int8")."""
    return "int8" if backend.endswith("-int8") else "fp32"


# Paper, Table I: (CPU ms, GPU ms); ResNet-18 has no entry
PAPER_LATENCY_MS: dict[str, tuple[float, float]] = {
    "convnet": (0.2, 0.4),
    "lstmnet": (4.8, 0.7),
    "unet_lstm": (5.6, 1.7),
    "vit": (5.6, 1.6),
    "vit_lstm": (9.2, 3.8),
}
PAPER_PARAMS: dict[str, int] = {
    "convnet": 235_269,
    "lstmnet": 2_949_937,
    "unet_lstm": 2_955_822,
    "vit": 3_101_199,
    "vit_lstm": 3_563_663,
}


@dataclass
class LatencyResult:
    """One model on one back end and device. Times in milliseconds per call (batch 1)."""

    model: str
    params: int
    backend: str
    device: str
    threads: int
    batch_size: int
    iters: int
    warmup: int
    median_ms: float
    p90_ms: float
    mean_ms: float
    min_ms: float
    max_abs_diff: float | None  # fast back end vs eager, from the check before timing
    paper_cpu_ms: float | None
    paper_gpu_ms: float | None

    def to_dict(self) -> dict:
        return asdict(self)


# "wall": elapsed time (the paper's measure); "cpu": CPU time of the process (all its threads), which leaves
# out the time spent waiting for a core on a shared machine (meaningful for one-thread runs)
CLOCKS: dict[str, Callable[[], float]] = {"wall": time.perf_counter, "cpu": time.process_time}


def time_calls(
    step: Callable[[], object],
    iters: int,
    warmup: int,
    synchronize: Callable[[], None] | None = None,
    clock: str = "wall",
) -> np.ndarray:
    """Milliseconds of each of ``iters`` calls of ``step`` after ``warmup`` untimed ones, on ``CLOCKS[clock]``."""
    if clock not in CLOCKS:
        raise VitflyError(f"--clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
    if iters < 1:
        raise VitflyError(f"--iters must be at least 1, got {iters}")
    if warmup < 0:
        raise VitflyError(f"--warmup must be >= 0, got {warmup}")
    for _ in range(warmup):
        step()
    if synchronize is not None:
        synchronize()
    times = np.empty(iters, dtype=np.float64)
    gc.collect()
    gc_was_enabled = gc.isenabled()
    gc.disable()  # a collection inside the loop would land in one sample
    try:
        now = CLOCKS[clock]
        for i in range(iters):
            start = now()
            step()
            if synchronize is not None:
                synchronize()
            times[i] = now() - start
    finally:
        if gc_was_enabled:
            gc.enable()
    return times * 1000.0


def time_interleaved(
    steps: dict[str, Callable[[], object]], calls: int, block: int = 20, warmup: int = 100
) -> dict[str, dict[str, np.ndarray]]:
    """Time several steps (one thread) side by side: milliseconds per call on both ``CLOCKS``, per step.

    After ``warmup`` untimed calls of each, the steps take turns in blocks of ``block`` calls, the order
    reversed every other round, until each has ``calls`` timed calls; a burst of load from other processes
    then lands on all of them alike instead of on whichever ran during it. Returns
    ``{name: {"wall": ms (calls,), "cpu": ms (calls,)}}``.
    """
    if calls < 1 or block < 1 or warmup < 0:
        raise VitflyError(f"calls and block must be >= 1 and warmup >= 0, got {calls}, {block}, {warmup}")
    names = list(steps)
    for name in names:
        for _ in range(warmup):
            steps[name]()
    times = {name: {clock: np.empty(calls) for clock in CLOCKS} for name in names}
    wall, cpu = CLOCKS["wall"], CLOCKS["cpu"]
    gc.collect()
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for round_, start in enumerate(range(0, calls, block)):
            stop = min(start + block, calls)
            for name in names if round_ % 2 == 0 else names[::-1]:
                step, w, c = steps[name], times[name]["wall"], times[name]["cpu"]
                for i in range(start, stop):
                    w0, c0 = wall(), cpu()
                    step()
                    c[i], w[i] = cpu() - c0, wall() - w0
    finally:
        if gc_was_enabled:
            gc.enable()
    return {name: {clock: t * 1000.0 for clock, t in by_clock.items()} for name, by_clock in times.items()}


def _inputs(device: torch.device, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One frame: random depth in [0, 1], 5 m/s, level attitude (w, x, y, z)."""
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(1, 1, 1, 60, 90, generator=g)
    speed = torch.full((1, 1, 1), 5.0)
    quat = torch.tensor([[[1.0, 0.0, 0.0, 0.0]]])
    return depth.to(device), speed.to(device), quat.to(device)


def eager_step(net: nn.Module, device: torch.device) -> Callable[[], object]:
    """A closure running one tick of ``net`` under inference mode, carrying its recurrent state."""
    depth, speed, quat = _inputs(device)
    state = {"hidden": None}

    def step():
        with torch.inference_mode():
            out, state["hidden"] = net(depth, speed, quat, state["hidden"])
        return out

    return step


def onnxruntime_step(
    net: nn.Module,
    device: torch.device,
    threads: int,
    atol: float | None = None,
    precision: str = "fp32",
    calibration_depth: np.ndarray | None = None,
) -> tuple[Callable[[], object], float]:
    """A closure running one tick through ONNX Runtime (fixed batch 1) and the check's largest difference.

    Raises VitflyError, timing nothing, if ONNX Runtime's outputs differ from eager by more than ``atol``
    (default: the export's ``CHECK_ATOL`` for ``precision``). ``calibration_depth``: see ``export_onnx_bytes``.
    """
    import onnxruntime as ort

    from vitfly.deploy.onnx import CHECK_ATOL, OnnxPolicyRunner, export_onnx_bytes

    providers = ["CPUExecutionProvider"]
    if device.type == "cuda" and precision == "int8":
        raise VitflyError("--backend onnxruntime-int8 runs on the CPU; use --device cpu")
    if device.type == "cuda":
        if "CUDAExecutionProvider" not in ort.get_available_providers():
            raise VitflyError("--backend onnxruntime --device cuda needs onnxruntime-gpu (CUDAExecutionProvider)")
        providers = ["CUDAExecutionProvider"]
    data = export_onnx_bytes(net, batch_size=1, precision=precision, calibration_depth=calibration_depth)
    runner = OnnxPolicyRunner(data, threads=threads, providers=providers)
    diff = runner.check_against(net.cpu(), atol=CHECK_ATOL[precision] if atol is None else atol, batch_size=1)
    if device.type == "cuda":  # inputs and outputs go through host memory here
        depth, speed, quat = (x.numpy() for x in _inputs(torch.device("cpu")))
        state = {"hidden": None}

        def step():
            out, state["hidden"] = runner.step(depth, speed, quat, state["hidden"])
            return out

        return step, diff
    bound = runner.bind(1)  # pre-bound buffers: what a flight loop would use
    for buffer, value in zip((bound.depth, bound.desired_speed, bound.quat), _inputs(device), strict=True):
        np.copyto(buffer, value.numpy())
    return bound, diff


def needs_calibration(net: nn.Module) -> bool:
    """Whether the int8 export of ``net`` has calibrated convolutions (the ViTs' mix-FFNs)."""
    from vitfly.zoo.vit import ViTBackbone

    return isinstance(net, ViTBackbone)


@dataclass
class PreparedStep:
    """One model ready to time: ``step()`` runs one control tick (batch 1), carrying its recurrent state."""

    model: str
    backend: str
    device: str
    threads: int
    params: int
    step: Callable[[], object]
    synchronize: Callable[[], None] | None = None
    max_abs_diff: float | None = None  # fast back end vs eager, from the check before timing


def prepare_step(
    name: str,
    backend: str = "eager",
    device: str = "cpu",
    threads: int = 1,
    net: nn.Module | None = None,
    calibration_depth: np.ndarray | None = None,
) -> PreparedStep:
    """Build (and, for ONNX Runtime back ends, export and check) one registered model (random weights unless
    ``net`` is given) for timing. The int8 back end of the ViTs calibrates its convolutions on
    ``calibration_depth`` (default ``vitfly.eval.agreement.calibration_depth()``, recorded expert flights)."""
    if backend not in BACKENDS:
        raise VitflyError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if threads < 1:
        raise VitflyError(f"--threads must be at least 1, got {threads}")
    check_torch_device(device, "--device")
    dev = torch.device(device)
    torch.manual_seed(0)
    net = (net if net is not None else create_model(name)).eval()
    params = sum(p.numel() for p in net.parameters())
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        diff = None
        if backend == "eager":
            net = net.to(dev)
            step = eager_step(net, dev)
        elif backend == "compiled":
            from vitfly.zoo import compile_encoder

            net = net.to(dev)
            compile_encoder(net)
            step = eager_step(net, dev)
        else:
            precision = backend_precision(backend)
            if precision == "int8" and calibration_depth is None and needs_calibration(net):
                from vitfly.eval.agreement import calibration_depth as default_calibration

                calibration_depth = default_calibration()
            step, diff = onnxruntime_step(net, dev, threads, precision=precision, calibration_depth=calibration_depth)
    finally:
        torch.set_num_threads(previous_threads)
    sync = torch.cuda.synchronize if (dev.type == "cuda" and backend == "eager") else None
    return PreparedStep(name, backend, dev.type, threads, params, step, sync, diff)


def prepare_original(module, name: str, threads: int = 1) -> PreparedStep:
    """The original project's network for model ``name`` (``original_networks.load_original_models``), called
    as the original deployment calls it (``original_networks.original_step``) on the same frame; CPU only.
    Back end "original"."""
    from vitfly.eval.original_networks import original_network, original_step

    if threads < 1:
        raise VitflyError(f"--threads must be at least 1, got {threads}")
    net = original_network(module, name)
    depth, speed, quat = _inputs(torch.device("cpu"))
    step = original_step(net, name, depth[0, 0, 0], float(speed), quat[0, 0])
    return PreparedStep(name, "original", "cpu", threads, sum(p.numel() for p in net.parameters()), step)


def time_step(prepared: PreparedStep, iters: int = 1000, warmup: int = 100, clock: str = "wall") -> LatencyResult:
    """Time a prepared model: ``warmup`` untimed ticks, then ``iters`` timed ones, torch on ``threads``.

    ``clock`` "cpu" (the process's CPU time) needs one thread on the CPU: VitflyError otherwise.
    """
    if clock == "cpu" and (prepared.threads != 1 or prepared.device != "cpu"):
        raise VitflyError("--clock cpu measures one thread on the CPU: use --threads 1 and the CPU")
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(prepared.threads)
    try:
        times = time_calls(prepared.step, iters, warmup, prepared.synchronize, clock)
    finally:
        torch.set_num_threads(previous_threads)
    paper = PAPER_LATENCY_MS.get(prepared.model)
    return LatencyResult(
        model=prepared.model,
        params=prepared.params,
        backend=prepared.backend,
        device=prepared.device,
        threads=prepared.threads,
        batch_size=1,
        iters=iters,
        warmup=warmup,
        median_ms=float(np.median(times)),
        p90_ms=float(np.percentile(times, 90)),
        mean_ms=float(times.mean()),
        min_ms=float(times.min()),
        max_abs_diff=prepared.max_abs_diff,
        paper_cpu_ms=paper[0] if paper else None,
        paper_gpu_ms=paper[1] if paper else None,
    )


def benchmark_model(
    name: str,
    backend: str = "eager",
    device: str = "cpu",
    threads: int = 1,
    iters: int = 1000,
    warmup: int = 100,
    net: nn.Module | None = None,
) -> LatencyResult:
    """Time one registered model (random weights unless ``net`` is given) on one back end and device."""
    return time_step(prepare_step(name, backend, device, threads, net), iters, warmup)


def benchmark_original(module, name: str, threads: int = 1, iters: int = 1000, warmup: int = 100) -> LatencyResult:
    """Time the original project's network for model ``name``; same frame, settings and clock as
    ``benchmark_model``."""
    return time_step(prepare_original(module, name, threads), iters, warmup)


def latency_table(results: Iterable[LatencyResult], title: str = "Inference latency (batch 1)"):
    """A rich Table in the paper's layout: one row per (model, back end), CPU and GPU columns side by side."""
    from rich.table import Table

    rows: dict[tuple[str, str], dict[str, LatencyResult]] = {}
    for r in results:
        rows.setdefault((r.model, r.backend), {})[r.device] = r
    threads = sorted({r.threads for group in rows.values() for r in group.values()})
    table = Table(title=f"{title}, {'/'.join(map(str, threads))} thread(s)")
    for column in ("Model", "Parameters", "Backend"):
        table.add_column(column)
    for column in ("CPU median ms", "CPU p90 ms", "GPU median ms", "Paper CPU ms", "Paper GPU ms"):
        table.add_column(column, justify="right")

    def fmt(x: float | None, digits: int = 3) -> str:
        return "n/a" if x is None else f"{x:.{digits}f}"

    for (model, backend), by_device in rows.items():
        cpu, gpu = by_device.get("cpu"), by_device.get("cuda")
        any_result = cpu or gpu
        paper = PAPER_LATENCY_MS.get(model)
        table.add_row(
            model,
            f"{any_result.params:,}",
            backend,
            fmt(cpu.median_ms if cpu else None),
            fmt(cpu.p90_ms if cpu else None),
            fmt(gpu.median_ms if gpu else None),
            fmt(paper[0] if paper else None, 1),
            fmt(paper[1] if paper else None, 1),
        )
    return table
