"""Loading the repository's scripts/ and benchmarks/ in a test: they are command-line files, not part of the
installed vitfly, so a test imports them by path."""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]


def load_script(name: str) -> ModuleType:
    """scripts/<name>.py, imported as ``scripts.<name>``, the way the scripts import each other."""
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    return importlib.import_module(f"scripts.{name}")


def load_benchmark(name: str) -> ModuleType:
    """benchmarks/<name>.py, run as a module of its own (a fresh one each call: its globals are the test's)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
