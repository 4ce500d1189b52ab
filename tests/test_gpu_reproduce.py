"""scripts/gpu_reproduce.py: runs of a reproduce preset trained in one place, carried home and taken as done.

Here both ends run on the CPU with the tiny preset: collect, refuse other data, train one run, pack it
(fp16 network, no optimiser state), unpack it into a fresh run directory, and check that the reproduce
workflow takes it as finished (no retraining) and reports its epochs from done.json.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import torch

from vitfly.datamodules.provenance import dataset_fingerprint
from vitfly.workflows.pipeline import stage_train
from vitfly.workflows.reproduce_config import load_reproduce_config, train_callbacks, train_stage
from vitfly.workflows.reproduce_report import _training_table
from vitfly.zoo import load_network

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "gpu_reproduce.py"


def script(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], cwd=REPO, capture_output=True, text=True,
                          timeout=600)


def test_runs_trained_elsewhere_come_back_as_done(tmp_path):
    run_dir, data, out = tmp_path / "run", tmp_path / "tiny.h5", tmp_path / "back"
    where = ["--preset", "tiny", "--run-dir", str(run_dir), "--data", str(data)]
    train = ["train", *where, "--out", str(out), "--work", str(tmp_path / "work"), "--collect-workers", "1",
             "--threads", "1", "--runs", "convnet-nostate"]

    refused = script(*train, "--expect-data-hash", "0000000000000000")
    assert refused.returncode == 1, refused.stdout + refused.stderr
    assert "nothing trained" in refused.stdout
    assert "!= expected 0000000000000000" in json.loads((out / "gpu_reproduce.json").read_text())["error"]
    assert not (run_dir / "train").exists()

    data_hash = dataset_fingerprint(data)["dataset_hash"]
    done = script(*train, "--expect-data-hash", data_hash)
    assert done.returncode == 0, done.stdout + done.stderr
    report = json.loads((out / "gpu_reproduce.json").read_text())
    assert report["runs"]["convnet-nostate"] == {"rc": 0, "packed": True}
    assert report["data"]["dataset_hash"] == data_hash

    trained = run_dir / "train" / "convnet-nostate"
    original = load_network(trained / "checkpoints" / "best.ckpt")
    shutil.rmtree(trained)
    unpacked = script("unpack", *where, str(out))
    assert unpacked.returncode == 0, unpacked.stdout + unpacked.stderr
    marker = json.loads((trained / "done.json").read_text())
    assert Path(marker["checkpoint"]) == (trained / "checkpoints" / "best.ckpt").resolve()
    assert marker["trained_on"]["epochs"] == 1 and marker["trained_on"]["steps"] == 2  # tiny: 1 epoch, 2 batches
    assert not (trained / "checkpoints" / "last.ckpt").exists()
    saved = torch.load(marker["checkpoint"], map_location="cpu", weights_only=True)
    assert "optimizer_states" not in saved

    back = load_network(marker["checkpoint"])  # the weights, rounded to fp16 and nothing else
    for (name, a), b in zip(original.state_dict().items(), back.state_dict().values(), strict=True):
        expected = a.half().float() if a.is_floating_point() else a
        assert torch.equal(expected, b), name

    cfg = load_reproduce_config(REPO / "configs" / "reproduce.yaml", "tiny", {"out": str(run_dir), "data": str(data)})
    stage, callbacks = train_callbacks(train_stage(cfg, "convnet", False), cfg, "test")
    assert stage_train(stage, data, trained, 1, progress=False, callbacks=callbacks) == Path(marker["checkpoint"])
    assert not (trained / "checkpoints" / "last.ckpt").exists()  # taken as done, not trained again
    assert "| convnet-nostate | 1 | 2 |" in _training_table(cfg)

    again = script("unpack", *where, str(out))
    assert again.returncode == 0 and "left alone" in again.stdout
