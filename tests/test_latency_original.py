"""Timing the original project's networks from a checkout (``--original-repo``).

These tests exercise the *loading and calling mechanism* with a tiny stand-in checkout written to tmp_path:
``models/model.py`` defines the original's five class names and imports a sibling ``ViTsubmodules.py`` by
bare name, as the original does. The stand-in networks are not the original's (nothing of the original is in
vitfly or its tests); they record how they are called so the tests can check the original deployment's
calling convention (``envtest/ros/user_code.py``): a list [image (1, 1, 60, 90), desired velocity (1, 1),
quaternion (1, 4)] plus, for the LSTM classes, the state (h, c) of shape (layers, hidden), zeros first and
then what the previous call returned.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import torch
from helpers import load_benchmark

from vitfly.errors import VitflyError
from vitfly.eval.latency import benchmark_original, prepare_original
from vitfly.eval.original_networks import load_original_models, original_network, original_step

SUBMODULES = '''
import torch.nn as nn

class Head(nn.Linear):
    def __init__(self):
        super().__init__(5, 3)
'''

MODEL = '''
import torch
import torch.nn as nn
from ViTsubmodules import *

class _Stateless(nn.Module):
    def __init__(self):
        super().__init__()
        self.head = Head()
        self.calls = []

    def forward(self, X):
        self.calls.append([tuple(x.shape) for x in X])
        return self.head(torch.cat((X[1] * 0.1, X[2]), dim=1)), None

class _Recurrent(_Stateless):
    def forward(self, X):
        self.calls.append([tuple(x.shape) for x in X[:3]])
        self.seen = X[3] if len(X) > 3 else None
        h, c = X[3]
        return self.head(torch.cat((X[1] * 0.1, X[2]), dim=1)), (h + 1, c + 2)

class ConvNet(_Stateless): pass
class ViT(_Stateless): pass
class LSTMNet(_Recurrent): pass
class UNetConvLSTMNet(_Recurrent): pass
class LSTMNetVIT(_Recurrent): pass
'''


@pytest.fixture
def stand_in(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    (models / "ViTsubmodules.py").write_text(SUBMODULES)
    (models / "model.py").write_text(MODEL)
    return tmp_path


def test_loads_the_checkout_and_leaves_no_bare_module_behind(stand_in):
    module = load_original_models(stand_in)
    assert {"ConvNet", "LSTMNet", "UNetConvLSTMNet", "ViT", "LSTMNetVIT"} <= set(vars(module))
    assert "ViTsubmodules" not in sys.modules and str(stand_in / "models") not in sys.path
    net = original_network(module, "vit")
    assert not net.training


def test_called_as_the_original_deployment_calls_it(stand_in):
    module = load_original_models(stand_in)
    depth, quat = torch.rand(60, 90), torch.tensor([1.0, 0.0, 0.0, 0.0])
    net = original_network(module, "lstmnet")
    step = original_step(net, "lstmnet", depth, 5.0, quat)
    step()
    # first call: user_code's zero state, (num_layers, hidden_size) = (2, 395) for LSTMNet
    assert net.calls[0] == [(1, 1, 60, 90), (1, 1), (1, 4)]
    assert [tuple(x.shape) for x in net.seen] == [(2, 395), (2, 395)] and float(net.seen[0].abs().sum()) == 0
    step()
    step()
    # the state is carried: the stand-in adds 1 to h and 2 to c per call, so the third call sees 2 and 4
    assert float(net.seen[0].mean()) == 2.0 and float(net.seen[1].mean()) == 4.0
    vit = original_network(module, "vit_lstm")
    original_step(vit, "vit_lstm", depth, 5.0, quat)()
    assert [tuple(x.shape) for x in vit.seen] == [(3, 128), (3, 128)]  # LSTMNetVIT: 3 layers of 128
    conv = original_network(module, "convnet")
    original_step(conv, "convnet", depth, 5.0, quat)()
    assert conv.calls == [[(1, 1, 60, 90), (1, 1), (1, 4)]]  # no state passed to feed-forward networks


def test_timed_like_vitfly_back_ends(stand_in):
    result = benchmark_original(load_original_models(stand_in), "unet_lstm", iters=5, warmup=2)
    assert result.backend == "original" and result.iters == 5 and 0 < result.median_ms <= result.p90_ms
    assert result.params == 18  # the stand-in's Linear(5, 3)
    assert prepare_original(load_original_models(stand_in), "convnet").threads == 1


def test_bad_checkouts_fail_with_one_line(tmp_path, stand_in):
    with pytest.raises(VitflyError, match="no models/model.py"):
        load_original_models(tmp_path / "nowhere")
    (stand_in / "models" / "model.py").write_text(MODEL.replace("class ViT(_Stateless): pass", ""))
    with pytest.raises(VitflyError, match="no class ViT"):
        load_original_models(stand_in)
    (stand_in / "models" / "model.py").write_text("import not_a_module_anywhere\n")
    with pytest.raises(VitflyError, match="import failed: ModuleNotFoundError"):
        load_original_models(stand_in)


def test_benchmark_script_original_column_only_with_a_checkout(stand_in, tmp_path, capsys):
    script = load_benchmark("latency")
    out = tmp_path / "lat.json"
    argv = ["--models", "convnet", "--backends", "eager", "--iters", "5", "--warmup", "1", "--repeats", "2"]
    script.main([*argv, "--original-repo", str(stand_in), "--out", str(out)])
    assert "x original" in capsys.readouterr().out
    rows = {r["backend"]: r for r in json.loads(out.read_text())["summary"]}
    assert set(rows) == {"original", "eager"}
    eager, original = rows["eager"], rows["original"]
    # the ratio is per repeat (same repeat's medians), then the median of those, on each clock
    for clock in ("wall", "cpu"):
        expected = [e / o for e, o in zip(eager[f"medians_ms_{clock}"], original[f"medians_ms_{clock}"], strict=True)]
        assert eager[f"ratios_{clock}"] == pytest.approx(expected)
        assert eager[f"ratio_{clock}"] == pytest.approx(float(np.median(expected)))
    met = eager["ratio_wall"] <= 1.0 and eager["ratio_cpu"] <= 1.0
    assert eager["target_ratio"] == 1.0 and eager["met"] == met
    assert script.main([*argv, "--out", str(out)]) == 0
    assert "x original" not in capsys.readouterr().out
    assert {r["backend"] for r in json.loads(out.read_text())["summary"]} == {"eager"}
    assert script.main([*argv, "--original-repo", str(tmp_path / "nowhere")]) == 2


def test_cpu_clock_leaves_out_waiting(monkeypatch):
    import time

    from vitfly.eval.latency import CLOCKS, time_calls

    # the CPU clock is the process's CPU time, which stands still while a call waits
    assert CLOCKS == {"wall": time.perf_counter, "cpu": time.process_time}
    # clocks the step moves by hand (a real sleep races other threads of a shared machine): it waits 20 ms and
    # computes for 3 ms; each clock sees its own share
    now = {"wall": 0.0, "cpu": 0.0}
    monkeypatch.setitem(CLOCKS, "wall", lambda: now["wall"])
    monkeypatch.setitem(CLOCKS, "cpu", lambda: now["cpu"])

    def step():
        now["wall"] += 0.023
        now["cpu"] += 0.003

    np.testing.assert_allclose(time_calls(step, iters=3, warmup=1), [23.0] * 3)
    np.testing.assert_allclose(time_calls(step, iters=3, warmup=0, clock="cpu"), [3.0] * 3)
    with pytest.raises(VitflyError, match="--clock must be one of wall, cpu"):
        time_calls(lambda: None, iters=1, warmup=0, clock="tsc")
