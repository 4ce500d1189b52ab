"""Fixtures shared by several test files."""

import os

import pytest
import torch


def pytest_configure(config):
    """Under pytest-xdist (`-n auto`), share the cores among the workers: each worker's torch would
    otherwise start one thread per core, and the oversubscribed threads wait for each other."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if workers > 1:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))


@pytest.fixture
def one_torch_thread():
    """One torch thread for the test: the batched engine's small ops gain nothing from threads, and on a busy
    machine they wait for them."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# the longest tests first: under pytest-xdist a long test started last keeps one core busy while the others idle.
# Only these two: sorted longest to shortest, the slow suite's compiling tests met other work and took longer (the
# compiled engine's 64 s against 35 s at the end, where inductor's compile workers had the cores to themselves)
LONGEST_FIRST = ("tests/test_reproduce_tiny.py", "tests/test_sim_batched.py::test_whole_expert_episodes")


def pytest_collection_modifyitems(config, items):
    """Collection order, but the tests named in LONGEST_FIRST ahead of the rest (a stable sort)."""
    items.sort(key=lambda item: not item.nodeid.startswith(LONGEST_FIRST))
