"""The int8 fast path of the ViTs (fused mix-FFN as calibrated int8 convolutions), bound buffers in the flight
loop, and interleaved timing."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch
import torch.nn.functional as F

from vitfly.deploy.onnx import OnnxPolicyRunner, export_onnx_bytes
from vitfly.deploy.optimize import FusedConvMixFFN
from vitfly.deploy.quantize import _uint8_params, calibrate_ranges
from vitfly.eval.agreement import (
    COMMAND_TOLERANCE_MPS,
    calibration_depth,
    compare_commands,
    record_flights,
    replay_commands,
)
from vitfly.eval.latency import CLOCKS, time_interleaved
from vitfly.eval.learned_policy import LearnedPolicy
from vitfly.zoo import create_model
from vitfly.zoo.mix_transformer import MixFFN

torch.set_num_threads(1)


def _mix_ffn_by_hand(ffn: MixFFN, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """The mix-FFN written out from its definition (MODELS.md): Linear, grouped 3x3 conv, GELU, Linear."""
    n, length, c = x.shape
    y = x @ ffn.mlp1.weight.T + ffn.mlp1.bias  # (N, L, C*E)
    grid = y.transpose(1, 2).reshape(n, -1, h, w)  # zero padding applies to mlp1's output, bias included
    z = F.conv2d(grid, ffn.depthwise.weight, ffn.depthwise.bias, padding=1, groups=c)
    z = F.gelu(z).flatten(2).transpose(1, 2)
    return z @ ffn.mlp2.weight.T + ffn.mlp2.bias


@pytest.mark.parametrize(("channels", "h", "w"), [(4, 5, 7), (8, 3, 4)])
def test_fused_mix_ffn_is_the_same_function(channels, h, w):
    torch.manual_seed(1)
    ffn = MixFFN(channels, expansion=8).eval()
    with torch.no_grad():  # large biases: mlp1's bias through the zero padding is what the border map carries
        ffn.mlp1.bias.uniform_(-2.0, 2.0)
        ffn.depthwise.bias.uniform_(-1.0, 1.0)
    fused = FusedConvMixFFN(ffn).eval()
    x = torch.randn(2, h * w, channels)
    with torch.no_grad():
        torch.testing.assert_close(fused(x, h, w), _mix_ffn_by_hand(ffn, x, h, w), atol=2e-5, rtol=0)
    # one dense convolution over the tokens, a channel of ones carrying mlp1's bias, three zero channels
    assert fused.fused_conv.weight.shape == (channels * 8, channels + 4, 3, 3) and fused.fused_conv.groups == 1
    assert torch.all(fused.fused_conv.weight[:, channels + 1 :] == 0)


def test_sigmoid_gelu_mix_ffn_by_hand():
    torch.manual_seed(2)
    ffn = MixFFN(4, expansion=8).eval()
    quick = FusedConvMixFFN(ffn, gelu="quick").eval()
    x = torch.randn(1, 5 * 6, 4)
    with torch.no_grad():
        y = x @ ffn.mlp1.weight.T + ffn.mlp1.bias
        z = F.conv2d(y.transpose(1, 2).reshape(1, -1, 5, 6), ffn.depthwise.weight, ffn.depthwise.bias, padding=1,
                     groups=4).flatten(2).transpose(1, 2)  # fmt: skip
        expected = (z * torch.sigmoid(1.702 * z)) @ ffn.mlp2.weight.T + ffn.mlp2.bias
        torch.testing.assert_close(quick(x, 5, 6), expected, atol=2e-5, rtol=0)
        # and it is an approximation: not the exact mix-FFN
        assert (quick(x, 5, 6) - _mix_ffn_by_hand(ffn, x, 5, 6)).abs().max() > 1e-4


def test_uint8_quantisation_parameters_by_hand():
    # [-1, 3] without margin: scale 4 / 255, zero point round(1 / (4 / 255)) = round(63.75) = 64
    scale, zero = _uint8_params(-1.0, 3.0, margin=1.0)
    assert scale == pytest.approx(4.0 / 255.0) and zero == 64
    # a range not holding 0 is extended to it; the margin widens both ends about 0
    scale, zero = _uint8_params(0.5, 2.0, margin=1.25)
    assert scale == pytest.approx(2.5 / 255.0) and zero == 0


def test_calibration_ranges_are_the_extremes_over_the_frames():
    torch.manual_seed(0)
    net = create_model("convnet").eval()
    data = export_onnx_bytes(net, batch_size=1)
    # the network's input itself as the observed tensor: its range over the frames is known exactly
    frames = np.stack([np.full((60, 90), 0.25, np.float32), np.full((60, 90), 0.75, np.float32)])
    frames[1, 3, 4] = 0.9
    ranges = calibrate_ranges(data, frames, ["depth"])
    assert ranges["depth"] == pytest.approx((0.0, 0.9))  # the low end always holds 0


@pytest.fixture(scope="module")
def flights():
    # recorded-style inputs: two short expert flights (3 and 2 s at 30 Hz), other scenes than the calibration's
    return record_flights("trees", seeds=(2,), speeds_mps=(7.0,), timeout_s=3.0) + record_flights(
        "spheres", seeds=(3,), speeds_mps=(4.0,), timeout_s=2.0
    )


@pytest.fixture(scope="module")
def calibration():
    frames = calibration_depth(seconds=2.0)
    assert frames.shape[1:] == (60, 90) and 0.0 <= frames.min() and frames.max() <= 1.0 and len(frames) > 50
    return frames


@pytest.mark.parametrize("name", ["vit", "vit_lstm"])
def test_int8_vit_convolutions_fly_the_float_commands(flights, calibration, name, monkeypatch):
    # the ViT's sigmoid-GELU uint8 chain, off by default (trained weights), is still built when asked for
    monkeypatch.setattr("vitfly.deploy.optimize.QUICK_GELU_STAGES", {"vit": (0, 1)})
    torch.manual_seed(0)
    net = create_model(name).eval()
    data = export_onnx_bytes(net, precision="int8", calibration_depth=calibration)
    model = onnx.load_from_string(data)
    ops = [n.op_type for n in model.graph.node]
    meta = {p.key: p.value for p in model.metadata_props}
    # every mix-FFN (2 stages x 2 layers) is one int8 convolution; the ViT's stay uint8 through the sigmoid
    # GELU and mlp2 (a second int8 convolution each); no float copy of them is left
    quick = name == "vit"
    convs = ops.count("QLinearConv")
    assert convs == (8 if quick else 4) and meta["vitfly.int8_convolutions"] == str(convs)
    assert ops.count("QLinearSigmoid") == ops.count("QLinearMul") == (4 if quick else 0)
    assert not any(i.name.endswith(("fused_conv.weight", "fused_mlp2.weight")) for i in model.graph.initializer)
    reference = replay_commands(LearnedPolicy(net), flights)
    fast = LearnedPolicy(net, step_fn=OnnxPolicyRunner(data))
    agreement = compare_commands(reference, replay_commands(fast, flights))
    assert agreement.ticks == 150
    assert agreement.within(COMMAND_TOLERANCE_MPS["onnxruntime-int8"]), agreement
    assert agreement.max_abs_mps > 1e-4  # int8 computes a different function: this is not the float path


def _ticks(n_envs: int, n_ticks: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    ticks = []
    for t in range(n_ticks):
        quat = np.tile([1.0, 0.0, 0.0, 0.0], (n_envs, 1)) + 0.05 * rng.standard_normal((n_envs, 4))
        quat /= np.linalg.norm(quat, axis=1)[:, None]
        obs = {"depth": rng.random((n_envs, 60, 90), dtype=np.float32), "desired_speed": np.linspace(3.0, 7.0, n_envs)}
        obs.update(quat=quat, position=np.tile([1.0 + t, 0.0, 3.5], (n_envs, 1)), active=np.ones(n_envs, bool))
        ticks.append(obs)
    return ticks


@pytest.mark.parametrize("name", ["convnet", "lstmnet"])
def test_bound_buffers_give_the_unbound_commands(name):
    torch.manual_seed(0)
    net = create_model(name).eval()
    runner = OnnxPolicyRunner(net)
    bound = LearnedPolicy(net, step_fn=runner)  # the runner has bind(): buffers bound at reset
    unbound = LearnedPolicy(net, step_fn=lambda *args: runner(*args))  # the same session, plain calls
    ticks = _ticks(3, 6)
    ticks[3]["active"] = np.array([True, False, True])  # one env done for a tick: the general path
    for policy in (bound, unbound):
        policy.reset(3)
    assert bound._bound is not None and unbound._bound is None
    for t, obs in enumerate(ticks):
        if t == 4:  # env 1 starts a new trial: its recurrent state is zeroed, the others carry on
            bound.reset_envs([1])
            unbound.reset_envs([1])
        np.testing.assert_allclose(bound(obs), unbound(obs), rtol=0, atol=1e-6)
    bound.reset(2)  # another batch size binds new buffers
    np.testing.assert_allclose(bound(_ticks(2, 1)[0]), unbound_commands(net, runner, _ticks(2, 1)[0]), atol=1e-6)


def unbound_commands(net, runner, obs):
    policy = LearnedPolicy(net, step_fn=lambda *args: runner(*args))
    policy.reset(len(obs["depth"]))
    return policy(obs)


def test_interleaved_timing_takes_turns_and_times_both_clocks(monkeypatch):
    # Clocks the steps move by hand, so the test asserts exact times instead of racing a shared machine:
    # step "a" computes for 1 ms, step "b" waits 2 ms and computes for 0.5 ms.
    now = {"wall": 0.0, "cpu": 0.0}
    monkeypatch.setitem(CLOCKS, "wall", lambda: now["wall"])
    monkeypatch.setitem(CLOCKS, "cpu", lambda: now["cpu"])
    calls = []

    def step(name, wall_s, cpu_s):
        calls.append(name)
        now["wall"] += wall_s
        now["cpu"] += cpu_s

    steps = {"a": lambda: step("a", 1e-3, 1e-3), "b": lambda: step("b", 2.5e-3, 0.5e-3)}
    times = time_interleaved(steps, calls=5, block=2, warmup=1)
    # warm-up once each, then blocks of 2 with the order reversed every other round: ab, ba, ab
    assert "".join(calls) == "ab" + "aabb" + "bbaa" + "ab"
    np.testing.assert_allclose(times["a"]["wall"], [1.0] * 5)
    np.testing.assert_allclose(times["a"]["cpu"], [1.0] * 5)
    np.testing.assert_allclose(times["b"]["wall"], [2.5] * 5)
    np.testing.assert_allclose(times["b"]["cpu"], [0.5] * 5)
