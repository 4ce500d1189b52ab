"""scripts/gpu_load.py: the card's load during a slot, from nvidia-smi's CSV lines, worked out by hand."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from scripts.gpu_load import CardLoad, summarize  # noqa: E402


def test_summary_of_the_samples_worked_out_by_hand():
    """Utilisation 37, 100, 0, 55 % (a line nvidia-smi may print on an error skipped): sorted 0, 37, 55, 100;
    median (37 + 55) / 2 = 46, mean 192 / 4 = 48; inclusive deciles at positions 0.3 and 2.7 of the sorted
    samples: 0 + 0.3 x 37 = 11.1 and 55 + 0.7 x 45 = 86.5; memory at most 10,300 MiB."""
    text = "37, 10240\n100, 10300\n[Unknown Error]\n0, 10200\n55, 10250\n"
    got = summarize(text, 5)
    assert got["samples"] == 4 and got["every_s"] == 5 and got["memory_used_mib_max"] == 10300
    assert got["utilization_pct"] == {"median": 46.0, "mean": 48.0, "p10": pytest.approx(11.1),
                                      "p90": pytest.approx(86.5)}
    assert got["utilization_samples"] == [37, 100, 0, 55]
    assert summarize("", 5) == {"samples": 0, "every_s": 5, "note": "no readable sample"}
    assert summarize("80, 500\n", 2)["utilization_pct"] == {"median": 80, "mean": 80.0, "p10": 80, "p90": 80}


def test_without_nvidia_smi_nothing_is_sampled(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # a machine without the NVIDIA tools
    with CardLoad(tmp_path / "load.csv") as load:
        pass
    assert load.summary() == {"note": "nvidia-smi not found: the card's load was not sampled"}
    assert not (tmp_path / "load.csv").exists()
