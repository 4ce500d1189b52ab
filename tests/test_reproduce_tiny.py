"""`vitfly reproduce --preset tiny` end to end, killed (SIGKILL) in each stage and rerun until it finishes.

Slow (several minutes): run with `pytest -m slow tests/test_reproduce_tiny.py`.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
import torch
import yaml

from vitfly.datamodules.schema import open_trajectories
from vitfly.eval import records
from vitfly.zoo import load_network, load_pretrained
from vitfly.zoo.pretrained import read_manifest

REPO = Path(__file__).resolve().parents[1]


def tiny_config(tmp_path: Path) -> Path:
    """The shipped config, with the tiny preset publishing its weights into tmp_path/weights."""
    cfg = yaml.safe_load((REPO / "configs/reproduce.yaml").read_text())
    cfg["presets"]["tiny"]["train"].update(publish_weights=True, weights_dir=str(tmp_path / "weights"))
    path = tmp_path / "reproduce.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def start(out: Path, data: Path, log: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "vitfly.cli", "reproduce", "--config", str(out.parent / "reproduce.yaml"),
           "--preset", "tiny", "--out", str(out), "--data", str(data), "--no-progress", *extra]
    env = {**os.environ, "PYTHONPATH": str(REPO), "MPLBACKEND": "Agg", "WANDB_MODE": "offline"}
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True)  # its own process group: the kill reaches its workers too


def kill_when(proc: subprocess.Popen, ready, timeout_s: float = 900.0) -> bool:
    """SIGKILL the run's process group as soon as ``ready()``; False if the run ended first."""
    t0 = time.monotonic()
    while proc.poll() is None:
        if ready():
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            return True
        if time.monotonic() - t0 > timeout_s:
            os.killpg(proc.pid, signal.SIGKILL)
            raise AssertionError("the tiny study took too long")
        time.sleep(0.1)
    return False


def lines(path: Path) -> int:
    return len(path.read_text().splitlines()) if path.exists() else 0


@pytest.mark.slow
def test_tiny_study_resumes_after_a_kill_in_every_stage(tmp_path):
    out, data = tmp_path / "study", tmp_path / "tiny.h5"
    tiny_config(tmp_path)
    kill_points = [
        ("data", lambda: data.exists()),
        ("train", lambda: (out / "train/convnet-state/done.json").exists()),
        ("evaluate", lambda: lines(out / "eval/spheres/trials.jsonl") >= 1),
        ("paths", lambda: lines(out / "eval/paths/trials.jsonl") >= 1),
    ]
    killed = []
    for i, (stage, ready) in enumerate(kill_points):
        log = tmp_path / f"run{i}.log"
        if kill_when(start(out, data, log), ready):
            killed.append(stage)
    assert killed == ["data", "train", "evaluate", "paths"], killed
    log = tmp_path / "final.log"
    proc = start(out, data, log)
    assert proc.wait(timeout=900) == 0, log.read_text()[-3000:]
    text = log.read_text()
    # nothing finished before was done again
    assert "[collect] " in text and "complete, 6 trajectories (0 new)" in text
    assert text.count("[train] done before") == 3
    # every trial once, and all of them: spheres/trees 4 policies x 2 speeds, window 4 x 1, ablation 2 x 2 envs,
    # the modular comparison fastplanner, ViT+LSTM and the expert at 3 m/s
    expected = {"spheres": 8, "trees": 8, "window": 4, "ablation": 4, "paths": 6, "modular": 3}
    for sweep, n in expected.items():
        recs = records.read_sweep(out / "eval" / sweep)
        keys = Counter(r.key for r in recs)
        assert len(recs) == n and max(keys.values()) == 1, (sweep, len(recs), keys.most_common(1))
    with open_trajectories(data) as tf:
        assert len(tf) == 6
    results = json.loads((out / "results.json").read_text())
    assert results["preset"] == "tiny" and len(results["findings"]) == 11
    md = (out / "results.md").read_text()
    assert "## Findings" in md and "## Ablation: state input" in md and "| ConvNet | 235,269 | 235,269 |" in md
    # the paired section: every paired finding, and ViT+LSTM against ConvNet on the same spheres scenes
    assert "## Paired comparisons" in md and len(results["paired_findings"]) == 10
    modular = records.read_sweep(out / "eval" / "modular")
    assert {r.scene_seed for r in modular} == {modular[0].scene_seed}  # one scene (seed 7070, trial 0) for all three
    assert len(next(r for r in modular if r.policy == "fastplanner").extra["replan_ms"]) > 0
    assert results["paired_findings"][-1]["key"] == "modular_baselines" and "## Modular baselines" in md
    assert results["modular"]["replan_latency"]["fastplanner"]["trials"] == 1
    assert "| ConvNet | " in md.split("ViT+LSTM's success minus each policy's in spheres")[1]
    for name in ("spheres_collision_metrics", "trees_collision_metrics", "command_characteristics",
                 "paths_fixed_scene", "paths_fixed_scene_3d", "window_paths", "modular_baselines", "paired_findings",
                 "training_curves"):
        assert (out / "figures" / f"{name}.png").stat().st_size > 10_000, name
    assert "![training and validation loss per epoch of every run](figures/training_curves.png)" in md
    # the state models were published (fp16 safetensors) with their closed-loop numbers
    manifest = read_manifest(tmp_path / "weights")["models"]
    assert sorted(manifest) == ["convnet", "vit_lstm"]
    for name, entry in manifest.items():
        ckpt = Path(json.loads((out / f"train/{name}-state/done.json").read_text())["checkpoint"])
        assert entry["source_checkpoint"] == str(ckpt.resolve()) and entry["preset"] == "tiny"
        assert entry["dataset_trajectories"] == 6 and entry["train_frames"] > 0
        assert entry["closed_loop"]["spheres"]["7"]["trials"] == 1
        trained, published = load_network(ckpt), load_pretrained(name, tmp_path / "weights")
        for k, v in trained.state_dict().items():
            expected = v.half().to(v.dtype) if v.is_floating_point() else v
            assert torch.equal(published.state_dict()[k], expected), (name, k)
    # a rerun of the finished study does nothing new
    log = tmp_path / "again.log"
    proc = start(out, data, log, "--stages", "train", "evaluate", "paths", "modular")
    assert proc.wait(timeout=600) == 0
    again = log.read_text()
    assert " 0 trials flown" in again and " 1 trials flown" not in again and " 2 trials flown" not in again
    assert "0 repeats flown" in again and "[train] done before" in again
