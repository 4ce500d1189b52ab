"""Static shapes for CUDA graphs: batches padded to a length bucket train exactly as unpadded ones.

``data.time_bucket_steps`` pads each batch's time axis (and a short last batch) with masked steps;
``model.static_shapes`` keeps that shape through the step (every frame through the encoder, batch norm
weighted to the real frames, a masked-sum loss). Loss and gradients must be those of today's path, and an
epoch must show at most one shape per bucket.
"""

from __future__ import annotations

import math

import lightning as L
import pytest
import torch
from test_datamodule import write_dataset
from test_policy_module import quiet_trainer
from torch import nn

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.dataset import TrajectoryDataset, collate_trajectories, pad_to_bucket
from vitfly.errors import VitflyError
from vitfly.zoo.compiled import compile_encoder
from vitfly.zoo.masked_norm import FrameWeights, MaskedBatchNorm2d, mask_batch_norm
from vitfly.zoo.policy import create_policy, dense_masked_mse, weighted_masked_mse

torch.set_num_threads(1)

LENGTHS = [10, 23, 17, 6, 31, 12, 27, 9, 19, 14]


@pytest.fixture(scope="module")
def dataset_path(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("data") / "d.h5", LENGTHS)


def batch_of(path, indices):
    ds = TrajectoryDataset(path)
    return collate_trajectories([ds[i] for i in indices])


def twin_policies(name: str, **kwargs):
    """(today's path, static shapes) with the same weights; LSTM dropout off (its masks are drawn per shape)."""
    if name in ("lstmnet", "unet_lstm", "vit_lstm"):
        kwargs["model_kwargs"] = {"lstm_dropout": 0.0}
    torch.manual_seed(0)
    reference = create_policy(name, **kwargs)
    static = create_policy(name, static_shapes=True, **kwargs)
    static.load_state_dict(reference.state_dict())
    reference.train()
    static.train()
    return reference, static


def chunk_results(module, batch):
    """Per optimiser step (chunk): (chunk shape, loss, gradients); the recurrent state carried, detached."""
    results, hidden = [], None
    for chunk in module.tbptt_chunks(batch):
        module.zero_grad()
        loss, hidden = module.chunk_loss(chunk, hidden)
        loss.backward()
        hidden = None if hidden is None else tuple(h.detach() for h in hidden)
        results.append((tuple(chunk["mask"].shape), loss.detach(), [p.grad.clone() for p in module.parameters()]))
    return results


def assert_same_steps(results_a, results_b):
    assert len(results_a) == len(results_b)
    for (_, loss_a, grads_a), (_, loss_b, grads_b) in zip(results_a, results_b, strict=True):
        torch.testing.assert_close(loss_a, loss_b, rtol=1e-5, atol=1e-7)
        for ga, gb in zip(grads_a, grads_b, strict=True):
            # float rounding of differently ordered sums (batch-norm statistics over more frames)
            torch.testing.assert_close(ga, gb, rtol=1e-4, atol=2e-4 * float(ga.abs().max()) + 1e-12)


# -- same loss, same gradients ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["convnet", "vit", "lstmnet", "vit_lstm"])  # feed-forward and recurrent; BN and LN
@pytest.mark.parametrize("tbptt_steps", [None, 8])  # the paper's whole trajectories, and vitfly's chunks
def test_bucket_padding_keeps_loss_and_gradients(dataset_path, name, tbptt_steps):
    reference, static = twin_policies(name, tbptt_steps=tbptt_steps)
    batch = batch_of(dataset_path, [0, 1])  # lengths 10 and 23
    padded = pad_to_bucket(batch, 16, batch_size=3)  # (3, 32): one more row and 9 more steps, all masked
    assert padded["mask"].shape == (3, 32) and int(padded["mask"].sum()) == 33
    ref_steps, static_steps = chunk_results(reference, batch), chunk_results(static, padded)
    assert_same_steps(ref_steps, static_steps)
    # the static chunks keep the padded batch's shape: whole chunks, every row
    expected = [(3, 32)] if tbptt_steps is None else [(3, 8)] * 3
    assert [shape for shape, _, _ in static_steps] == expected
    # batch-norm running statistics moved as over the real frames alone
    for (key, a), (_, b) in zip(reference.net.named_buffers(), static.net.named_buffers(), strict=True):
        if a.is_floating_point():
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=key)


