"""Data loading: HDF5 (vitfly) versus the original PNG folders, and memory while streaming.

Measures, on synthetic depth trajectories with the look of the simulator's (smooth spheres on a far
background, so compression behaves as on real data):

1. time to first batch and steady samples (frames) per second through the training DataLoader from
   the HDF5 file (depth stored uncompressed, the default, and gzip-compressed), against the original
   way of reading PNG folders with PIL one image at a time (both as the original code did it,
   preloading every folder before the first step, and streamed);
2. peak resident memory (RSS) while streaming one epoch of a dataset larger than the cache.

    .venv/bin/python benchmarks/data_loading.py [--trajectories 40 --steps 300 --big-trajectories 240 --workers 0 2]
        [--depth-compression none gzip]

Numbers depend on the machine and on what else runs; docs/datasets.md quotes one run and the command.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from rich.progress import track

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.dataset import collate_trajectories
from vitfly.datamodules.schema import TrajectoryRecord, TrajectoryWriter, open_trajectories

LEGACY_HEADER = [
    "", "timestamp", "desired_vel", "quat_1", "quat_2", "quat_3", "quat_4", "pos_x", "pos_y", "pos_z",
    "vel_x", "vel_y", "vel_z", "velcmd_x", "velcmd_y", "velcmd_z", "ct_cmd", "br_cmd_x", "br_cmd_y", "br_cmd_z",
    "is_collide",
]  # fmt: skip


def sphere_frames(rng: np.random.Generator, steps: int) -> np.ndarray:
    """(steps, 60, 90) normalised depth: a ground plane below the horizon and a few shaded spheres
    drifting towards the camera, with sensor-like noise (so compression sees realistic texture)."""
    yy, xx = np.mgrid[0:60, 0:90].astype(np.float32)
    ground = np.where(yy > 30, np.clip(3.5 / np.maximum(yy - 30, 1e-3) * 45 / 10.0 / 10.0, 0, 1), 1.0)
    n = int(rng.integers(2, 6))
    cx, cy = rng.uniform(0, 90, n), rng.uniform(0, 60, n)
    dist = rng.uniform(0.3, 1.0, n)
    radius = rng.uniform(4, 14, n)
    frames = np.empty((steps, 60, 90), np.float32)
    for t in range(steps):
        frame = ground.copy()
        d = np.clip(dist - 0.002 * t, 0.05, 1.0)
        r = radius / d * 0.3
        for k in range(n):
            rho2 = ((xx - cx[k]) ** 2 + (yy - cy[k]) ** 2) / r[k] ** 2
            surface = d[k] - 0.05 * np.sqrt(np.clip(1 - rho2, 0, 1))
            frame = np.where(rho2 < 1, np.minimum(frame, surface), frame)
        frames[t] = np.clip(frame + rng.normal(0, 0.003, frame.shape), 0, 1)
    return frames


def make_record(seed: int, steps: int) -> TrajectoryRecord:
    rng = np.random.default_rng(seed)
    cmd = rng.normal(size=(steps, 3)).astype(np.float32)
    return TrajectoryRecord(
        depth=sphere_frames(rng, steps),
        desired_speed=3.0,
        quat=np.tile([1.0, 0.0, 0.0, 0.0], (steps, 1)),
        position=np.cumsum(cmd, axis=0),
        velocity=cmd,
        velocity_cmd=cmd,
        time=np.arange(steps) / 30.0,
        collision=np.zeros(steps, bool),
        seed=seed,
    )


def source_records(args: argparse.Namespace):
    """Records for the benchmark: the trajectories of --data (cycled), else synthetic ones."""
    if args.data is None:
        return lambda k: make_record(k, args.steps)
    tf = open_trajectories(args.data)
    return lambda k: tf[k % len(tf)]


def write_png_folder(root: Path, rec: TrajectoryRecord, index: int) -> None:
    folder = root / f"traj_{index:05d}"
    folder.mkdir(parents=True)
    with open(folder / "data.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(LEGACY_HEADER)
        for t in range(rec.length):
            stamp = 1e9 + t / 30.0
            Image.fromarray(rec.depth[t], mode="L").save(folder / f"{stamp:.6f}.png")
            writer.writerow([t, stamp, 3.0, *rec.quat[t], *rec.position[t], *rec.velocity[t],
                             *rec.velocity_cmd[t], 0, 0, 0, 0, False])  # fmt: skip


def png_trajectory(folder: Path) -> dict[str, torch.Tensor]:
    """One trajectory the original way: PIL per image (sorted by timestamp) + the CSV."""
    images = sorted(folder.glob("*.png"), key=lambda p: float(p.stem))
    depth = np.stack([np.asarray(Image.open(p), dtype=np.float32) / 255.0 for p in images])
    rows = np.genfromtxt(folder / "data.csv", delimiter=",", skip_header=1, usecols=range(1, 20))
    return {
        "depth": torch.from_numpy(np.rint(depth * 255).astype(np.uint8)),
        "desired_speed": torch.from_numpy(rows[:, 1:2].astype(np.float32)),
        "quat": torch.from_numpy(rows[:, 2:6].astype(np.float32)),
        "velocity_cmd": torch.from_numpy(rows[:, 12:15].astype(np.float32)),
        "traj_index": 0,
        "start": 0,
    }


class PngFolders(torch.utils.data.Dataset):
    def __init__(self, root: Path):
        self.folders = sorted(p for p in root.iterdir() if p.is_dir())

    def __len__(self) -> int:
        return len(self.folders)

    def __getitem__(self, i: int):
        return png_trajectory(self.folders[i])


def time_loader(loader, max_batches: int | None = None) -> tuple[float, float, int]:
    """(seconds to the first batch, steady frames/s after it, frames)."""
    start = time.perf_counter()
    first = None
    frames = 0
    for i, batch in enumerate(loader):
        n = int(batch["mask"].sum())
        if first is None:
            first = time.perf_counter() - start
            steady_start = time.perf_counter()
        else:
            frames += n
        if max_batches is not None and i + 1 >= max_batches:
            break
    steady = time.perf_counter() - steady_start
    return first, frames / steady if steady > 0 else float("nan"), frames


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def streaming(work: Path, args: argparse.Namespace) -> None:
    """Stream one epoch of a dataset larger than the cache; print resident memory before and at peak."""
    big = work / "big.h5"
    if not big.exists():
        with TrajectoryWriter(big, {"benchmark": True}, depth_compression=args.depth_compression[0]) as writer:
            record = source_records(args)
            for k in track(range(args.big_trajectories), description="writing the streaming dataset"):
                rec = record(k)
                rec.seed = 10_000 + k
                writer.append(rec)
    dm = TrajectoryDataModule(str(big), batch_size=args.batch_size, val_fraction=0.0, cache_mb=args.cache_mb)
    dm.setup("fit")
    before = peak = rss_mb()
    start = time.perf_counter()
    n = 0
    for batch in dm.train_dataloader():
        n += int(batch["mask"].sum())
        peak = max(peak, rss_mb())
    secs = time.perf_counter() - start
    file_mb = big.stat().st_size / 2**20
    raw_mb = n * 60 * 90 / 2**20
    print(
        f"\nstreaming {args.big_trajectories} trajectories = {n} frames ({raw_mb:.0f} MiB as uint8, "
        f"{4 * raw_mb:.0f} MiB as float32; file {file_mb:.0f} MiB, depth {args.depth_compression[0]}) "
        f"with a {args.cache_mb:.0f} MiB cache:"
    )
    print(f"RSS {before:.0f} MiB after start-up, peak {peak:.0f} MiB while streaming (+{peak - before:.0f} MiB); "
          f"{n / secs:,.0f} frames/s")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trajectories", type=int, default=40, help="trajectories for the HDF5 vs PNG comparison")
    parser.add_argument("--steps", type=int, default=300, help="steps (frames) per trajectory (30 Hz: 10 s)")
    parser.add_argument("--big-trajectories", type=int, default=240, help="trajectories of the streaming test")
    parser.add_argument("--cache-mb", type=float, default=64.0, help="loader cache in the streaming test")
    parser.add_argument("--batch-size", type=int, default=4)
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 2])
    parser.add_argument("--keep", type=Path, default=None, help="keep the generated data in this folder")
    parser.add_argument("--data", type=Path, default=None, help="take trajectories from this dataset (cycled)")
    parser.add_argument("--streaming-only", action="store_true", help="only the resident-memory measurement")
    parser.add_argument("--depth-compression", nargs="+", choices=("none", "gzip"), default=["none", "gzip"],
                        help="HDF5 depth storages to compare; the first is used for the memory test")  # fmt: skip
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.streaming_only:
        streaming(args.keep, args)
        return

    work = args.keep or Path(tempfile.mkdtemp(prefix="vitfly-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        h5_paths = {c: work / f"small-{c}.h5" for c in args.depth_compression}
        png_root = work / "png"
        if not png_root.exists():
            writers = [TrajectoryWriter(p, {"benchmark": True}, depth_compression=c) for c, p in h5_paths.items()]
            record = source_records(args)
            for seed in track(range(args.trajectories), description="writing HDF5 + PNG folders"):
                rec = record(seed)
                rec.seed = seed
                for writer in writers:
                    writer.append(rec)
                write_png_folder(png_root, TrajectoryRecord(**{**rec.__dict__, "depth": rec.row_arrays()["depth"]}),
                                 seed)  # fmt: skip
            for writer in writers:
                writer.close()
        with open_trajectories(next(iter(h5_paths.values()))) as tf:
            frames = tf.num_rows
        sizes = ", ".join(f"HDF5 depth {c} {p.stat().st_size / 2**20:.1f} MiB" for c, p in h5_paths.items())
        png_mb = sum(p.stat().st_size for p in png_root.rglob("*")) / 2**20
        print(f"\ndataset: {args.trajectories} trajectories, {frames} frames; {sizes}, PNG folders {png_mb:.1f} MiB")
        print("\n| source | workers | time to first batch (s) | steady frames/s |")
        print("|---|---|---|---|")
        for compression, h5_path in h5_paths.items():
            for workers in args.workers:
                dm = TrajectoryDataModule(str(h5_path), batch_size=args.batch_size, val_fraction=0.0,
                                          num_workers=workers, cache_mb=0)  # fmt: skip
                start = time.perf_counter()
                dm.setup("fit")  # opens and validates the file (NaN scan included)
                setup_s = time.perf_counter() - start
                first, rate, _ = time_loader(dm.train_dataloader())
                source = f"HDF5 (vitfly, streamed), depth {compression}"
                print(f"| {source} | {workers} | {setup_s + first:.2f} | {rate:,.0f} |")
        for workers in args.workers:
            loader = torch.utils.data.DataLoader(PngFolders(png_root), batch_size=args.batch_size, shuffle=True,
                                                 num_workers=workers, collate_fn=collate_trajectories)  # fmt: skip
            first, rate, _ = time_loader(loader)
            print(f"| PNG folders, PIL per image (streamed) | {workers} | {first:.2f} | {rate:,.0f} |")
        start = time.perf_counter()
        preloaded = [png_trajectory(f) for f in PngFolders(png_root).folders]
        preload_s = time.perf_counter() - start
        held_mb = sum(p["depth"].numel() * 4 for p in preloaded) / 2**20
        print(f"| PNG folders, preloaded as the original code (every folder before step 1) | 0 | {preload_s:.2f} | "
              f"(holds {held_mb:.0f} MiB as float32) |")  # fmt: skip
        del preloaded

        # memory in a fresh process, so the numbers above (and their garbage) do not count
        cmd = [sys.executable, __file__, "--streaming-only", "--big-trajectories", str(args.big_trajectories),
               "--steps", str(args.steps), "--cache-mb", str(args.cache_mb), "--batch-size", str(args.batch_size),
               "--keep", str(work), "--depth-compression", *args.depth_compression]
        cmd += ["--data", str(args.data)] if args.data else []
        subprocess.run(cmd, check=True)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
