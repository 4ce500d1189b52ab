"""Is data ever the bottleneck? Loader frames/s against the frames/s a ConvNet training step consumes.

Streams a real dataset through ``TrajectoryDataModule``'s loader for a few epochs (the first reads from
disk and decompresses; later ones hit the LRU cache when it holds the dataset). The loader hands depth
over as uint8; the datamodule's ``on_after_batch_transfer`` makes it float32 on the training device, so
that conversion is timed on the consumer's side, together with ConvNet optimiser steps
(``benchmarks/train_speed.py``'s ``measure_steps``). Prints the ratio per epoch. Target: >= 10x.

    .venv/bin/python benchmarks/loader_headroom.py --data data/quickstart_spheres.h5 [--cache-mb 1024] [--cold]

``--cold`` evicts the dataset file from the OS page cache before every epoch (posix_fadvise DONTNEED, no root
needed), so reads that miss the loader's own cache come from the disk.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.dataset import depth_to_unit_float

sys.path.insert(0, str(Path(__file__).parent))
from train_speed import measure_steps  # noqa: E402


def evict_from_page_cache(path: str) -> None:
    """Ask the kernel to drop the file's cached pages, so the next reads go to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fdatasync(fd)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="a vitfly HDF5 dataset (e.g. from vitfly collect)")
    parser.add_argument("--cache-mb", type=float, default=1024.0)
    parser.add_argument("--batch-size", type=int, default=4, help="trajectories per batch")
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--workers", type=int, default=0, help="DataLoader worker processes")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--no-readahead", action="store_true", help="no OS read-ahead hints for the next batch")
    parser.add_argument("--cold", action="store_true", help="evict the file from the OS page cache before each epoch")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    dm = TrajectoryDataModule(
        data_path=args.data,
        batch_size=args.batch_size,
        cache_mb=args.cache_mb,
        num_workers=args.workers,
        readahead=not args.no_readahead,
    )
    dm.setup("fit")
    loader = dm.train_dataloader()
    rates = []
    for _ in range(args.epochs):
        if args.cold:
            evict_from_page_cache(args.data)
        start, frames = time.perf_counter(), 0
        for batch in loader:
            frames += int(batch["mask"].sum())
        rates.append(frames / (time.perf_counter() - start))
    convert_s, convert_frames = 0.0, 0
    for batch in loader:
        start = time.perf_counter()
        depth_to_unit_float(batch)
        convert_s += time.perf_counter() - start
        convert_frames += batch["depth"].shape[0] * batch["depth"].shape[1]
    step_rate = measure_steps("convnet", "fp32", batch=4, steps=64, iters=5, warmup=1, device="cpu",
                              threads=args.threads)["fps"]
    convert_rate = convert_frames / convert_s
    consumed = 1.0 / (1.0 / step_rate + 1.0 / convert_rate)

    print(
        f"{args.data}: {frames} training frames per epoch, cache {args.cache_mb:.0f} MiB, "
        f"{args.workers} loader workers, {args.threads} threads"
        + (", file evicted from the page cache before each epoch" if args.cold else "")
        + (", no read-ahead" if args.no_readahead else "")
    )
    print(
        f"ConvNet training step {step_rate:,.0f} frames/s (4 trajectories x 64 steps per step), uint8 -> float32 "
        f"depth {convert_rate:,.0f} frames/s: the trainer consumes {consumed:,.0f} frames/s"
    )
    for epoch, rate in enumerate(rates):
        print(f"loader epoch {epoch}: {rate:,.0f} frames/s = {rate / consumed:.1f}x")


if __name__ == "__main__":
    main()
