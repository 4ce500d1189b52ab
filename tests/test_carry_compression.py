"""benchmarks/carry_compression.py: the byte planes and the tensor groups it compresses, checked by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import load_benchmark
from safetensors.torch import save_file

bench = load_benchmark("carry_compression")


def test_byte_planes_put_each_values_bytes_in_their_plane():
    # 1.0 = 0x3F800000 and 2.0 = 0x40000000, little-endian: 00 00 80 3F and 00 00 00 40
    assert bench.shuffled(np.array([1.0, 2.0], dtype=np.float32)) == bytes([0, 0, 0, 0, 0x80, 0, 0x3F, 0x40])


def test_groups_split_weights_and_moments_and_round_the_moments_to_bf16(tmp_path, capsys):
    run = tmp_path / "vit-state"
    run.mkdir()
    save_file({"/state_dict/net.w": torch.tensor([1.0, -2.0]), "/state_dict/net.steps": torch.tensor([3]),
               "/optimizer_states/0/state/0/exp_avg": torch.tensor([1.0, 1.00390625]),
               "/optimizer_states/0/state/0/exp_avg_sq": torch.tensor([0.5, 0.25]),
               "/optimizer_states/0/state/0/step": torch.tensor(7.0)}, run / "last.safetensors")
    g = bench.groups(run / "last.safetensors")
    assert sorted(g) == ["exp_avg", "exp_avg_bf16", "exp_avg_sq", "exp_avg_sq_bf16", "weights"]
    assert g["weights"].tolist() == [1.0, -2.0]  # the integer buffer and Adam's step are not weights
    # bf16 keeps 7 mantissa bits: 1 + 2**-8 rounds to 1.0 (ties to even), whose pattern is 0x3F80 = 16256
    assert g["exp_avg_bf16"].tolist() == [16256, 16256] and g["exp_avg_sq_bf16"].tolist() == [0x3F00, 0x3E80]
    assert g["exp_avg"].view(np.float32).tolist() == [1.0, 1.00390625]
    assert bench.main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "| vit-state | **weights + bf16 moments** | 0.0 MiB |" in out and out.count("\n") == 10
    with pytest.raises(SystemExit, match="no such file"):
        bench.main([str(tmp_path)])
