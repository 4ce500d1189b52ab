"""Where one training step's time goes: torch.profiler over PolicyModule optimiser steps on the CPU.

One step is what ``vitfly fit`` runs per batch: ``training_step`` on B trajectories x T steps (TBPTT chunks,
paper eq. 1, backward, Adam), outside Lightning's loop (the module gets a minimal trainer stand-in for the
learning-rate schedule). Prints the profiler's table of operators by self CPU time.

    .venv/bin/python benchmarks/profile_train_step.py [--model vit_lstm --batch 4 --steps 64 --precision 32 --rows 30]
"""

from __future__ import annotations

import argparse
import contextlib
import time

import torch
from torch.profiler import ProfilerActivity, profile

from vitfly.zoo.policy import create_policy


def synthetic_batch(batch: int, steps: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A batch as the datamodule hands it over (depth still uint8, converted by the step's own path)."""
    g = torch.Generator().manual_seed(seed)
    return {
        "depth": torch.randint(0, 256, (batch, steps, 1, 60, 90), generator=g, dtype=torch.uint8),
        "desired_speed": torch.full((batch, steps, 1), 5.0),
        "quat": torch.nn.functional.normalize(torch.randn(batch, steps, 4, generator=g), dim=-1),
        "velocity_cmd": torch.randn(batch, steps, 3, generator=g) + torch.tensor([5.0, 0.0, 0.0]),
        "mask": torch.ones(batch, steps, dtype=torch.bool),
    }


def one_step(module, optimizer, batch: dict[str, torch.Tensor], autocast: bool) -> None:
    """One batch: uint8 -> float on the device, then every TBPTT chunk's forward, backward and Adam step."""
    data = dict(batch)
    data["depth"] = data["depth"].to(torch.float32).mul_(1.0 / 255.0)
    hidden = None
    ctx = torch.autocast("cpu", dtype=torch.bfloat16) if autocast else contextlib.nullcontext()
    for chunk in module.tbptt_chunks(data):
        with ctx:
            loss, hidden = module.chunk_loss(chunk, hidden)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        hidden = None if hidden is None else tuple(h.detach() for h in hidden)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="vit_lstm")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--steps", type=int, default=64)
    parser.add_argument("--precision", choices=("32", "bf16"), default="32")
    parser.add_argument("--iters", type=int, default=2, help="profiled steps (after one warm-up step)")
    parser.add_argument("--rows", type=int, default=30)
    parser.add_argument("--sort", default="self_cpu_time_total")
    parser.add_argument("--shapes", action="store_true", help="one row per operator and input shapes")
    parser.add_argument("--threads", type=int, default=None, help="intra-op threads (default: all)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    module = create_policy(args.model, tbptt_steps=args.steps)
    module.train()
    optimizer = module.configure_optimizers()  # the module's own Adam (fused where the code has it)
    batch = synthetic_batch(args.batch, args.steps)
    autocast = args.precision == "bf16"
    one_step(module, optimizer, batch, autocast)  # warm-up: oneDNN primitives, allocator
    start = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU], record_shapes=args.shapes) as prof:
        for _ in range(args.iters):
            one_step(module, optimizer, batch, autocast)
    elapsed = (time.perf_counter() - start) / args.iters
    frames = args.batch * args.steps
    print(f"{args.model}, precision {args.precision}, {torch.get_num_threads()} threads: "
          f"{elapsed:.3f} s per step under the profiler ({frames / elapsed:,.0f} frames/s)")  # fmt: skip
    print(prof.key_averages(group_by_input_shape=args.shapes).table(sort_by=args.sort, row_limit=args.rows))


if __name__ == "__main__":
    main()
