"""The int8 fast path with the shipped trained weights (weights/): the export's self-check against eager and the
commands over short recorded flights. Random weights hide what trained ones show (large state-column weights,
near-zero outputs), so these are checked on the weights users fly."""

from __future__ import annotations

import onnx
import pytest
import torch

from vitfly.deploy.onnx import CHECK_ATOL, OnnxPolicyRunner, export_onnx_bytes
from vitfly.eval.agreement import (
    COMMAND_TOLERANCE_MPS,
    calibration_depth,
    compare_commands,
    record_flights,
    replay_commands,
)
from vitfly.eval.latency import needs_calibration
from vitfly.eval.learned_policy import LearnedPolicy
from vitfly.eval.policy_source import PolicySource

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def flights():
    # scenes and speeds other than the calibration's (seed 10); 2 flights x 1.5 s = 90 ticks
    return record_flights("spheres", seeds=(0,), speeds_mps=(7.0,), timeout_s=1.5) + record_flights(
        "trees", seeds=(1,), speeds_mps=(5.0,), timeout_s=1.5
    )


@pytest.mark.parametrize("name", ["lstmnet", "vit_lstm"])
def test_int8_export_of_trained_weights_checks_and_flies_the_float_commands(flights, name):
    net = PolicySource(f"pretrained:{name}").load_network().eval()
    calibration = calibration_depth(seconds=2.0) if needs_calibration(net) else None
    data = export_onnx_bytes(net, precision="int8", calibration_depth=calibration)
    meta = {p.key: p.value for p in onnx.load_from_string(data).metadata_props}
    assert int(meta["vitfly.int8_products"]) > 0  # the LSTM products are int8: this is not the float path
    runner = OnnxPolicyRunner(data)
    worst = runner.check_against(net, atol=CHECK_ATOL["int8"])  # raises above the tolerance
    assert 1e-4 < worst <= CHECK_ATOL["int8"]
    reference = replay_commands(LearnedPolicy(net), flights)
    agreement = compare_commands(reference, replay_commands(LearnedPolicy(net, step_fn=runner), flights))
    assert agreement.ticks == 90
    assert agreement.within(COMMAND_TOLERANCE_MPS["onnxruntime-int8"]), agreement
