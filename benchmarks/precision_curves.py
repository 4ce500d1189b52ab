"""fp32 against bf16 mixed precision: loss curves of every model over the same steps, data and seed.

For each model and each precision (Lightning ``32-true`` and ``bf16-mixed``) the shipped
``configs/fit/<model>.yaml`` hyper-parameters train on one dataset from the same seed for ``--epochs``
epochs (same batches in the same order, same number of optimiser steps), validating ``--val-per-epoch``
times per epoch. The warm-up is shortened to ``--warmup-epochs`` so the run reaches the full learning
rate (a stricter test of bf16 than the first epochs of the paper's 5-epoch warm-up). Writes
``<out>/precision_curves.csv`` (model, precision, kind = train|val, optimiser step, loss) and
``<out>/precision_curves.png``, and prints the final validation losses and their ratio.

    .venv/bin/python benchmarks/precision_curves.py --data data/speed40.h5 --out runs/precision \
        [--models vit_lstm convnet --epochs 2 --train-batches 4]
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import lightning as L
import torch
import yaml
from lightning.pytorch.callbacks import Callback

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.zoo import list_models
from vitfly.zoo.policy import create_policy

PRECISIONS = ("32-true", "bf16-mixed")
CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs" / "fit"


class LossRecorder(Callback):
    """Train loss after every batch (mean over its TBPTT chunks) and val loss after every validation."""

    def __init__(self) -> None:
        self.rows: list[tuple[str, int, float]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        loss = trainer.callback_metrics.get("train/loss_step")
        if loss is not None:
            self.rows.append(("train", trainer.global_step, float(loss)))

    def on_validation_end(self, trainer, pl_module) -> None:
        loss = trainer.callback_metrics.get("val/loss")
        if loss is not None and not trainer.sanity_checking:
            self.rows.append(("val", trainer.global_step, float(loss)))


def shipped_args(model: str) -> tuple[dict, dict]:
    """(model init_args, data args) of configs/fit/<model>.yaml, less the keys this script sets itself."""
    config = yaml.safe_load((CONFIG_DIR / f"{model}.yaml").read_text())
    model_args = dict(config["model"].get("init_args", {}))
    data_args = {k: v for k, v in config["data"].items() if k not in ("data_path", "split_seed")}
    model_args.pop("compile", None)  # compilation changes no arithmetic worth comparing here
    return model_args, data_args


def run(model, precision, data, epochs, val_per_epoch, warmup, seed, root, train_batches):
    model_args, data_args = shipped_args(model)
    model_args["warmup_epochs"] = warmup
    L.seed_everything(seed, verbose=False)
    policy = create_policy(model, **model_args)
    datamodule = TrajectoryDataModule(data, split_seed=seed, **data_args)
    recorder = LossRecorder()
    trainer = L.Trainer(
        max_epochs=epochs,
        precision=precision,
        accelerator="cpu",
        default_root_dir=root / model / precision,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        val_check_interval=1.0 / val_per_epoch,
        limit_train_batches=train_batches,
        callbacks=[recorder],
    )
    start = time.perf_counter()
    trainer.fit(policy, datamodule=datamodule)
    return recorder.rows, time.perf_counter() - start


def plot(rows: list[dict], models: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(3, len(models))
    nrows = (len(models) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(5 * cols, 3.6 * nrows), squeeze=False)
    for ax, model in zip(axes.flat, models, strict=False):
        for precision, color in zip(PRECISIONS, ("tab:blue", "tab:orange"), strict=True):
            for kind, style in (("train", "-"), ("val", "o--")):
                key = (model, precision, kind)
                pts = [(r["step"], r["loss"]) for r in rows if (r["model"], r["precision"], r["kind"]) == key]
                if pts:
                    xs, ys = zip(*pts, strict=True)
                    alpha = 0.5 if kind == "train" else 1.0
                    ax.plot(xs, ys, style, color=color, alpha=alpha, label=f"{precision} {kind}")
        ax.set_title(model)
        ax.set_xlabel("optimiser step")
        ax.set_ylabel("MSE (paper eq. 1)")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(models) :]:
        ax.set_visible(False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="vitfly HDF5 dataset (e.g. from vitfly collect)")
    parser.add_argument("--out", default="runs/precision")
    parser.add_argument("--models", nargs="+", default=list_models())
    parser.add_argument("--epochs", type=int, default=2)
    parser.add_argument("--val-per-epoch", type=int, default=2)
    parser.add_argument("--train-batches", type=int, default=None, help="batches per epoch (default: all)")
    parser.add_argument("--warmup-epochs", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--tolerance", type=float, default=0.05, help="bf16 passes if its final val loss is within this share of fp32's"
    )
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    summary = []
    for model in args.models:
        final = {}
        for precision in PRECISIONS:
            recorded, seconds = run(
                model, precision, args.data, args.epochs, args.val_per_epoch, args.warmup_epochs, args.seed, out,
                args.train_batches,
            )
            rows += [{"model": model, "precision": precision, "kind": k, "step": s, "loss": v} for k, s, v in recorded]
            vals = [v for k, _, v in recorded if k == "val"]
            steps = max((s for _, s, _ in recorded), default=0)
            final[precision] = (vals[-1] if vals else float("nan"), steps, seconds)
            print(f"{model} {precision}: final val/loss {final[precision][0]:.5f} after {final[precision][1]} steps "
                  f"({seconds:.0f} s wall, shared machine)", flush=True)  # fmt: skip
        ratio = final["bf16-mixed"][0] / final["32-true"][0]
        summary.append((model, final["32-true"][0], final["bf16-mixed"][0], ratio, final["32-true"][1]))
        with open(out / "precision_curves.csv", "w", newline="") as f:  # rewritten after each model
            writer = csv.DictWriter(f, fieldnames=["model", "precision", "kind", "step", "loss"])
            writer.writeheader()
            writer.writerows(rows)
        plot(rows, [s[0] for s in summary], out / "precision_curves.png")
    per_epoch = "all" if args.train_batches is None else args.train_batches
    print(f"\n{args.epochs} epochs of {per_epoch} batches on {args.data}, seed {args.seed}, torch {torch.__version__}")
    print("| model | steps | fp32 final val loss | bf16 final val loss | bf16 / fp32 | within tolerance |")
    print("|---|---:|---:|---:|---:|---|")
    for model, fp32, bf16, ratio, steps in summary:
        ok = "yes" if abs(ratio - 1) <= args.tolerance else "no"
        print(f"| {model} | {steps} | {fp32:.5f} | {bf16:.5f} | {ratio:.3f} | {ok} |")
    print(f"\nwrote {out / 'precision_curves.csv'} and {out / 'precision_curves.png'}")


if __name__ == "__main__":
    main()
