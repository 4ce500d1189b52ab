"""How busy the card was while a slot trained: ``nvidia-smi`` sampled every few seconds beside the runs, summed up
in the slot's report (``gpu_reproduce.json``: ``card_load``), so the next plan knows whether the card had room
for another run.

``utilization.gpu`` is the share of the sample period in which at least one kernel ran: near 100 % the card
was never idle (another process would only take turns with it); well below, the runs left it waiting for
their hosts, and a third run could use the gaps. It says nothing about how full the multiprocessors were
while a kernel ran (one trajectory a step fills few of them).
"""

from __future__ import annotations

import shutil
import statistics
import subprocess
from pathlib import Path

QUERY = "utilization.gpu,memory.used"  # %, MiB


class CardLoad:
    """``with CardLoad(path, every_s):`` samples the card into ``path`` until the block ends; without
    ``nvidia-smi`` (a CPU machine) it samples nothing."""

    def __init__(self, path: Path, every_s: int = 5) -> None:
        self.path, self.every_s = Path(path), every_s
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> CardLoad:
        exe = shutil.which("nvidia-smi")
        if exe is not None:
            with open(self.path, "w") as out:  # the child writes through its own copy
                self.proc = subprocess.Popen([exe, f"--query-gpu={QUERY}", "--format=csv,noheader,nounits",
                                              "-l", str(self.every_s)], stdout=out, stderr=subprocess.DEVNULL)
        return self

    def __exit__(self, *exc) -> None:
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def summary(self) -> dict:
        if self.proc is None:
            return {"note": "nvidia-smi not found: the card's load was not sampled"}
        return summarize(self.path.read_text() if self.path.exists() else "", self.every_s)


def summarize(text: str, every_s: int) -> dict:
    """The samples of ``nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader,nounits``
    (one line per sample and GPU; unreadable lines skipped): their count, the utilisation's median, mean,
    10th and 90th percentiles (%), the most memory used (MiB), and the utilisation samples themselves."""
    util, memory = [], []
    for line in text.splitlines():
        fields = [f.strip() for f in line.split(",")]
        try:
            u, m = float(fields[0]), float(fields[1])
        except (IndexError, ValueError):
            continue
        util.append(u)
        memory.append(m)
    if not util:
        return {"samples": 0, "every_s": every_s, "note": "no readable sample"}
    deciles = statistics.quantiles(util, n=10, method="inclusive") if len(util) > 1 else [util[0]] * 9
    return {"samples": len(util), "every_s": every_s, "utilization_pct": {
        "median": statistics.median(util), "mean": round(statistics.fmean(util), 1),
        "p10": round(deciles[0], 1), "p90": round(deciles[-1], 1)},
        "memory_used_mib_max": max(memory), "utilization_samples": util}