@pytest.mark.parametrize("name", ["lstmnet", "vit_lstm"])
def test_padding_at_the_end_leaves_the_real_steps_of_a_recurrent_model_alone(dataset_path, name):
    reference, static = twin_policies(name, tbptt_steps=None)
    batch = batch_of(dataset_path, [1, 3])  # lengths 23 and 6: row 1 is padded inside the batch already
    padded = pad_to_bucket(batch, 32)  # 9 more steps after everything
    mask = batch["mask"]
    with torch.no_grad():
        ref_out, _ = reference._forward_valid(batch["depth"], batch["desired_speed"], batch["quat"], None, mask)
        out, _ = static._forward_all_frames(padded["depth"], padded["desired_speed"], padded["quat"], None,
                                            padded["mask"])
    # the LSTM is causal: what follows a real step (padding) cannot change it
    torch.testing.assert_close(out[:, :23][mask], ref_out[mask], rtol=1e-5, atol=1e-6)
    assert static._frame_weights is None or static._frame_weights.weights is None  # cleared after the forward


def test_compiled_static_step_traces_the_masked_batch_norm_once(dataset_path):
    """What CUDA graphs will replay: the compiled encoder (aot_eager here: no code generation on the CPU) with
    batch norm weighted by the frame mask, the same gradients for every bucket, one graph for all frame counts."""
    from torch._dynamo.utils import counters

    reference, static = twin_policies("lstmnet", tbptt_steps=None)
    compile_encoder(static.net, backend="aot_eager")
    static.compile_mode = "default"  # mark the frame weights dynamic, as the frames
    torch._dynamo.reset()
    counters.clear()
    for index in (0, 1, 3, 0):
        batch = batch_of(dataset_path, [index])
        assert_same_steps(chunk_results(reference, batch), chunk_results(static, pad_to_bucket(batch, 8)))
    assert not counters["graph_break"]
    assert counters["stats"]["unique_graphs"] == 1


# -- one shape per bucket over a real epoch ---------------------------------------------------------------------


class ShapeRecorder(L.Callback):
    def __init__(self, net: nn.Module) -> None:
        self.batch_shapes: set[tuple] = set()
        self.frame_counts: set[int] = set()  # frames per encoder call, training and validation
        self.train_frame_counts: set[int] = set()
        encode = net.encode

        def recording_encode(frames):
            self.frame_counts.add(frames.shape[0])
            if net.training:
                self.train_frame_counts.add(frames.shape[0])
            return encode(frames)

        net.encode = recording_encode

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self.batch_shapes.add(tuple(batch["mask"].shape))


def shapes_of_one_epoch(path, root, bucket, resident=True, tbptt_steps=None):
    module = create_policy("convnet", static_shapes=True, tbptt_steps=tbptt_steps, warmup_epochs=0)
    data = TrajectoryDataModule(path, batch_size=3, val_fraction=0.2, num_workers=0, resident=resident,
                                time_bucket_steps=bucket)
    recorder = ShapeRecorder(module.net)
    trainer = quiet_trainer(root, max_epochs=1)
    trainer.callbacks.append(recorder)
    trainer.fit(module, datamodule=data)
    return recorder


@pytest.mark.parametrize("resident", [True, False])
def test_an_epoch_has_at_most_one_shape_per_bucket(dataset_path, tmp_path, resident):
    bucket = 8
    buckets = math.ceil(max(LENGTHS) / bucket)  # 4
    recorded = shapes_of_one_epoch(dataset_path, tmp_path, bucket, resident)
    # 8 training trajectories in batches of 3: the last batch (2) is padded to 3 rows
    assert {b for b, _ in recorded.batch_shapes} == {3}
    assert all(t % bucket == 0 for _, t in recorded.batch_shapes)
    assert len(recorded.frame_counts) <= buckets  # training and validation encoder calls together
    # without buckets the same epoch shows a shape per batch length
    unbucketed = shapes_of_one_epoch(dataset_path, tmp_path / "none", None, resident)
    assert len(unbucketed.frame_counts) > len(recorded.frame_counts)


def validation_metrics(path, root, name, **data_kwargs) -> tuple[dict[str, float], int]:
    """(the validation metrics, the number of validation batches) of one fixed network, 5 held-out trajectories."""
    torch.manual_seed(0)
    module = create_policy(name, static_shapes=bool(data_kwargs.get("time_bucket_steps")))
    dm = TrajectoryDataModule(path, batch_size=1, val_fraction=0.5, resident=False, **data_kwargs)
    trainer = quiet_trainer(root, 1)
    [metrics] = trainer.validate(module, datamodule=dm, verbose=False)
    return metrics, trainer.num_val_batches[0]


