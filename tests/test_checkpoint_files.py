"""vitfly.training.checkpoint_files: a checkpoint as safetensors + JSON, read back as the dict it was.

The dict here has what a Lightning checkpoint of vitfly holds (worked out from a real one of the tiny preset):
weights, Adam's state keyed by integer parameter ids, loop counters, the ModelCheckpoint state with a tensor
score and an infinite one, RngState's Python generator state (a tuple holding a tuple) and numpy's (a tensor
in a list). The round trip through the resumed training is tests/test_gpu_reproduce.py's.
"""

from __future__ import annotations

import json
import math
import random

import numpy as np
import pytest
import torch

from vitfly.errors import VitflyError
from vitfly.training import checkpoint_files


def a_checkpoint() -> dict:
    gen = torch.Generator().manual_seed(3)
    w = torch.randn(4, 3, generator=gen)
    return {
        "epoch": 4, "global_step": 1880, "pytorch-lightning_version": "2.6.6",
        "state_dict": {"net.fc.weight": w, "net.fc.bias": torch.zeros(4), "net.bn.num_batches_tracked":
                       torch.tensor(7)},
        "optimizer_states": [{"state": {0: {"step": torch.tensor(1880.0), "exp_avg": w * 0.1,
                                            "exp_avg_sq": (w * w).to(torch.bfloat16)}},
                              "param_groups": [{"lr": 1e-4, "betas": (0.9, 0.999), "params": [0, 1, 2],
                                                "fused": None}]}],
        "callbacks": {"ModelCheckpoint{'monitor': 'val/loss'}": {"best_model_score": torch.tensor(0.0159),
                                                                "kth_value": torch.tensor(math.inf),
                                                                "best_k_models": {"/r/best.ckpt": torch.tensor(0.0159)},
                                                                "dirpath": "/r"},
                      "RngState": {"torch": torch.get_rng_state(), "python": random.getstate(),
                                   "numpy": ["MT19937", torch.arange(5), 624, 0, 0.0]}},
        "hyper_parameters": {"lr": 1e-4, "warmup_epochs": 5, "tbptt_steps": None, "nan": math.nan},
        "loops": {"fit_loop": {"epoch_progress": {"total": {"ready": 5, "completed": 5}}}},
    }


def assert_same(a, b, path=""):
    assert type(a) is type(b), path
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), path
    elif isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            assert_same(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{path}/{i}")
    elif isinstance(a, float) and math.isnan(a):
        assert math.isnan(b), path
    else:
        assert a == b, path


def test_a_checkpoint_comes_back_as_it_was(tmp_path):
    ckpt = a_checkpoint()
    size = checkpoint_files.write(ckpt, tmp_path, "last")
    tensors, rest = checkpoint_files.paths(tmp_path, "last")
    assert size == tensors.stat().st_size + rest.stat().st_size
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.json", "last.safetensors"]  # no temporary left
    back = checkpoint_files.read(tmp_path, "last")
    assert_same(ckpt, back)
    assert list(back["optimizer_states"][0]["state"]) == [0]  # the integer key is an integer again
    random.setstate(back["callbacks"]["RngState"]["python"])  # a usable generator state
    skeleton = json.loads(rest.read_text())
    assert skeleton["epoch"] == 4
    assert skeleton["state_dict"]["net.fc.weight"] == {"__tensor__": "/state_dict/net.fc.weight"}


def test_what_has_no_plain_form_is_refused_with_its_path(tmp_path):
    ckpt = a_checkpoint()
    ckpt["callbacks"]["RngState"]["numpy"][1] = np.arange(5)
    with pytest.raises(VitflyError, match=r"last.json: /callbacks/RngState/numpy/1: a ndarray has no plain form"):
        checkpoint_files.write(ckpt, tmp_path, "last")
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_a_missing_half_is_one_line(tmp_path):
    checkpoint_files.write(a_checkpoint(), tmp_path, "last")
    checkpoint_files.paths(tmp_path, "last")[0].unlink()
    assert not checkpoint_files.exists(tmp_path, "last")
    with pytest.raises(VitflyError, match="checkpoint 'last' unreadable .* expected last.safetensors and last.json"):
        checkpoint_files.read(tmp_path, "last")
