"""The report's learning curves: a run's epochs read whole across resumes, and the figure of a study's runs."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image

from vitfly.training.metrics_csv import epoch_curves
from vitfly.workflows.reproduce_config import load_reproduce_config
from vitfly.workflows.training_curves import study_curves, training_curves_figure

REPO = Path(__file__).resolve().parents[1]
HEADER = "epoch,step,train/loss_epoch,train/loss_step,val/loss\n"


def test_epoch_curves_join_the_parts_of_a_resumed_run(tmp_path):
    """Rows as CSVLogger writes them (step rows without an epoch value, epoch rows, validation rows apart); the
    earlier part's epoch 1 (0-based) was trained again after a resume, so the later row is the one kept."""
    (tmp_path / "metrics.earlier.csv").write_text(
        HEADER + "0,9,,0.5,\n0,9,0.40,,\n0,9,,,0.30\n1,19,0.35,,\n")
    (tmp_path / "metrics.csv").write_text(
        HEADER + ",,,,\n1,19,0.25,,\n1,19,,,0.28\n2,29,0.20,,\n")
    curves = epoch_curves(tmp_path)
    assert curves == {"train/loss_epoch": [(1, 0.40), (2, 0.25), (3, 0.20)], "val/loss": [(1, 0.30), (2, 0.28)]}
    assert epoch_curves(tmp_path, ("train/loss_step", "val/r2_lateral")) == {
        "train/loss_step": [(1, 0.5)], "val/r2_lateral": []}
    assert epoch_curves(tmp_path / "none") == {"train/loss_epoch": [], "val/loss": []}


def test_the_report_draws_every_run_that_logged_an_epoch(tmp_path):
    """The tiny preset's three runs, two of them with metrics (one unfinished, one without validation yet); a
    draw folder is not the run's own and is left out."""
    cfg = load_reproduce_config(REPO / "configs" / "reproduce.yaml", "tiny", {"out": str(tmp_path / "study")})
    figure = tmp_path / "study" / "figures" / "training_curves.png"
    assert training_curves_figure(cfg, figure) is None and not figure.exists()  # nothing trained yet
    for folder, text in (("convnet-state", HEADER + "0,9,0.4,,\n0,9,,,0.3\n1,19,0.3,,\n"),
                         ("convnet-nostate", HEADER + "0,9,0.5,,\n"),
                         ("convnet-state-s1", HEADER + "0,9,0.9,,\n")):
        (cfg.out_dir / "train" / folder).mkdir(parents=True)
        (cfg.out_dir / "train" / folder / "metrics.csv").write_text(text)
    assert study_curves(cfg) == {
        "convnet": {"train/loss_epoch": [(1, 0.4), (2, 0.3)], "val/loss": [(1, 0.3)]},
        "convnet-nostate": {"train/loss_epoch": [(1, 0.5)], "val/loss": []}}
    assert training_curves_figure(cfg, figure) == figure
    height, width, _ = matplotlib.image.imread(figure).shape
    assert width > 2 * height  # two panels side by side
