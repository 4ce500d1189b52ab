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


# the longest tests first, longest to shortest (measured in CI on a fresh clone, compile caches cold): under
# pytest-xdist a long test started last keeps one core busy while the others idle
LONGEST_FIRST = (
    "tests/test_reproduce_tiny.py",  # 100 s
    "tests/test_installed.py",  # 60 s, one xdist group
    "tests/test_sim_batched.py::test_whole_expert_episodes",  # 65 s
    "tests/test_fast_paths.py::test_compiled_encoder_matches_eager[vit_lstm]",  # 50 s
    "tests/test_card_sharing.py",  # 37 s
    "tests/test_sim_batched.py::test_compiled_engine",  # 35 s
)


def pytest_collection_modifyitems(config, items):
    """Collection order, but the tests named in LONGEST_FIRST ahead of the rest, in its order (a stable sort)."""
    def rank(item) -> int:
        return next((i for i, prefix in enumerate(LONGEST_FIRST) if item.nodeid.startswith(prefix)),
                    len(LONGEST_FIRST))

    items.sort(key=rank)
