"""PolicyModule: paper eq. 1, truncated BPTT across chunks, padding kept out of the loss, metrics, overfitting."""

from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch
from test_datamodule import write_dataset
from torch import nn

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.dataset import TrajectoryDataset, collate_trajectories
from vitfly.zoo import create_model, register_model
from vitfly.zoo.base import DepthPolicyNet
from vitfly.zoo.policy import (
    CommandCosine,
    PolicyModule,
    create_policy,
    lr_factor,
    masked_mse,
    policy_class,
    weighted_masked_mse,
)

torch.set_num_threads(1)


class RecordingLSTM(DepthPolicyNet):
    """A tiny recurrent network that records the state it is handed and the outputs it gives."""

    is_recurrent = True

    def __init__(self, use_state: bool = True) -> None:
        super().__init__(use_state)
        self.pool = nn.AdaptiveAvgPool2d((3, 3))
        self.lstm = nn.LSTM(9 + 5, 8, num_layers=1, batch_first=True)
        self.out = nn.Linear(8, 3)
        self.calls: list[tuple] = []

    def encode(self, frames):
        return self.pool(frames).flatten(1)

    def head(self, features, state, hidden=None):
        x, new_hidden = self.lstm(torch.cat((features, state), dim=-1), hidden)
        out = self.out(x)
        self.calls.append((hidden, out.detach().clone(), tuple(h.detach().clone() for h in new_hidden)))
        return out, new_hidden


if "test_recording_lstm" not in __import__("vitfly.zoo", fromlist=["list_models"]).list_models():
    register_model(lambda use_state=True: RecordingLSTM(use_state), name="test_recording_lstm")


def quiet_trainer(root, max_epochs: int) -> L.Trainer:
    """A Trainer without logger, checkpoints, progress bar or summary."""
    return L.Trainer(
        max_epochs=max_epochs,
        default_root_dir=root,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )


@pytest.fixture(scope="module")
def dataset_path(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("data") / "d.h5", [10, 23, 17, 6])


def make_batch(path, indices):
    ds = TrajectoryDataset(path)
    return collate_trajectories([ds[i] for i in indices])


def test_loss_is_paper_eq1_over_valid_steps(dataset_path):
    module = create_policy("convnet", tbptt_steps=None)
    module.eval()
    batch = make_batch(dataset_path, [0, 1])
    (chunk,) = list(module.tbptt_chunks(batch))
    loss, _ = module.chunk_loss(chunk)
    with torch.no_grad():
        expected = []
        for i, n in enumerate(batch["mask"].sum(dim=1).tolist()):
            pred, _ = module.net(
                batch["depth"][i : i + 1, :n], batch["desired_speed"][i : i + 1, :n], batch["quat"][i : i + 1, :n]
            )
            target = batch["velocity_cmd"][i, :n] / batch["desired_speed"][i, :n]
            expected.append((pred[0] - target) ** 2)
        expected = torch.cat(expected).mean()
    torch.testing.assert_close(loss, expected, rtol=1e-5, atol=1e-7)


def test_recurrent_state_crosses_chunk_boundaries(dataset_path):
    module = create_policy("test_recording_lstm", tbptt_steps=5)
    module.train()
    batch = make_batch(dataset_path, [1, 2])  # lengths 23 and 17 -> chunks of 5, 5, 5, 5, 3
    chunks = list(module.tbptt_chunks(batch))
    assert [c["mask"].shape[1] for c in chunks] == [5, 5, 5, 5, 3]
    net = module.net
    net.calls.clear()
    hidden = None
    outputs = []
    for chunk in chunks:
        loss, hidden = module.chunk_loss(chunk, hidden)
        loss.backward()
        outputs.append(net.calls[-1][1])
        hidden = tuple(h.detach() for h in hidden)
    # each chunk started from the previous chunk's final state, detached
    assert net.calls[0][0] is None
    for prev, cur in zip(net.calls[:-1], net.calls[1:], strict=True):
        assert not any(h.requires_grad for h in cur[0])
        for handed, returned in zip(cur[0], prev[2], strict=True):
            torch.testing.assert_close(handed, returned)
    # chunk by chunk equals one pass over the whole sequence (same weights: no optimiser step here)
    with torch.no_grad():
        whole, _ = net(batch["depth"], batch["desired_speed"], batch["quat"])
    torch.testing.assert_close(torch.cat(outputs, dim=1), whole[:, :23], rtol=1e-5, atol=1e-6)


