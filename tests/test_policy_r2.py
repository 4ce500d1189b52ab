"""Validation R^2 of the lateral and vertical commands: a constant command scores 0, a perfect one 1.

R^2 = 1 - sum (y - f)^2 / sum (y - mean y)^2 over the valid validation steps. A constant prediction equal
to the mean of the labels makes the two sums equal, so R^2 = 0 exactly (worked out by hand); a prediction
equal to every label makes the first sum 0, so R^2 = 1. MSE and cosine cannot tell the constant command
apart (the issue's constant predictor reached a cosine of 0.977).
"""

from __future__ import annotations

import lightning as L
import pytest
import torch
from test_datamodule import write_dataset
from torch import nn

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.dataset import depth_to_unit_float
from vitfly.zoo.policy import create_policy, normalised_target

torch.set_num_threads(1)


class ConstantNet(nn.Module):
    """The same normalised command for every frame."""

    def __init__(self, command: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("command", command.float())

    def forward(self, depth, desired_speed, quat, hidden=None):
        b, t = depth.shape[:2]
        return self.command.expand(b, t, 3).clone(), None


class LookupNet(nn.Module):
    """A perfect predictor: the label of each validation frame, looked up by the frame's pixels."""

    def __init__(self, table: dict[bytes, torch.Tensor]) -> None:
        super().__init__()
        self.table = table

    def forward(self, depth, desired_speed, quat, hidden=None):
        b, t = depth.shape[:2]
        out = torch.zeros(b, t, 3)
        for i in range(b):
            for j in range(t):
                out[i, j] = self.table.get(depth[i, j].numpy().tobytes(), torch.zeros(3))
        return out, None


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = write_dataset(tmp_path_factory.mktemp("r2") / "d.h5", [14, 9, 21, 11, 17, 8, 12, 10])
    dm = TrajectoryDataModule(path, batch_size=3, val_fraction=0.5, cache_mb=8)
    dm.setup("fit")
    return dm


def validation_labels(dm: TrajectoryDataModule) -> tuple[torch.Tensor, dict[bytes, torch.Tensor]]:
    """All valid validation labels (N, 3) and a frame -> label table (refusing frames seen with two labels)."""
    labels, table = [], {}
    for batch in dm.val_dataloader():
        batch = depth_to_unit_float(batch)
        target = normalised_target(batch["velocity_cmd"], batch["desired_speed"])
        mask = batch["mask"]
        for frame, label in zip(batch["depth"][mask], target[mask], strict=True):
            key = frame.numpy().tobytes()
            assert key not in table or torch.equal(table[key], label), "two labels for one frame"
            table[key] = label
        labels.append(target[mask])
    return torch.cat(labels), table


def validate(module, dm, tmp_path) -> dict[str, float]:
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, default_root_dir=tmp_path)
    (metrics,) = trainer.validate(module, datamodule=dm, verbose=False)
    return metrics


def test_constant_command_scores_zero_r2_but_a_high_cosine(data, tmp_path):
    labels, _ = validation_labels(data)
    module = create_policy("convnet")
    module.net = ConstantNet(labels.mean(dim=0))
    m = validate(module, data, tmp_path)
    assert m["val/r2_lateral"] == pytest.approx(0.0, abs=1e-5)
    assert m["val/r2_vertical"] == pytest.approx(0.0, abs=1e-5)
    assert m["val/cosine"] > 0.9  # what the old metrics saw: a constant forward command looks good
    # any other constant is worse than the mean: R^2 < 0 (shifted by 0.1 in y: -(0.1^2) / var(y))
    module.net = ConstantNet(labels.mean(dim=0) + torch.tensor([0.0, 0.1, 0.0]))
    shifted = validate(module, data, tmp_path)
    expected = -(0.1**2) / float(labels[:, 1].var(unbiased=False))
    assert shifted["val/r2_lateral"] == pytest.approx(expected, rel=1e-3)


def test_perfect_command_scores_one(data, tmp_path):
    _, table = validation_labels(data)
    module = create_policy("convnet")
    module.net = LookupNet(table)
    m = validate(module, data, tmp_path)
    assert m["val/r2_lateral"] == pytest.approx(1.0, abs=1e-6)
    assert m["val/r2_vertical"] == pytest.approx(1.0, abs=1e-6)
    assert m["val/loss"] == pytest.approx(0.0, abs=1e-10)
