"""Training through the simulator: what a gradient through the whole closed loop costs, beside the same flight
without one, in one run.

    .venv/bin/python benchmarks/sim_gradients.py                               # CPU: ConvNet, 16 scenes, 30 ticks
    .venv/bin/python benchmarks/sim_gradients.py --models convnet vit_lstm --scenes 16 64 --modes eager compiled
    python3 benchmarks/sim_gradients.py --device cuda --models convnet vit_lstm --scenes 64 1024 \\
        --modes eager compiled --json $OUT/sim_gradients.json                  # a GPU

For each model and batch of ``--scenes`` spheres/medium scenes at 5 m/s: ``fly_differentiable`` flies the
untrained network (``DifferentiablePolicy``, eval mode) for ``--ticks`` control ticks (every 90 x 60 image
rendered, 8 physics steps a tick), once under ``torch.no_grad`` and once keeping the graph, then the loss
(clearance and speed tracking) is backpropagated to the network's parameters. Each is run ``--repeats`` times
after one untimed warm-up, taking turns, and the fastest counts. Reported: env-steps (30 Hz ticks of one
scene) per second without and with the gradient, the gradient's cost as a ratio, and on CUDA the peak memory
the graph holds. ``--modes eager compiled`` measures both in one run, each batch eager then compiled
(``compile=True``: the warm-up then includes compiling, reported), and compares the compiled gradients with
the eager flight's once (the largest gap relative to the largest gradient). The modes run one after the other
for each batch (not alternating: a compiled mode's first call compiles).
``--json`` is rewritten after every measurement.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from vitfly.eval.learned_policy import DifferentiablePolicy
from vitfly.sim import make_scene
from vitfly.sim.batched.differentiable import fly_differentiable
from vitfly.sim.batched.scenes import scene_batch
from vitfly.zoo import create_model

SPEED_MPS = 5.0


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(model: str, scenes: int, mode: str, args) -> dict:
    """Seconds of the flight without a graph, with one, and of its backward pass, for one model and batch."""
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    torch.manual_seed(0)  # the same untrained weights in every mode and run
    net = create_model(model).to(device=device, dtype=dtype).eval()
    batch = scene_batch([make_scene("spheres", "medium", s) for s in range(scenes)], device, dtype)
    speed = torch.full((scenes,), SPEED_MPS, device=device, dtype=dtype)

    def flight(compile=mode == "compiled"):
        return fly_differentiable(batch, DifferentiablePolicy(net), speed, args.ticks, compile=compile)

    def loss_of(f):
        return torch.relu(1.0 - f.clearance).square().mean() + (f.velocity[..., 0] - speed).square().mean()

    def gradients(compile) -> torch.Tensor:
        net.zero_grad(set_to_none=True)
        loss_of(flight(compile)).backward()
        return torch.cat([p.grad.flatten() for p in net.parameters() if p.grad is not None])

    def forward_only() -> float:
        _sync(device)
        start = time.perf_counter()
        with torch.no_grad():
            flight()
        _sync(device)
        return time.perf_counter() - start

    def with_gradient() -> tuple[float, float, int]:
        net.zero_grad(set_to_none=True)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        _sync(device)
        start = time.perf_counter()
        loss = loss_of(flight())
        _sync(device)
        middle = time.perf_counter()
        loss.backward()
        _sync(device)
        peak = torch.cuda.max_memory_allocated(device) if device.type == "cuda" else 0
        return middle - start, time.perf_counter() - middle, peak

    start = time.perf_counter()
    forward_only()
    with_gradient()  # warm-up: allocator, cuDNN's choices, compiling
    warm_up_s = time.perf_counter() - start
    gap = None
    if mode == "compiled":  # the compiled gradients against eager ones, relative to the largest
        eager, compiled = gradients(False), gradients(True)
        gap = float((compiled - eager).abs().max() / eager.abs().max())
    plain, graph, backward, peak = [], [], [], 0
    for _ in range(args.repeats):
        plain.append(forward_only())
        f, b, p = with_gradient()
        graph.append(f)
        backward.append(b)
        peak = max(peak, p)
    steps = scenes * args.ticks
    best_plain, best_grad = min(plain), min(g + b for g, b in zip(graph, backward, strict=True))
    return {
        "model": model, "scenes": scenes, "ticks": args.ticks, "device": str(device), "dtype": args.dtype,
        "mode": mode, "warm_up_s": warm_up_s, "compiled_gradient_gap": gap,
        "forward_s": best_plain, "graph_forward_s": min(graph), "backward_s": min(backward),
        "env_steps_per_s": steps / best_plain, "env_steps_per_s_with_gradient": steps / best_grad,
        "gradient_cost": best_grad / best_plain, "peak_memory_mib": peak / 2**20 if peak else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["convnet"], help="zoo networks (default convnet)")
    parser.add_argument("--scenes", nargs="+", type=int, default=[16], help="scenes in lockstep (default 16)")
    parser.add_argument("--ticks", type=int, default=30, help="control ticks a flight (default 30: 1 s)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--threads", type=int, default=None, help="torch threads on the CPU (default torch's)")
    parser.add_argument("--modes", nargs="+", choices=["eager", "compiled"], default=["eager"],
                        help="eager, and/or compiled: the physics and camera through torch.compile "
                        "(fly_differentiable(compile=True)); its warm-up then includes compiling")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []
    for model in args.models:
        for scenes in args.scenes:
            for mode in args.modes:
                row = measure(model, scenes, mode, args)
                rows.append(row)
                memory = f", peak {row['peak_memory_mib']:,.0f} MiB" if row["peak_memory_mib"] else ""
                with_grad = row["env_steps_per_s_with_gradient"]
                gap = "" if row["compiled_gradient_gap"] is None else \
                    f"; compiled gradients within {row['compiled_gradient_gap']:.1e} of eager ones (relative)"
                print(f"{model} x {scenes} scenes, {mode}: {row['env_steps_per_s']:,.0f} env-steps/s without a "
                      f"gradient, {with_grad:,.0f} with one ({row['gradient_cost']:.1f}x the time){memory}{gap}",
                      flush=True)
                if args.json:
                    args.json.parent.mkdir(parents=True, exist_ok=True)
                    args.json.write_text(json.dumps({"rows": rows}, indent=2))
    print(f"\n{args.device}, {args.dtype}, {args.ticks} ticks a flight; fastest of {args.repeats}")
    print("| model | scenes | mode | env-steps/s, no gradient | env-steps/s, with gradient | gradient's cost "
          "| warm-up s | peak MiB |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    for r in rows:
        peak = f"{r['peak_memory_mib']:,.0f}" if r["peak_memory_mib"] else "-"
        rates = f"{r['env_steps_per_s']:,.0f} | {r['env_steps_per_s_with_gradient']:,.0f}"
        cost = f"{r['gradient_cost']:.1f}x | {r['warm_up_s']:.0f}"
        print(f"| {r['model']} | {r['scenes']} | {r['mode']} | {rates} | {cost} | {peak} |")


if __name__ == "__main__":
    main()