@pytest.mark.parametrize("name", ["lstmnet", "vit_lstm"])  # recurrent, with batch norms and with layer norms
def test_validation_batches_of_many_trajectories_score_as_one_at_a_time(dataset_path, tmp_path, name):
    """``val_batch_size``: the paper's one-trajectory steps validated 4 trajectories a call (padded rows and
    steps, bucketed or not) give the metrics of validating them one by one, in fewer calls."""
    one, calls_one = validation_metrics(dataset_path, tmp_path / "a", name)
    assert calls_one == 5 and set(one) == {"val/loss", "val/cosine", "val/r2_lateral", "val/r2_vertical"}
    for kwargs in ({"val_batch_size": 4}, {"val_batch_size": 4, "time_bucket_steps": 16}):
        many, calls = validation_metrics(dataset_path, tmp_path / "b", name, **kwargs)
        assert calls == 2  # ceil(5 / 4)
        for key, value in one.items():
            torch.testing.assert_close(many[key], value, rtol=1e-5, atol=1e-6, msg=key)


def test_a_validation_batch_size_below_one_is_one_error(dataset_path):
    with pytest.raises(VitflyError, match="val_batch_size: expected a positive number of trajectories, got 0"):
        TrajectoryDataModule(dataset_path, val_batch_size=0)
    with pytest.raises(VitflyError, match="cpu_val_batch_size: expected a positive number of trajectories, got -1"):
        TrajectoryDataModule(dataset_path, val_batch_size=16, cpu_val_batch_size=-1)


def test_a_trainer_on_the_cpu_validates_cpu_val_batch_size_a_call(dataset_path, tmp_path):
    """``cpu_val_batch_size: 2`` beside ``val_batch_size: 16``: a CPU trainer validates the 5 held-out trajectories
    in ceil(5 / 2) = 3 calls (16 a call would be one), with the one-at-a-time metrics."""
    one, _ = validation_metrics(dataset_path, tmp_path / "a", "lstmnet")
    many, calls = validation_metrics(dataset_path, tmp_path / "b", "lstmnet", val_batch_size=16,
                                     cpu_val_batch_size=2, time_bucket_steps=16)
    assert calls == 3
    for key, value in one.items():
        torch.testing.assert_close(many[key], value, rtol=1e-5, atol=1e-6, msg=key)
    _, calls = validation_metrics(dataset_path, tmp_path / "c", "lstmnet", val_batch_size=16)
    assert calls == 1


def test_chunks_of_a_bucket_multiple_share_one_shape(dataset_path, tmp_path):
    recorded = shapes_of_one_epoch(dataset_path, tmp_path, bucket=8, tbptt_steps=8)
    assert recorded.train_frame_counts == {3 * 8}  # every training step: 3 rows x 8 steps


# -- the pieces ------------------------------------------------------------------------------------------------


def test_pad_to_bucket_pads_time_and_rows_with_masked_zeros(dataset_path):
    batch = batch_of(dataset_path, [2, 3])  # lengths 17 and 6
    padded = pad_to_bucket(batch, 8, batch_size=4)
    assert padded["depth"].shape == (4, 24, 1, 60, 90) and padded["quat"].shape == (4, 24, 4)
    assert padded["mask"].sum(dim=1).tolist() == [17, 6, 0, 0]
    assert padded["traj_index"].tolist() == [2, 3, -1, -1] and padded["start"].tolist() == [0, 0, 0, 0]
    for key in ("depth", "desired_speed", "quat", "velocity_cmd"):
        torch.testing.assert_close(padded[key][:2, :17], batch[key], rtol=0, atol=0)
        assert float(padded[key][:, 17:].abs().sum()) == 0.0 and float(padded[key][2:].abs().sum()) == 0.0
    assert pad_to_bucket(padded, 8, batch_size=4) is padded  # already bucketed


