"""Every benchmark and script imports, and those run from the shell print their --help.

Most of them run only on a GPU slot or by hand, so a rename in vitfly (or in a sibling they import) would
otherwise go unnoticed until someone needs the tool.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from helpers import load_benchmark, load_script

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted(p.stem for p in (REPO / "benchmarks").glob("*.py"))
SCRIPTS = sorted(p.stem for p in (REPO / "scripts").glob("*.py"))


def prints_its_help(module, name: str, monkeypatch, capfd) -> None:
    """``main()`` as the shell would run ``NAME.py --help`` (a tool handing over to another process included)."""
    monkeypatch.setattr(sys, "argv", [f"{name}.py", "--help"])
    try:
        code = module.main()
    except SystemExit as exit_:
        code = exit_.code
    assert code in (0, None)
    assert "usage:" in capfd.readouterr().out


@pytest.mark.parametrize("name", BENCHMARKS)
def test_a_benchmark_imports_and_prints_its_help(name, monkeypatch, capfd):
    module = load_benchmark(name)
    if "__main__" in (REPO / "benchmarks" / f"{name}.py").read_text():
        prints_its_help(module, name, monkeypatch, capfd)


@pytest.mark.parametrize("name", SCRIPTS)
def test_a_script_imports_and_prints_its_help(name, monkeypatch, capfd):
    module = load_script(name)
    if "__main__" in (REPO / "scripts" / f"{name}.py").read_text():
        prints_its_help(module, name, monkeypatch, capfd)


def test_the_tools_are_all_found():
    assert {"train_speed", "loader_headroom", "sim_speed"} <= set(BENCHMARKS)
    assert {"gpu", "gpu_reproduce", "paired_figure"} <= set(SCRIPTS)


def test_sim_speed_compares_the_back_ends_trial_by_trial(tmp_path, monkeypatch):
    """The end-to-end part on both physics back ends, two trials each: the same outcomes (pybullet's and vitfly's
    integrator fly one airframe alike), a comparison no --help reaches."""
    pytest.importorskip("pybullet")
    out = tmp_path / "sim_speed.json"
    monkeypatch.setattr(sys, "argv", ["sim_speed.py", "--physics", "pybullet", "native", "--trials", "1",
                                      "--lockstep", "2", "--eval-trials", "2", "--repeats", "1", "--skip-collect",
                                      "--skip-batched", "--json", str(out)])
    load_benchmark("sim_speed").main()
    row = json.loads(out.read_text())["end_to_end"]["native"]
    assert row["same_outcome"] == "2/2" and row["max_path_gap_m"] < 1e-3
