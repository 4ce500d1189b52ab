"""Training throughput per model on the CPU: frames per second one PolicyModule optimiser step consumes.

Each step is what ``vitfly fit`` runs per TBPTT chunk: forward over B trajectories x T steps, paper
eq. 1, backward, Adam step. The data loader must deliver at least 10x the ConvNet's rate
(see benchmarks/data_loading.py) so that data is never the bottleneck.

    .venv/bin/python benchmarks/train_speed.py [--models convnet vit_lstm --batch 4 --steps 64 --iters 5 --threads 2]
"""

from __future__ import annotations

import argparse
import time

import torch

from vitfly.zoo import list_models
from vitfly.zoo.policy import create_policy


def synthetic_batch(batch: int, steps: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    speed = torch.full((batch, steps, 1), 5.0)
    cmd = torch.randn(batch, steps, 3, generator=generator) + torch.tensor([5.0, 0.0, 0.0])
    quat = torch.nn.functional.normalize(torch.randn(batch, steps, 4, generator=generator), dim=-1)
    return {
        "depth": torch.rand(batch, steps, 1, 60, 90, generator=generator),
        "desired_speed": speed,
        "quat": quat,
        "velocity_cmd": cmd,
        "mask": torch.ones(batch, steps, dtype=torch.bool),
    }


def measure(name: str, batch: int, steps: int, iters: int, warmup: int) -> tuple[float, float]:
    """(frames per second, seconds per optimiser step) for one model."""
    module = create_policy(name, tbptt_steps=steps)
    module.train()
    optimizer = torch.optim.Adam(module.net.parameters(), lr=1e-4)
    data = synthetic_batch(batch, steps, torch.Generator().manual_seed(0))
    hidden = None
    times = []
    for i in range(warmup + iters):
        start = time.perf_counter()
        loss, hidden = module.chunk_loss(data, hidden)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        hidden = None if hidden is None else tuple(h.detach() for h in hidden)
        if i >= warmup:
            times.append(time.perf_counter() - start)
    per_step = sorted(times)[len(times) // 2]
    return batch * steps / per_step, per_step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list_models())
    parser.add_argument("--batch", type=int, default=4, help="trajectories per batch")
    parser.add_argument("--steps", type=int, default=64, help="time steps per TBPTT chunk")
    parser.add_argument("--iters", type=int, default=5, help="timed optimiser steps (median reported)")
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"CPU, {args.threads} threads, batch {args.batch} trajectories x {args.steps} steps per optimiser step\n")
    print("| model | frames/s | s per optimiser step |")
    print("|---|---|---|")
    for name in args.models:
        rate, per_step = measure(name, args.batch, args.steps, args.iters, args.warmup)
        print(f"| {name} | {rate:,.0f} | {per_step:.3f} |", flush=True)


if __name__ == "__main__":
    main()