def test_dense_masked_mse_is_the_weighted_masked_mse_whatever_the_padding_holds():
    g = torch.Generator().manual_seed(0)
    prediction, target = torch.randn(3, 7, 3, generator=g), torch.randn(3, 7, 3, generator=g)
    mask = torch.rand(3, 7, generator=g) > 0.4
    prediction[~mask] = float("inf")  # padding may hold anything
    for avoid_weight in (0.0, 10.0):
        torch.testing.assert_close(dense_masked_mse(prediction, target, mask, avoid_weight),
                                   weighted_masked_mse(prediction, target, mask, avoid_weight))


@pytest.mark.parametrize("momentum", [0.1, None])
def test_masked_batch_norm_is_batch_norm_over_the_real_frames(momentum):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(7, 4, 5, 6, generator=g)
    real = torch.tensor([1, 1, 0, 1, 0, 0, 1], dtype=torch.bool)
    plain = nn.BatchNorm2d(4, momentum=momentum)
    masked = nn.Sequential(nn.BatchNorm2d(4, momentum=momentum))
    masked.load_state_dict({"0." + k: v for k, v in plain.state_dict().items()})
    weights = mask_batch_norm(masked)
    assert isinstance(masked[0], MaskedBatchNorm2d) and isinstance(weights, FrameWeights)
    assert set(masked.state_dict()) == {"0." + k for k in plain.state_dict()}  # checkpoints unchanged
    for _ in range(2):
        weights.weights = real.float()
        torch.testing.assert_close(masked(x)[real], plain(x[real]), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(masked[0].running_mean, plain.running_mean)
    torch.testing.assert_close(masked[0].running_var, plain.running_var)
    assert int(masked[0].num_batches_tracked) == 2
    masked.eval(), plain.eval()
    torch.testing.assert_close(masked(x), plain(x))  # eval: the running statistics, as batch norm
    weights.weights = None
    masked.train(), plain.train()
    torch.testing.assert_close(masked(x), plain(x))  # no weights: plain batch norm


def test_other_batch_norm_kinds_refuse_static_shapes():
    with pytest.raises(VitflyError, match=r"model.static_shapes: layer '0' is a BatchNorm1d"):
        mask_batch_norm(nn.Sequential(nn.BatchNorm1d(3)))
    assert mask_batch_norm(nn.Sequential(nn.LayerNorm(3))) is None  # nothing to mask


# -- configuration ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", [0, -8, 2.5, True, "64"])
def test_bad_time_bucket_is_one_error_naming_the_field(dataset_path, value):
    with pytest.raises(VitflyError, match=r"^data.time_bucket_steps: expected a positive number of time steps"):
        TrajectoryDataModule(dataset_path, time_bucket_steps=value)


@pytest.mark.parametrize("kwargs,message", [
    ({"compile": "fast"}, r"^model.compile: expected false, true \(default mode\) or reduce-overhead, got 'fast'"),
    ({"compile": 1}, r"^model.compile: expected false, true"),
    ({"compile": "reduce-overhead"}, r"^model.compile: reduce-overhead .* needs model.static_shapes: true"),
])
def test_bad_compile_mode_is_one_error_naming_the_field(kwargs, message):
    with pytest.raises(VitflyError, match=message):
        create_policy("convnet", **kwargs)


def test_reduce_overhead_runs_eagerly_off_cuda(dataset_path):
    reference, _ = twin_policies("vit", tbptt_steps=None)
    torch.manual_seed(0)
    graphs = create_policy("vit", tbptt_steps=None, static_shapes=True, compile="reduce-overhead")
    graphs.load_state_dict(reference.state_dict())
    graphs.train()
    batch = batch_of(dataset_path, [3])
    with pytest.warns(RuntimeWarning, match="reduce-overhead \\(CUDA graphs\\) needs a CUDA device"):
        steps = chunk_results(graphs, pad_to_bucket(batch, 8))
    assert_same_steps(chunk_results(reference, batch), steps)


def test_backends_that_generate_no_code_need_no_cxx_compiler(monkeypatch):
    """aot_eager and eager need no C++ compiler (the Docker image has none): only inductor falls back to eager."""
    import shutil

    from vitfly.zoo import create_model

    monkeypatch.setattr(shutil, "which", lambda _name: None)
    monkeypatch.delenv("CXX", raising=False)
    frames = torch.rand(3, 1, 60, 90)
    traced = compile_encoder(create_model("convnet").eval(), backend="aot_eager")
    inductor = compile_encoder(create_model("convnet").eval())
    with torch.no_grad():
        traced.encode(frames)
        inductor.encode(frames)
    assert not traced.encode.failed and inductor.encode.failed