def test_training_step_takes_one_optimiser_step_per_chunk(dataset_path, tmp_path):
    module = create_policy("test_recording_lstm", tbptt_steps=4, warmup_epochs=0)
    data = TrajectoryDataModule(dataset_path, batch_size=4, val_fraction=0.0)
    trainer = quiet_trainer(tmp_path, max_epochs=1)
    trainer.fit(module, datamodule=data)
    assert trainer.global_step == 6  # one batch of lengths up to 23 -> ceil(23 / 4) chunks


@pytest.mark.parametrize("name", ["convnet", "test_recording_lstm"])
def test_padding_never_reaches_the_loss(dataset_path, name):
    torch.manual_seed(0)
    module = create_policy(name, tbptt_steps=8)
    module.train()
    clean = make_batch(dataset_path, [0, 1, 3])  # lengths 10, 23, 6
    dirty = {k: v.clone() for k, v in clean.items()}
    pad = ~dirty["mask"]
    generator = torch.Generator().manual_seed(1)
    for key in ("depth", "desired_speed", "quat", "velocity_cmd"):
        garbage = 1e3 * torch.randn(dirty[key].shape, generator=generator)
        dirty[key][pad] = garbage[pad]

    def grads(batch):
        state = {k: v.clone() for k, v in module.state_dict().items()}
        result, hidden = [], None
        for chunk in module.tbptt_chunks(batch):
            module.zero_grad()
            loss, hidden = module.chunk_loss(chunk, hidden)
            loss.backward()
            hidden = None if hidden is None else tuple(h.detach() for h in hidden)
            result.append((loss.detach(), [p.grad.clone() for p in module.parameters()]))
        module.load_state_dict(state)  # batch-norm running statistics back to where they were
        return result

    for (loss_a, grads_a), (loss_b, grads_b) in zip(grads(clean), grads(dirty), strict=True):
        assert torch.isfinite(loss_a)
        torch.testing.assert_close(loss_a, loss_b, rtol=0, atol=0)
        for ga, gb in zip(grads_a, grads_b, strict=True):
            torch.testing.assert_close(ga, gb, rtol=1e-6, atol=1e-9)


def test_batch_norm_statistics_see_only_valid_frames(dataset_path):
    module = create_policy("convnet", tbptt_steps=None)
    module.train()
    batch = make_batch(dataset_path, [0, 1])  # 10 + 23 valid frames of 23 * 2
    reference = create_model("convnet")
    reference.load_state_dict(module.net.state_dict())
    reference.train()
    (chunk,) = list(module.tbptt_chunks(batch))
    module.chunk_loss(chunk)
    reference.encode(batch["depth"][batch["mask"]])
    torch.testing.assert_close(module.net.bn1.running_mean, reference.bn1.running_mean)
    torch.testing.assert_close(module.net.bn1.running_var, reference.bn1.running_var)


def test_command_cosine_keeps_sums_only():
    rng = torch.Generator().manual_seed(0)
    pred, target = torch.randn(50, 3, generator=rng), torch.randn(50, 3, generator=rng)
    metric = CommandCosine()
    metric.update(pred[:20], target[:20])
    metric.update(pred[20:], target[20:])
    expected = torch.nn.functional.cosine_similarity(pred, target, dim=-1).mean()
    torch.testing.assert_close(metric.compute(), expected)
    assert all(getattr(metric, name).numel() == 1 for name in ("cos_sum", "count"))


def test_lr_warmup_follows_the_paper_code():
    assert lr_factor(0, 5, 0.1, 1.0, 100) == pytest.approx(0.1)
    assert lr_factor(2.5, 5, 0.1, 1.0, 100) == pytest.approx(0.55)
    assert lr_factor(5, 5, 0.1, 1.0, 100) == 1.0
    assert lr_factor(80, 5, 0.1, 1.0, 100) == 1.0
    assert lr_factor(105, 5, 0.1, 0.1, 100) == pytest.approx(0.1)
    assert lr_factor(55, 5, 0.1, 0.1, 100) == pytest.approx(0.1**0.5)


