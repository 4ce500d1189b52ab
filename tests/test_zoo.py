"""Model zoo: registry, call contract, parameter counts, spectral norm, inference fast paths, checkpoints."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from vitfly.errors import VitflyError
from vitfly.zoo import create_model, list_models, load_network, register_model, save_checkpoint
from vitfly.zoo.layers import SNLinear, min_pool2d, state_vector
from vitfly.zoo.recurrent import lstm_inference, run_lstm

torch.set_num_threads(1)

PAPER_PARAMS = {
    "convnet": 235_269,
    "lstmnet": 2_949_937,
    "unet_lstm": 2_955_822,
    "vit": 3_101_199,
    "vit_lstm": 3_563_663,
}
RECURRENT = {"lstmnet": (2, 395), "unet_lstm": (2, 200), "vit_lstm": (3, 128)}


def _inputs(b: int = 2, t: int = 3, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(b, t, 1, 60, 90, generator=g)
    speed = 3.0 + 4.0 * torch.rand(b, t, 1, generator=g)
    quat = torch.nn.functional.normalize(torch.randn(b, t, 4, generator=g), dim=-1)
    return depth, speed, quat


def test_registry_lists_the_six_names():
    assert set(list_models()) >= {"convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18"}


def test_unknown_model_lists_known_names():
    with pytest.raises(VitflyError, match="unknown model 'vit_gru'.*convnet.*vit_lstm"):
        create_model("vit_gru")


@pytest.mark.parametrize("name", sorted(PAPER_PARAMS))
@pytest.mark.parametrize("use_state", [True, False])
def test_parameter_counts_equal_the_paper(name, use_state):
    net = create_model(name, use_state=use_state)
    assert sum(p.numel() for p in net.parameters()) == PAPER_PARAMS[name]


@pytest.mark.parametrize("name", ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18"])
def test_call_contract_shapes_and_state(name):
    net = create_model(name).eval()
    depth, speed, quat = _inputs(2, 3)
    with torch.no_grad():
        out, hidden = net(depth, speed, quat)
    assert out.shape == (2, 3, 3)
    assert torch.isfinite(out).all()
    assert net.is_recurrent == (name in RECURRENT)
    if name in RECURRENT:
        layers, size = RECURRENT[name]
        assert hidden[0].shape == (layers, 2, size) and hidden[1].shape == (layers, 2, size)
        # running the sequence in two calls, carrying the state, equals one call over all of T
        with torch.no_grad():
            first, h1 = net(depth[:, :2], speed[:, :2], quat[:, :2])
            second, h2 = net(depth[:, 2:], speed[:, 2:], quat[:, 2:], h1)
        torch.testing.assert_close(torch.cat((first, second), 1), out, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(h2[0], hidden[0], atol=1e-4, rtol=0)
    else:
        assert hidden is None
        # frames are independent: one frame alone gives the same output as inside the batch
        with torch.no_grad():
            single, _ = net(depth[1:, 2:], speed[1:, 2:], quat[1:, 2:])
        torch.testing.assert_close(single[0, 0], out[1, 2], atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("name", ["convnet", "vit_lstm"])
def test_use_state_false_ignores_speed_and_attitude(name):
    depth, speed, quat = _inputs(1, 2)
    with torch.no_grad():
        blind = create_model(name, use_state=False).eval()
        a, _ = blind(depth, speed, quat)
        b, _ = blind(depth, speed * 2.0, torch.roll(quat, 1, dims=-1))
        torch.testing.assert_close(a, b)
        seeing = create_model(name, use_state=True).eval()
        seeing.load_state_dict(blind.state_dict())
        c, _ = seeing(depth, speed, quat)
    assert (a - c).abs().max() > 1e-6  # the state does reach the output when used


def test_state_vector_scales_speed_and_keeps_quaternion():
    speed = torch.tensor([[[5.0]]])
    quat = torch.tensor([[[0.5, 0.5, -0.5, 0.5]]])
    assert state_vector(speed, quat, True).tolist() == [[[0.5, 0.5, 0.5, -0.5, 0.5]]]
    assert state_vector(speed, quat, False).tolist() == [[[0.0] * 5]]


def test_min_pool_is_the_minimum_of_each_window():
    x = torch.tensor([[[[3.0, 1.0, 4.0], [1.0, 5.0, 9.0]]]])
    assert min_pool2d(x, 2, 1).tolist() == [[[[1.0, 1.0]]]]


@pytest.mark.parametrize(
    "args, match",
    [
        ((torch.zeros(1, 1, 1, 64, 64), torch.zeros(1, 1, 1), torch.zeros(1, 1, 4)), r"depth: expected shape \(B, T, 1, 60, 90\), got \(1, 1, 1, 64, 64\)"),  # noqa: E501
        ((torch.zeros(2, 1, 60, 90), torch.zeros(2, 1), torch.zeros(2, 4)), r"depth: expected shape \(B, T, 1, 60, 90\)"),  # noqa: E501
        ((torch.zeros(1, 2, 1, 60, 90), torch.zeros(1, 2), torch.zeros(1, 2, 4)), r"desired_speed: expected shape \(1, 2, 1\)"),  # noqa: E501
        ((torch.zeros(1, 2, 1, 60, 90), torch.zeros(1, 2, 1), torch.zeros(1, 2, 3)), r"quat: expected shape \(1, 2, 4\)"),  # noqa: E501
    ],
)
def test_wrong_input_shapes_name_the_expected_shape(args, match):
    net = create_model("convnet")
    with pytest.raises(VitflyError, match=match):
        net(*args)


def test_wrong_hidden_shape_names_the_expected_shape():
    net = create_model("lstmnet").eval()
    depth, speed, quat = _inputs(1, 1)
    bad = (torch.zeros(2, 1, 64), torch.zeros(2, 1, 64))
    with torch.no_grad(), pytest.raises(VitflyError, match=r"hidden h: expected shape \(2, 1, 395\)"):
        net(depth, speed, quat, bad)


def test_sn_linear_matches_torch_spectral_norm_in_training_and_eval():
    torch.manual_seed(0)
    ours = SNLinear(7, 5)
    reference = nn.utils.spectral_norm(nn.Linear(7, 5))
    reference.load_state_dict(ours.state_dict())
    x = torch.randn(4, 7)
    for _ in range(3):  # training: one power iteration per call, updating u and v
        torch.testing.assert_close(ours(x), reference(x))
    torch.testing.assert_close(ours.weight_u, reference.weight_u)
    torch.testing.assert_close(ours.weight_v, reference.weight_v)
    ours.eval()
    reference.eval()
    u_before = ours.weight_u.clone()
    with torch.no_grad():
        torch.testing.assert_close(ours(x), reference(x))
    assert torch.equal(ours.weight_u, u_before)  # eval never updates the stored vectors
    # the normalised weight has spectral norm ~1 after enough power iterations
    ours.train()
    for _ in range(50):
        ours(x)
    assert torch.linalg.matrix_norm(ours.weight.detach(), ord=2).item() == pytest.approx(1.0, abs=1e-4)


def test_sn_linear_inference_cache_follows_weight_changes():
    torch.manual_seed(1)
    layer = SNLinear(6, 4).eval()
    x = torch.randn(2, 6)
    with torch.inference_mode():
        first = layer(x)
    with torch.no_grad():
        layer.weight_orig.mul_(2.0)
        layer.weight_orig[0, 0] += 1.0  # changes sigma as well as the direction
        cached = layer(x)
    fresh = layer(x)  # grad-enabled path: always recomputed
    assert not torch.allclose(first, cached)
    torch.testing.assert_close(cached, fresh.detach())
    # the training path stays differentiable
    layer.train()
    layer(x).sum().backward()
    assert layer.weight_orig.grad is not None and layer.weight_orig.grad.abs().sum() > 0


@pytest.mark.parametrize("bias", [True, False])
def test_lstm_inference_matches_nn_lstm(bias):
    torch.manual_seed(2)
    lstm = nn.LSTM(11, 9, num_layers=3, bias=bias, batch_first=True, dropout=0.2).eval()
    x = torch.randn(3, 5, 11)
    h0 = (torch.randn(3, 3, 9), torch.randn(3, 3, 9))
    with torch.no_grad():
        ref_out, (ref_h, ref_c) = lstm(x, h0)
        out, (h, c) = lstm_inference(lstm, x, h0)
    torch.testing.assert_close(out, ref_out, atol=1e-6, rtol=0)
    torch.testing.assert_close(h, ref_h, atol=1e-6, rtol=0)
    torch.testing.assert_close(c, ref_c, atol=1e-6, rtol=0)


def test_long_sequences_at_inference_take_the_fused_lstm_on_a_gpu(monkeypatch):
    """Eval and no autograd: a GPU runs sequences of more than one step through ``nn.LSTM`` (the step-by-step
    ops launched ~9,000 kernels for one validation trajectory of ViT+LSTM), a control tick's single step and
    every CPU call through ``lstm_inference``. The fused branch, forced here on the CPU, gives nn.LSTM's result."""
    from vitfly.zoo import recurrent

    assert recurrent.fused_at_inference("cuda", 418) and recurrent.fused_at_inference("cuda", 2)
    assert not recurrent.fused_at_inference("cuda", 1) and not recurrent.fused_at_inference("cpu", 418)
    torch.manual_seed(3)
    lstm = nn.LSTM(11, 9, num_layers=3, batch_first=True).eval()
    x = torch.randn(2, 7, 11)
    with torch.no_grad():
        reference, _ = lstm(x)
        monkeypatch.setattr(recurrent, "fused_at_inference", lambda device_type, steps: steps > 1)
        monkeypatch.setattr(recurrent, "lstm_inference", lambda *args, **kwargs: pytest.fail("step by step"))
        out, _ = run_lstm(lstm, x, None)
    torch.testing.assert_close(out, reference, atol=1e-6, rtol=0)


