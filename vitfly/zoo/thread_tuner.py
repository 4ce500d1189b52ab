"""Choosing the CPU's intra-op thread count for training by measuring optimiser steps, not by guessing.

On a machine whose cores are shared with other processes, every parallel operator waits at a barrier
for its slowest thread, and a thread that is not scheduled holds everyone up: on the shared 2-core
machine this was written on, with a load average of ~10, a ConvNet step took 5x longer with 2 threads
than with 1 (benchmarks/train_speed.py), while on the quiet machine 2 threads are faster for the large
networks. ``ThreadTuner`` times steps under each candidate (all threads, one thread), runs the faster
one, and measures again every ``probe_every`` steps, because the other load comes and goes.
"""

from __future__ import annotations

import statistics
import time

import torch


class ThreadTuner:
    """Alternates the candidates for ``probe_steps`` steps each, then keeps the fastest for ``probe_every`` steps.

    Call ``before_step()`` before an optimiser step and ``after_step(frames)`` after it; the cost compared
    is seconds per frame, so steps of different sizes (the short last TBPTT chunk) compare fairly.
    """

    def __init__(self, max_threads: int | None = None, probe_steps: int = 3, probe_every: int = 100) -> None:
        self.max_threads = max_threads or torch.get_num_threads()
        self.candidates = [self.max_threads, 1] if self.max_threads > 1 else [1]
        self.probe_steps = probe_steps
        self.probe_every = probe_every
        self.choice = self.max_threads
        self._costs: dict[int, list[float]] = {c: [] for c in self.candidates}
        self._since_probe = 0
        self._probing = len(self.candidates) > 1
        self._current = self.choice
        self._start = 0.0

    @property
    def active(self) -> bool:
        return len(self.candidates) > 1

    def _next_threads(self) -> int:
        if not self._probing:
            return self.choice
        # alternate candidates until each has probe_steps samples
        counts = {c: len(self._costs[c]) for c in self.candidates}
        return min(self.candidates, key=lambda c: (counts[c], self.candidates.index(c)))

    def before_step(self) -> None:
        self._current = self._next_threads()
        if torch.get_num_threads() != self._current:
            torch.set_num_threads(self._current)
        self._start = time.perf_counter()

    def after_step(self, frames: int) -> None:
        elapsed = time.perf_counter() - self._start
        if not self.active or frames <= 0:
            return
        if self._probing:
            self._costs[self._current].append(elapsed / frames)
            if all(len(v) >= self.probe_steps for v in self._costs.values()):
                self.choice = min(self.candidates, key=lambda c: statistics.median(self._costs[c]))
                self._probing = False
                self._since_probe = 0
                self._costs = {c: [] for c in self.candidates}
            return
        self._since_probe += 1
        if self._since_probe >= self.probe_every:
            self._probing = True

    def restore(self) -> None:
        """Back to the thread count the tuner started from."""
        if torch.get_num_threads() != self.max_threads:
            torch.set_num_threads(self.max_threads)