def test_masked_mse_ignores_masked_rows():
    pred = torch.tensor([[[1.0, 1, 1], [np.nan, 0, 0]]])
    target = torch.zeros(1, 2, 3)
    mask = torch.tensor([[True, False]])
    assert float(masked_mse(pred, target, mask)) == 1.0


def test_avoidance_weighting_by_hand():
    # two valid steps: a straight label (weight 1) and a swerve with |(y, z)| = |(0.3, 0.4)| = 0.5
    # (weight 1 + 4 * 0.5 = 3); the third step is padding
    target = torch.tensor([[[1.0, 0.0, 0.0], [0.8, 0.3, 0.4], [5.0, 5.0, 5.0]]])
    pred = torch.tensor([[[1.0, 0.0, 0.3], [0.8, 0.0, 0.4], [0.0, 0.0, 0.0]]])
    mask = torch.tensor([[True, True, False]])
    # per-step mean squared errors: 0.09 / 3 = 0.03 and 0.09 / 3 = 0.03 -> any weighting gives 0.03
    assert float(weighted_masked_mse(pred, target, mask, 4.0)) == pytest.approx(0.03)
    pred[0, 1] = torch.tensor([0.8, 0.0, 0.0])  # the swerve's error grows to (0.09 + 0.16) / 3
    expected = (1 * 0.03 + 3 * 0.25 / 3) / (1 + 3)
    assert float(weighted_masked_mse(pred, target, mask, 4.0)) == pytest.approx(expected)
    assert float(weighted_masked_mse(pred, target, mask, 0.0)) == pytest.approx((0.03 + 0.25 / 3) / 2)
    with pytest.raises(Exception, match="model.avoid_weight"):
        create_policy("convnet", avoid_weight=-1.0)


def test_gradient_clipping_trains_under_bf16_autocast(dataset_path, tmp_path):
    # the fused Adam cannot be clipped by Lightning's mixed-precision plugin: clipping must pick another
    module = create_policy("convnet", tbptt_steps=8, warmup_epochs=0, gradient_clip_val=1e-3, cpu_threads=None)
    data = TrajectoryDataModule(dataset_path, batch_size=4, val_fraction=0.0)
    before = [p.detach().clone() for p in module.net.parameters()]
    trainer = L.Trainer(max_epochs=1, default_root_dir=tmp_path, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, precision="bf16-mixed")
    trainer.fit(module, datamodule=data)
    assert trainer.global_step == 3  # lengths up to 23 in chunks of 8
    moved = [p.detach() - b for p, b in zip(module.net.parameters(), before, strict=True)]
    assert any(float(m.abs().max()) > 0 for m in moved)


def test_short_names_are_policy_classes_with_contract_hparams():
    cls = policy_class("vit_lstm")
    assert issubclass(cls, PolicyModule) and cls.__name__ == "vit_lstm"
    import vitfly.zoo.policy as policy_module

    assert policy_module.vit_lstm is cls
    module = create_policy("lstmnet", use_state=False)
    assert module.hparams.model == "lstmnet" and module.hparams.use_state is False
    assert module.hparams.model_kwargs == {}
    assert module.net.use_state is False and module.is_recurrent
    assert all(k.startswith("net.") for k in module.state_dict())
    with pytest.raises(Exception, match="unknown model 'nope'"):
        create_policy("nope")


def test_convnet_overfits_a_tiny_dataset(dataset_path, tmp_path):
    torch.manual_seed(0)
    module = create_policy("convnet", lr=3e-3, warmup_epochs=0, tbptt_steps=None)
    data = TrajectoryDataModule(dataset_path, batch_size=4, val_fraction=0.0, cache_mb=16)
    data.setup("fit")
    batch = collate_trajectories([data._datasets["train"][i] for i in range(4)])

    def train_set_loss():
        module.eval()
        with torch.no_grad():
            (chunk,) = list(module.tbptt_chunks(batch))
            loss = float(module.chunk_loss(chunk)[0])
        module.train()
        return loss

    before = train_set_loss()
    trainer = quiet_trainer(tmp_path, max_epochs=80)
    trainer.fit(module, datamodule=data)
    after = train_set_loss()
    assert after < before / 10, (before, after)
