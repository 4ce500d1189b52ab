"""benchmarks/train_speed.py --arm: the settings it takes from the presets, its FLOP count and its peak table.

(The timing itself is a benchmark, never a test; `benchmarks/train_speed.py --arm paper --iters 3` runs on a CPU.)
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import load_benchmark

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("train_speed")


def test_arms_take_batch_chunks_precision_and_static_shapes_from_their_presets(bench):
    paper = bench.arm_settings("paper", "vit_lstm", "recipe")
    assert paper == {"batch": 1, "bucket": 64, "precision": "bf16", "policy_kwargs": {
        "tbptt_steps": None, "avoid_weight": 0.0, "gradient_clip_val": None, "static_shapes": True,
        "compile": "reduce-overhead"}}
    assert bench.arm_settings("paper", "convnet", "recipe")["precision"] == "fp32"
    unpadded = bench.arm_settings("paper", "vit_lstm", "unpadded")
    assert unpadded["bucket"] is None and unpadded["policy_kwargs"]["static_shapes"] is False
    assert unpadded["policy_kwargs"]["compile"] is False
    assert bench.arm_settings("paper", "vit_lstm", "eager")["policy_kwargs"]["static_shapes"] is True
    assert bench.arm_settings("paper", "vit_lstm", "fp32")["precision"] == "fp32"
    vitfly = bench.arm_settings("vitfly", "vit_lstm", "recipe")
    assert (vitfly["batch"], vitfly["bucket"], vitfly["precision"]) == (64, None, "bf16")
    assert vitfly["policy_kwargs"] == {"tbptt_steps": 32, "avoid_weight": 10.0, "gradient_clip_val": 1.0,
                                       "compile": True}
    assert bench.arm_models("vitfly")[-1] == "resnet18" and "resnet18" not in bench.arm_models("paper")


def test_peaks_are_the_dense_datasheet_figures(bench):
    assert bench.peak_tflops("NVIDIA H100 80GB HBM3", "bf16")[0] == pytest.approx(989.5)
    assert bench.peak_tflops("NVIDIA H100 80GB HBM3", "fp32")[0] == pytest.approx(494.5)
    assert bench.peak_tflops("NVIDIA H100 PCIe", "bf16")[0] == pytest.approx(756.5)
    assert bench.peak_tflops("NVIDIA H100 PCIe", "fp32")[0] == pytest.approx(378.0)
    assert bench.peak_tflops("NVIDIA H200", "bf16")[0] == pytest.approx(989.5)
    assert bench.peak_tflops("cpu", "bf16") is None
    assert bench.rate_cells(1e2, 2e9, (1000.0, "x")) == " 2 | 0.2 | 0.02 % |"
    assert bench.rate_cells(1e5, 2e9, None).endswith("| n/a |")


@pytest.mark.parametrize("model,rel", [("convnet", 0.0), ("lstmnet", 0.01)])
def test_flops_per_frame_hold_for_any_trajectory_length(bench, monkeypatch, model, rel):
    monkeypatch.setattr(bench, "FLOP_COUNT_STEPS", 32)
    short = bench.flops_per_frame(model)
    monkeypatch.setattr(bench, "FLOP_COUNT_STEPS", 96)  # a count on 32 frames holds for longer trajectories
    long = bench.flops_per_frame(model)
    assert short > 0 and long == pytest.approx(short, rel=rel, abs=0)


def test_the_profile_names_where_a_step_goes(bench):
    """Three calls of a step of two matrix products (64 x 32 by 32 x 16, then by 16 x 8): the table counts 6 mm."""
    import torch

    a, b, c = torch.randn(64, 32), torch.randn(32, 16), torch.randn(16, 8)
    table = bench.profile_table(lambda: (a @ b) @ c, torch.device("cpu"))
    row = next(line for line in table.splitlines() if line.strip().startswith("aten::mm"))
    assert row.split()[-1] == "6"  # "# of Calls", the table's last column


def test_the_loop_mode_trains_the_presets_run_on_real_flights(bench, monkeypatch, tmp_path):
    """``--modes loop``: the paper preset's ConvNet run (one flight a step) through ``train_policy`` on a small
    dataset, 4 training batches of which the first is left out, 1 validation batch timed by the run."""
    from test_datamodule import write_dataset

    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))  # the worker's path: fit_timer beside the script
    lengths = [12, 9, 15, 7, 11, 14, 8, 10]
    data = write_dataset(tmp_path / "d.h5", lengths)
    result = bench.measure_loop("convnet", "paper", data, batches=4, skip=1, val_batches=1, device="cpu")
    assert result["padded"] == [1, "flights"] and result["graphs"] == 0  # one flight a step; eager on a CPU
    assert result["fps"] > 0 and result["warmup_s"] > 0 and result["val_s"] > 0
    with pytest.raises(RuntimeError, match="only 4 training batches ran; need more than --fit-skip 4"):
        bench.measure_loop("convnet", "paper", data, batches=4, skip=4, val_batches=0, device="cpu")
