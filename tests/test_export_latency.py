"""ONNX export, the ONNX Runtime runner, inference rewrites and the latency benchmark."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from vitfly.cli import main
from vitfly.deploy.onnx import OnnxPolicyRunner, example_inputs, export_onnx, export_onnx_bytes
from vitfly.deploy.optimize import inference_copy, merge_conv_groups
from vitfly.errors import VitflyError
from vitfly.eval.latency import PAPER_LATENCY_MS, benchmark_model, latency_table, time_calls
from vitfly.zoo import create_model, load_legacy_checkpoint

torch.set_num_threads(1)

FIXTURES = Path(
    os.environ.get("VITFLY_LEGACY_FIXTURES", Path(__file__).resolve().parents[1] / ".." / "shared/fixtures/legacy")
)
needs_fixtures = pytest.mark.skipif(
    not (FIXTURES / "vit_lstm.pth").exists(),
    reason=f"original-checkpoint fixtures not found in {FIXTURES} (set VITFLY_LEGACY_FIXTURES)",
)


def _sequence(b: int, t: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(b, t, 1, 60, 90, generator=g)
    speed = 3.0 + 4.0 * torch.rand(b, t, 1, generator=g)
    quat = torch.nn.functional.normalize(torch.randn(b, t, 4, generator=g), dim=-1)
    return depth, speed, quat


@pytest.mark.parametrize("name", ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18"])
def test_inference_copy_matches_eager(name):
    torch.manual_seed(0)
    net = create_model(name).eval()
    fast = inference_copy(net)
    depth, speed, quat = _sequence(2, 3)
    with torch.inference_mode():
        ref, ref_hidden = net(depth, speed, quat)
        out, hidden = fast(depth, speed, quat)
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=0)
    if ref_hidden is not None:
        torch.testing.assert_close(hidden[1], ref_hidden[1], atol=1e-5, rtol=0)
    assert all(p.requires_grad for p in net.parameters())  # the original is untouched


@needs_fixtures
@pytest.mark.parametrize("name", ["vit", "vit_lstm"])
def test_inference_copy_reproduces_the_original_outputs(name):
    io = torch.load(FIXTURES / f"{name}_io.pt", weights_only=True)
    fast = inference_copy(load_legacy_checkpoint(name, FIXTURES / f"{name}.pth"))
    with torch.inference_mode():
        out, hidden = fast(io["depth"][None], io["desired_speed"][None], io["quat"][None])
    torch.testing.assert_close(out[0], io["velocity"], atol=1e-5, rtol=0)
    if "c_n" in io:
        torch.testing.assert_close(hidden[1][:, 0], io["c_n"], atol=1e-5, rtol=0)


def test_merged_group_convolution_is_the_same_convolution():
    torch.manual_seed(1)
    conv = torch.nn.Conv2d(64, 64, 3, padding=1, groups=8).eval()  # 8 channels per group
    merged = merge_conv_groups(conv)
    assert merged.groups == 4 and merged.weight.shape == (64, 16, 3, 3)
    x = torch.randn(2, 64, 7, 9)
    torch.testing.assert_close(merged(x), conv(x), atol=1e-5, rtol=0)
    dense = torch.nn.Conv2d(16, 16, 3)
    assert merge_conv_groups(dense) is dense


@pytest.fixture(scope="module")
def lstmnet_onnx(tmp_path_factory) -> tuple[Path, torch.nn.Module]:
    torch.manual_seed(2)
    net = create_model("lstmnet").eval()
    path = tmp_path_factory.mktemp("onnx") / "lstmnet.onnx"
    diff = export_onnx(net, path)
    assert diff is not None and diff < 1e-4
    return path, net


def test_exported_recurrent_graph_signature(lstmnet_onnx):
    path, _ = lstmnet_onnx
    model = onnx.load(path)
    inputs = {i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim] for i in model.graph.input}
    outputs = [o.name for o in model.graph.output]
    assert list(inputs) == ["depth", "desired_speed", "quat", "h0", "c0"]
    assert inputs["depth"][1:] == [1, 1, 60, 90] and isinstance(inputs["depth"][0], str)  # dynamic batch
    assert inputs["h0"][0] == 2 and inputs["h0"][2] == 395
    assert outputs == ["velocity", "hn", "cn"]
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["vitfly.model"] == "lstmnet" and meta["vitfly.recurrent"] == "True"


def test_runner_carries_state_over_batches_and_sequences(lstmnet_onnx):
    path, net = lstmnet_onnx
    runner = OnnxPolicyRunner(path)
    depth, speed, quat = _sequence(3, 4, seed=3)
    with torch.inference_mode():
        ref, (h_ref, c_ref) = net(depth, speed, quat)
    out, (h, c) = runner(depth, speed, quat)  # torch in -> torch out, four ticks with the state carried
    assert isinstance(out, torch.Tensor) and out.shape == (3, 4, 3)
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(c, c_ref, atol=1e-5, rtol=0)
    out_np, hidden_np = runner(depth[:1, :1].numpy(), speed[:1, :1].numpy(), quat[:1, :1].numpy())
    assert isinstance(out_np, np.ndarray) and hidden_np[0].shape == (2, 1, 395)
    with pytest.raises(VitflyError, match=r"hidden: expected \(h, c\), each of shape \(2, 3, 395\)"):
        runner(depth, speed, quat, (h[:, :1], c[:, :1]))
    with pytest.raises(VitflyError, match=r"depth: expected shape \(B, T, 1, 60, 90\), got \(3, 4, 1, 30, 45\)"):
        runner(torch.zeros(3, 4, 1, 30, 45), speed, quat)


def test_runner_refuses_an_export_that_differs_from_eager(lstmnet_onnx):
    path, _ = lstmnet_onnx
    other = create_model("lstmnet").eval()  # same architecture, other weights
    with pytest.raises(VitflyError, match="differs from eager by .*refusing"):
        OnnxPolicyRunner(path).check_against(other)


def test_runner_rejects_foreign_files(tmp_path):
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(VitflyError, match="junk.onnx: ONNX Runtime cannot load it"):
        OnnxPolicyRunner(tmp_path / "junk.onnx")
    with pytest.raises(VitflyError, match="no such ONNX file"):
        OnnxPolicyRunner(tmp_path / "missing.onnx")


def test_export_command_from_registry_name_and_checkpoint(tmp_path, capsys):
    out = tmp_path / "convnet.onnx"
    assert main(["export", "convnet", "--format", "onnx", "--out", str(out), "--batch-size", "1"]) == 0
    captured = capsys.readouterr()
    assert "RANDOM-INITIALISED" in captured.err and f"wrote {out}: convnet" in captured.out
    runner = OnnxPolicyRunner(out)
    assert not runner.is_recurrent and runner.model_name == "convnet"
    velocity, hidden = runner(*example_inputs(create_model("convnet"), 1))
    assert velocity.shape == (1, 1, 3) and hidden is None
    assert main(["export", "convnet", "--out", str(out)]) == 2  # exists, no --force
    assert main(["export", "transformer", "--out", str(tmp_path / "x.onnx")]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and "neither an existing checkpoint file nor a registry name" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["convnet.onnx"]


@needs_fixtures
def test_exported_original_checkpoint_reproduces_the_stored_outputs(tmp_path):
    out = tmp_path / "vit_lstm.onnx"
    assert main(["export", str(FIXTURES / "vit_lstm.pth"), "--arch", "vit_lstm", "--out", str(out)]) == 0
    io = torch.load(FIXTURES / "vit_lstm_io.pt", weights_only=True)
    velocity, (h, c) = OnnxPolicyRunner(out)(io["depth"][None], io["desired_speed"][None], io["quat"][None])
    torch.testing.assert_close(velocity[0], io["velocity"], atol=1e-5, rtol=0)
    torch.testing.assert_close(c[:, 0], io["c_n"], atol=1e-5, rtol=0)


def test_time_calls_counts_and_validates():
    calls = []
    times = time_calls(lambda: calls.append(1), iters=7, warmup=3)
    assert len(calls) == 10 and times.shape == (7,) and (times >= 0).all()
    with pytest.raises(VitflyError, match="--iters must be at least 1"):
        time_calls(lambda: None, iters=0, warmup=0)


class _ExportsDifferently(torch.nn.Module):
    """A real network whose traced graph adds 1 to the output: the check must catch it."""

    model_name = "convnet"
    is_recurrent = False

    def __init__(self) -> None:
        super().__init__()
        self.net = create_model("convnet").eval()

    def forward(self, depth, desired_speed, quat, hidden=None):
        out, _ = self.net(depth, desired_speed, quat)
        return (out + 1.0 if torch.compiler.is_exporting() else out), None


def test_fast_backend_refuses_to_time_when_outputs_differ():
    with pytest.raises(VitflyError, match="refusing"):
        benchmark_model("convnet", backend="onnxruntime", iters=2, warmup=0, net=_ExportsDifferently())


def test_benchmark_latency_command_writes_the_table_and_json(tmp_path, capsys):
    out = tmp_path / "latency.json"
    argv = ["benchmark-latency", "--models", "convnet", "vit_lstm", "--iters", "5", "--warmup", "1"]
    assert main([*argv, "--device", "cpu", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "convnet" in table and "235,269" in table and "n/a" in table and "9.2" in table
    results = json.loads(out.read_text())
    assert [r["model"] for r in results] == ["convnet", "vit_lstm"]
    for r in results:
        assert {"model", "params", "backend", "device", "threads", "median_ms", "p90_ms"} <= set(r)
        assert r["backend"] == "eager" and r["device"] == "cpu" and r["threads"] == 1
        assert 0 < r["median_ms"] <= r["p90_ms"]
    assert results[1]["params"] == 3_563_663 and results[1]["paper_cpu_ms"] == PAPER_LATENCY_MS["vit_lstm"][0]
    assert main(["benchmark-latency", "--models", "vitt"]) == 2
    assert "unknown model(s) vitt" in capsys.readouterr().err


def test_benchmark_onnxruntime_backend_checks_then_times():
    result = benchmark_model("convnet", backend="onnxruntime", iters=5, warmup=1)
    assert result.backend == "onnxruntime" and result.max_abs_diff is not None and result.max_abs_diff < 1e-4
    assert result.median_ms > 0 and result.params == 235_269
    table = latency_table([result])
    assert table.row_count == 1


def test_export_bytes_fixed_batch_has_static_shapes():
    model = onnx.load_from_string(export_onnx_bytes(create_model("convnet"), batch_size=1))
    depth = model.graph.input[0].type.tensor_type.shape.dim
    assert [d.dim_value for d in depth] == [1, 1, 1, 60, 90]


def test_bound_step_matches_the_plain_runner(lstmnet_onnx):
    path, _ = lstmnet_onnx
    runner = OnnxPolicyRunner(path)
    bound = runner.bind(2)
    depth, speed, quat = _sequence(2, 3, seed=4)
    expected, _ = runner(depth, speed, quat)
    for t in range(3):
        np.copyto(bound.depth, depth[:, t : t + 1].numpy())
        np.copyto(bound.desired_speed, speed[:, t : t + 1].numpy())
        np.copyto(bound.quat, quat[:, t : t + 1].numpy())
        np.testing.assert_allclose(bound(), expected[:, t : t + 1].numpy(), atol=1e-6)
    assert np.abs(bound.hidden[0]).sum() > 0
    bound.reset()
    assert np.abs(bound.hidden[0]).sum() == 0


def test_unoptimised_export_of_a_spectral_norm_lstm_network():
    torch.manual_seed(5)
    net = create_model("lstmnet").eval()  # SN layers and nn.LSTM traced as written
    runner = OnnxPolicyRunner(export_onnx_bytes(net, optimize=False))
    assert runner.check_against(net) < 1e-5
