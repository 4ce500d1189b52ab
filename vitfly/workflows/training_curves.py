"""The report's learning curves: each run's training and validation loss against the epoch.

Read from every run's ``metrics.csv`` (whole across resumes and GPU slots, ``vitfly.training.metrics_csv``),
unfinished runs included, so a study in progress shows how far each run has come and whether its validation loss
still falls. One colour per network; the run with the state input solid, without it dashed. A run's other
training draws (``train.draws``) are left out: each would draw its run's curve again.
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure

from vitfly.eval.plots import _save, policy_colours
from vitfly.training.metrics_csv import epoch_curves
from vitfly.workflows.reproduce_config import ReproduceConfig, runs

PANELS = (("train/loss_epoch", "training loss (epoch mean)", True), ("val/loss", "validation loss", False))


def study_curves(cfg: ReproduceConfig) -> dict[str, dict[str, list]]:
    """Run label -> ``epoch_curves`` of each of the study's own runs (no other draws) that has logged an epoch."""
    curves = {}
    for run in runs(cfg, with_draws=False):
        curve = epoch_curves(cfg.train_dir(*run), tuple(column for column, _, _ in PANELS))
        if any(curve.values()):
            curves[run.label] = curve
    return curves


def training_curves_figure(cfg: ReproduceConfig, path: Path) -> Path | None:
    """Training loss (log scale) and validation loss per epoch of the study's runs into ``path``; None (nothing
    drawn) when no run has logged an epoch (a study of the shipped weights has no runs)."""
    if cfg.train.source == "pretrained":
        return None
    curves = study_curves(cfg)
    if not curves:
        return None
    colours = policy_colours([label.removesuffix("-nostate") for label in curves])
    fig = Figure(figsize=(11, 4))
    axes = fig.subplots(1, len(PANELS))
    for ax, (column, title, log) in zip(axes, PANELS, strict=True):
        for label, curve in curves.items():
            if curve[column]:
                epochs, values = zip(*curve[column], strict=True)
                model = label.removesuffix("-nostate")
                ax.plot(epochs, values, color=colours[model], linestyle="--" if label != model else "-",
                        marker="." if len(epochs) < 30 else None, label=label)
        ax.set_title(title)
        ax.set_xlabel("epoch")
        if log:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    handles = {}  # every run once, also one with a training curve only (no validation yet)
    for ax in axes:
        handles.update(zip(*reversed(ax.get_legend_handles_labels()), strict=True))
    axes[-1].legend(handles.values(), handles.keys(), fontsize=8, loc="best")
    fig.suptitle(f"{cfg.preset} preset: learning curves (dashed: without the state input)")
    return _save(fig, path)
