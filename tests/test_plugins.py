"""Model plug-ins: a package's ``vitfly.models`` entry point puts its networks behind every vitfly command.

Each test writes a tiny installed package into tmp_path (a module and a ``*.dist-info`` with the entry
point) and puts tmp_path on sys.path, where importlib.metadata finds it as it would a ``pip install``.
"""

from __future__ import annotations

import logging
import sys
import textwrap

import pytest
import torch
from test_datamodule import write_dataset

import vitfly.zoo.policy as policy
from vitfly.cli import main
from vitfly.errors import VitflyError
from vitfly.zoo import create_model, list_models, registry

# a minimal network of the zoo's call contract: not a DepthPolicyNet, just forward(depth, speed, quat, hidden)
PLUGIN_SOURCE = '''
import torch
from torch import nn

from vitfly.zoo import register_model


class TinyNet(nn.Module):
    is_recurrent = False
    model_name = "{name}"

    def __init__(self, use_state=True):
        super().__init__()
        self.use_state = use_state
        self.pool = nn.AdaptiveAvgPool2d((3, 3))
        self.out = nn.Linear(9 + 5, 3)

    def forward(self, depth, desired_speed, quat, hidden=None):
        b, t = depth.shape[:2]
        image = self.pool(depth.reshape(b * t, 1, 60, 90)).reshape(b, t, 9)
        state = torch.cat([desired_speed, quat], dim=-1)
        if not self.use_state:
            state = torch.zeros_like(state)
        return self.out(torch.cat([image, state], dim=-1)), None


@register_model
def {name}(use_state=True, **kwargs):
    return TinyNet(use_state=use_state, **kwargs)
'''


def install_plugin(root, dist: str, module: str, source: str, target: str = "") -> None:
    """Write module ``module`` and the dist-info of distribution ``dist`` declaring it (or its callable
    ``target``) as a plug-in."""
    (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{dist}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    value = f"{module}:{target}" if target else module
    (info / "entry_points.txt").write_text(f"[vitfly.models]\n{module} = {value}\n")


@pytest.fixture
def plugin_root(tmp_path, monkeypatch):
    """tmp_path on sys.path, with the registry as if no plug-in had been loaded yet (restored after)."""
    root = tmp_path / "site"
    root.mkdir()
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.setattr(registry, "_BUILDERS", dict(registry._BUILDERS))
    monkeypatch.setattr(registry, "_plugins_loaded", False)
    monkeypatch.setattr(registry, "_plugin_clash", None)
    monkeypatch.setattr(policy, "_POLICY_CLASSES", dict(policy._POLICY_CLASSES))
    before = set(sys.modules)
    yield root
    for name in set(sys.modules) - before:
        if sys.modules[name] is not None and str(getattr(sys.modules[name], "__file__", "")).startswith(str(root)):
            del sys.modules[name]


def test_plugin_model_fits_evaluates_exports_and_benchmarks(plugin_root, tmp_path):
    install_plugin(plugin_root, "tiny-vitfly-net", "tiny_net_plugin", PLUGIN_SOURCE.format(name="tiny_net"))
    assert "tiny_net" in list_models()
    velocity, _ = create_model("tiny_net")(torch.zeros(2, 3, 1, 60, 90), torch.ones(2, 3, 1), torch.zeros(2, 3, 4))
    assert velocity.shape == (2, 3, 3)

    data = write_dataset(tmp_path / "d.h5", [9, 7, 11])
    config = tmp_path / "fit.yaml"
    config.write_text("model: tiny_net\n")  # the plug-in's name is the model's class, as for a built-in
    root = tmp_path / "run"
    assert main(["fit", "--config", str(config), "--data.data_path", data, "--data.num_workers", "0",
                 "--data.batch_size", "2", "--trainer.max_epochs", "1", "--trainer.default_root_dir", str(root),
                 "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"]) == 0
    (ckpt,) = root.glob("version_*/checkpoints/last.ckpt")
    assert torch.load(ckpt, weights_only=True)["hyper_parameters"]["model"] == "tiny_net"

    out = tmp_path / "eval"
    assert main(["evaluate", "--policy", str(ckpt), "--speeds", "3", "--trials", "1", "--out", str(out),
                 "--timeout", "1", "--no-gif", "--no-plots", "--no-progress", "--num-envs", "1"]) == 0
    assert any(out.rglob("*.jsonl"))
    assert main(["export", str(ckpt), "--out", str(tmp_path / "tiny.onnx")]) == 0
    assert main(["benchmark-latency", "--models", "tiny_net", "--device", "cpu", "--iters", "2", "--warmup", "0"]) == 0


def test_broken_plugin_is_one_warning_line_and_the_rest_still_work(plugin_root, caplog):
    install_plugin(plugin_root, "broken-net", "broken_net_plugin", "import no_such_module_anywhere\n")
    install_plugin(plugin_root, "good-net", "good_net_plugin", PLUGIN_SOURCE.format(name="good_net"))
    with caplog.at_level(logging.WARNING, logger=registry.__name__):
        names = list_models()
    assert {"convnet", "vit_lstm", "good_net"} <= set(names)
    (record,) = caplog.records
    line = record.getMessage()
    assert "\n" not in line and "broken-net" in line and "broken_net_plugin" in line
    assert "ModuleNotFoundError" in line
    assert create_model("convnet") is not None


def test_name_clash_with_a_builtin_is_one_error(plugin_root, capsys):
    install_plugin(plugin_root, "clash-net", "clash_net_plugin", PLUGIN_SOURCE.format(name="convnet"))
    with pytest.raises(VitflyError, match="clash-net .*'convnet'.*vitfly.zoo.convnet"):
        list_models()
    assert main(["benchmark-latency", "--models", "convnet", "--iters", "1", "--warmup", "0"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("vitfly: error: model plug-in clash-net")


def test_entry_point_may_name_a_registering_callable(plugin_root):
    source = PLUGIN_SOURCE.format(name="hooked_net").replace("@register_model\n", "")
    source += "\n\ndef register_all():\n    register_model(hooked_net)\n"
    install_plugin(plugin_root, "hooked-net", "hooked_net_plugin", source, target="register_all")
    assert "hooked_net" in list_models()
