"""benchmarks/card_sharing.py: one process alone, then several at once, timed over one common window; on a CPU
the MPS phase is left out and the output says why. (Its numbers are a benchmark's, never a test's: here only
the machinery and the arithmetic of its table.)"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "card_sharing.py"


@pytest.mark.slow
def test_phases_alone_and_together_with_their_sums_and_ratios(tmp_path):
    out = tmp_path / "sharing.json"
    done = subprocess.run([sys.executable, str(SCRIPT), "--arm", "paper", "--model", "convnet", "--mode", "unpadded",
                           "--steps", "16", "--warmup", "1", "--processes", "2", "--window-s", "1", "--device", "cpu",
                           "--threads", "1", "--json", str(out)], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(out.read_text())
    alone, turns = got["phases"]
    assert (alone["phase"], alone["processes"], alone["vs_alone"]) == ("alone", 1, 1.0)
    assert turns["phase"] == "turns" and len(turns["fps_each"]) == 2 and all(f > 0 for f in turns["fps_each"])
    assert turns["fps_total"] == pytest.approx(sum(turns["fps_each"]), abs=0.2)
    assert turns["vs_alone"] == pytest.approx(turns["fps_total"] / alone["fps_total"], abs=1e-3)
    assert got["mps"] == {"mps": False, "note": "not a CUDA device"}
    assert got["settings"]["batch"] == 1 and got["settings"]["bucket"] is None  # the paper arm, unpadded
    assert "no MPS phase: not a CUDA device" in done.stdout
    assert f"| turns | 2 | {turns['fps_each'][0]:,.0f}, {turns['fps_each'][1]:,.0f} |" in done.stdout


def test_one_process_is_not_a_comparison():
    done = subprocess.run([sys.executable, str(SCRIPT), "--processes", "1"], capture_output=True, text=True)
    assert done.returncode == 2 and "--processes: at least 2" in done.stderr