def test_an_lstm_trains_under_cpu_bf16_autocast():
    """torch 2.15's oneDNN LSTM refuses bf16 on CPUs without AVX512-BF16 ("could not create a primitive
    descriptor"; an AVX2-only AMD EPYC): under CPU autocast the recurrence runs in fp32, so it trains, and gives
    exactly the fp32 result."""
    torch.manual_seed(4)
    lstm = nn.LSTM(10, 8, num_layers=2, batch_first=True).train()
    x = torch.randn(2, 16, 10, requires_grad=True)
    ref, _ = run_lstm(lstm, x, None)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out, (h, c) = run_lstm(lstm, x, None)
    assert out.dtype == h.dtype == torch.float32 and torch.equal(out, ref)
    out.sum().backward()
    assert x.grad is not None and lstm.weight_ih_l0.grad.abs().sum() > 0


@pytest.mark.parametrize("name", sorted(RECURRENT) + ["vit"])
def test_inference_fast_path_matches_autograd_path(name):
    # random init gives outputs of order 10-100 (unconverged spectral-norm vectors), hence rtol here;
    # tests/test_legacy.py holds both paths to 1e-5 absolute on the original trained weights
    torch.manual_seed(3)
    net = create_model(name).eval()
    depth, speed, quat = _inputs(2, 4, seed=5)
    slow, slow_h = net(depth, speed, quat)  # grad enabled: nn.LSTM + freshly normalised SN weights
    with torch.inference_mode():
        fast, fast_h = net(depth, speed, quat)
    torch.testing.assert_close(fast, slow.detach(), atol=1e-5, rtol=1e-4)
    if slow_h is not None:
        torch.testing.assert_close(fast_h[1], slow_h[1].detach(), atol=1e-4, rtol=0)


