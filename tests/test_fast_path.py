"""The fast inference paths: folded ConvNet, int8 quantisation, and command agreement over recorded flights."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch

from vitfly.deploy.onnx import OnnxPolicyRunner, export_onnx_bytes
from vitfly.deploy.optimize import inference_copy
from vitfly.deploy.quantize import _gemms_as_matmuls, int8_saturates, quantize_int8
from vitfly.eval.agreement import (
    COMMAND_TOLERANCE_MPS,
    compare_commands,
    record_flights,
    replay_commands,
)
from vitfly.eval.learned_policy import LearnedPolicy
from vitfly.zoo import create_model

torch.set_num_threads(1)


def _sequence(b, t, seed=0):
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(b, t, 1, 60, 90, generator=g)
    speed = 3.0 + 4.0 * torch.rand(b, t, 1, generator=g)
    quat = torch.nn.functional.normalize(torch.randn(b, t, 4, generator=g), dim=-1)
    return depth, speed, quat


def _convnet_with_bn(weight_low: float):
    torch.manual_seed(3)
    net = create_model("convnet").eval()
    with torch.no_grad():  # batch-norm statistics as after training (the defaults fold trivially)
        net.bn1.weight.uniform_(weight_low, 2.0)
        net.bn1.bias.normal_()
        net.bn1.running_mean.uniform_(0.0, 1.0)
        net.bn1.running_var.uniform_(0.5, 2.0)
    return net


@pytest.mark.parametrize("weight_low", [0.5, -1.0])
def test_folded_convnet_is_the_same_function(weight_low):
    # positive batch-norm scales fold (BN, min-pool, average pool, speed scale into the layers); a negative
    # scale keeps the generic inference copy. Either way: the eager network's outputs within float rounding.
    net = _convnet_with_bn(weight_low)
    fast = inference_copy(net)
    assert (type(fast).__name__ == "_FoldedConvNet") == (weight_low > 0)
    depth, speed, quat = _sequence(2, 3, seed=1)
    with torch.inference_mode():
        torch.testing.assert_close(fast(depth, speed, quat)[0], net(depth, speed, quat)[0], atol=1e-5, rtol=0)


def test_gemm_rewrite_keeps_the_function_and_int8_quantises_the_large_products(monkeypatch):
    assert int(_int8_meta(quantize_int8(export_onnx_bytes(_convnet_with_bn(0.5), batch_size=1)))) == 0
    # the ConvNet's products stay float32 by default (FLOAT32_LARGEST, for its trained weights); without:
    monkeypatch.setattr("vitfly.deploy.quantize.FLOAT32_LARGEST", {})
    net = _convnet_with_bn(0.5)
    data = export_onnx_bytes(net, batch_size=1)  # the folded ConvNet's 2-D head exports as Gemm
    model = onnx.load_from_string(data)
    assert sum(n.op_type == "Gemm" for n in model.graph.node) == 5  # fc0's image and state columns apart
    _gemms_as_matmuls(model, 16_384)  # fc0 (1260 x 256) and fc1 (256 x 64 = 16,384) become MatMul (+ Add)
    assert [n.op_type for n in model.graph.node].count("Gemm") == 3
    depth, speed, quat = (x.numpy() for x in _sequence(1, 1, seed=2))
    before = OnnxPolicyRunner(data)(depth, speed, quat)[0]
    after = OnnxPolicyRunner(model.SerializeToString())(depth, speed, quat)[0]
    np.testing.assert_allclose(after, before, atol=1e-6)

    quantised = onnx.load_from_string(quantize_int8(data))
    ops = [n.op_type for n in quantised.graph.node]
    assert "DynamicQuantizeLinear" in ops and ops.count("MatMulInteger") == 2
    meta = {p.key: p.value for p in quantised.metadata_props}
    assert meta["vitfly.precision"] == "int8" and meta["vitfly.model"] == "convnet"
    runner = OnnxPolicyRunner(quantised.SerializeToString())
    assert runner.precision == "int8"
    with torch.inference_mode():
        ref = net(*_sequence(1, 1, seed=2))[0].numpy()
    assert np.abs(runner(depth, speed, quat)[0] - ref).max() < 0.05 * max(1.0, np.abs(ref).max())


def _int8_meta(data: bytes) -> str:
    return {p.key: p.value for p in onnx.load_from_string(data).metadata_props}["vitfly.int8_products"]


def test_compare_commands_by_hand():
    ref = [np.array([[5.0, 0.0, 0.0], [0.0, 3.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])]
    cand = [np.array([[4.9, 0.1, 0.0], [0.0, 3.0, 0.0]]), np.array([[1.0, 0.0, 0.02]])]
    a = compare_commands(ref, cand)
    assert (a.flights, a.ticks) == (2, 3)
    assert a.max_abs_mps == pytest.approx(0.1)
    assert a.mean_abs_mps == pytest.approx((0.1 + 0.0 + 0.02) / 3)
    # largest angle: between (5, 0, 0) and (4.9, 0.1, 0): atan(0.1 / 4.9) = 1.1691 deg
    assert a.max_angle_deg == pytest.approx(1.1691, abs=1e-4)
    assert a.within(0.1) and not a.within(0.09)


@pytest.fixture(scope="module")
def flights():
    # two short expert flights of different lengths (3 and 2 s at 30 Hz) through one spheres scene
    long_ = record_flights("spheres", seeds=(0,), speeds_mps=(7.0,), timeout_s=3.0)
    short = record_flights("spheres", seeds=(0,), speeds_mps=(4.0,), timeout_s=2.0)
    return long_ + short


def test_replay_batches_flights_as_the_rollout_would(flights):
    assert [len(f) for f in flights] == [90, 60] and flights[0].depth.shape == (90, 60, 90)
    torch.manual_seed(0)
    net = create_model("lstmnet").eval()
    together = replay_commands(LearnedPolicy(net), flights)
    alone = replay_commands(LearnedPolicy(net), flights[1:])
    # the shorter flight, batched with a longer one, gets the commands it gets alone (state per flight)
    np.testing.assert_allclose(together[1], alone[0], atol=1e-5)
    assert [c.shape for c in together] == [(90, 3), (60, 3)]
    # the take-off ramp applies at the recorded positions: vx = max(1, x / 2 * speed) while x < 2 m
    x = flights[0].position_m[:, 0]
    ramp = x < 2.0
    assert ramp[0] and together[0][ramp, 0] == pytest.approx(np.maximum(1.0, x[ramp] / 2.0 * 7.0))


@pytest.mark.parametrize(("name", "int8_products"), [("convnet", 0), ("vit_lstm", 6)])
def test_fast_paths_fly_the_eager_commands(flights, name, int8_products):
    torch.manual_seed(0)
    net = create_model(name).eval()
    reference = replay_commands(LearnedPolicy(net), flights)
    for backend, precision in (("onnxruntime", "fp32"), ("onnxruntime-int8", "int8")):
        runner = OnnxPolicyRunner(net, precision=precision)
        if precision == "int8":  # the ConvNet's stay float32 (FLOAT32_LARGEST), the ViT+LSTM's are int8, but for
            # its largest on a CPU without VNNI (FLOAT32_LARGEST_WITHOUT_VNNI)
            meta = runner.session.get_modelmeta().custom_metadata_map
            saturates = int8_saturates()
            assert meta["vitfly.int8_reduce_range"] == str(saturates)
            assert int(meta["vitfly.int8_products"]) == int8_products - (saturates and name == "vit_lstm")
        fast = LearnedPolicy(net, step_fn=runner)
        agreement = compare_commands(reference, replay_commands(fast, flights))
        assert agreement.ticks == 150
        assert agreement.within(COMMAND_TOLERANCE_MPS[backend]), (backend, agreement)


def test_int8_latency_backend_checks_then_times(tmp_path, capsys):
    from vitfly.cli import main
    from vitfly.eval.latency import benchmark_model

    result = benchmark_model("convnet", backend="onnxruntime-int8", iters=5, warmup=1)
    assert result.backend == "onnxruntime-int8" and 0 < result.max_abs_diff < 0.05 and result.median_ms > 0
    out = tmp_path / "convnet_int8.onnx"
    assert main(["export", "convnet", "--out", str(out), "--batch-size", "1", "--precision", "int8"]) == 0
    assert "int8" in capsys.readouterr().out
    assert OnnxPolicyRunner(out).precision == "int8"


def test_int8_weights_take_7_bits_where_the_cpu_products_saturate(monkeypatch, tmp_path):
    """An x86 CPU whose flags name no VNNI unit sums uint8 x int8 pairs in 16 bits (ONNX Runtime's AVX2 kernels):
    255 x 127 x 2 = 64,770 overflows 32,767, 255 x 63 x 2 = 32,130 does not, so the weights take 7 bits there."""
    from vitfly.deploy import quantize

    cpuinfo = tmp_path / "cpuinfo"
    real_path = quantize.Path
    monkeypatch.setattr(quantize, "Path", lambda p: real_path(cpuinfo) if p == "/proc/cpuinfo" else real_path(p))
    monkeypatch.setattr("platform.machine", lambda: "x86_64")
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 fma\n")
    assert quantize.int8_saturates()
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_vnni\n")
    assert not quantize.int8_saturates()
    monkeypatch.setattr("platform.machine", lambda: "aarch64")
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2\n")
    assert not quantize.int8_saturates()  # Arm's int8 dot products do not saturate this way