def test_training_mode_is_differentiable_and_uses_dropout():
    net = create_model("vit_lstm").train()
    depth, speed, quat = _inputs(2, 3)
    out, _ = net(depth, speed, quat)
    out.pow(2).mean().backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None for g in grads)
    assert net.encoder_blocks[0].patchMerge.cn1.weight.grad.abs().sum() > 0


def test_register_model_adds_an_architecture():
    @register_model(name="_test_tiny")
    def _tiny(use_state: bool = True, width: int = 4):
        return nn.Linear(width, 1)

    assert "_test_tiny" in list_models()
    assert create_model("_test_tiny", width=6).in_features == 6


@pytest.mark.parametrize("name", ["convnet", "vit_lstm"])
def test_checkpoint_round_trip(tmp_path, name):
    net = create_model(name, use_state=False).eval()
    path = tmp_path / f"{name}.ckpt"
    save_checkpoint(net, name, use_state=False, path=path, metadata={"note": "round trip"})
    raw = torch.load(path, weights_only=True)
    assert raw["hyper_parameters"] == {"model": name, "use_state": False, "model_kwargs": {}}
    assert all(k.startswith("net.") for k in raw["state_dict"])
    assert "pytorch-lightning_version" in raw
    loaded = load_network(path)
    assert not loaded.training and loaded.use_state is False
    depth, speed, quat = _inputs(1, 2)
    with torch.no_grad():
        torch.testing.assert_close(loaded(depth, speed, quat)[0], net(depth, speed, quat)[0])
    assert [p.name for p in tmp_path.iterdir()] == [f"{name}.ckpt"]  # no temp files left


def test_load_network_errors_are_one_line(tmp_path):
    with pytest.raises(VitflyError, match="no such file"):
        load_network(tmp_path / "missing.ckpt")
    net = create_model("convnet")
    good = tmp_path / "good.ckpt"
    save_checkpoint(net, "convnet", True, good)
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(good.read_bytes()[:500])
    with pytest.raises(VitflyError, match="truncated.ckpt: not a readable PyTorch checkpoint"):
        load_network(truncated)
    lie = torch.load(good, weights_only=True)
    lie["hyper_parameters"]["model"] = "vit"
    liar = tmp_path / "liar.ckpt"
    torch.save(lie, liar)
    with pytest.raises(VitflyError, match=r"does not fit architecture 'vit'.*looks like a 'convnet' checkpoint"):
        load_network(liar)
    other = copy.deepcopy(lie)
    other["hyper_parameters"]["model"] = "nope"
    torch.save(other, liar)
    with pytest.raises(VitflyError, match="hyper_parameters.model 'nope' is not a known model"):
        load_network(liar)
