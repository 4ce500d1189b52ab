"""Trial records: one JSON line per finished trial in ``DIR/trials.jsonl``.

A line holds who flew (policy label), where (env, preset, scene seed), how fast (desired speed,
m/s), the outcome and why the trial ended, the metrics (``vitfly.eval.metrics.TrialMetrics``,
undefined values as ``null``) and the flown path per control tick (``time`` s, world-frame
``position`` m, ``velocity`` m/s, ``command`` m/s, ``contact`` bool), enough to recompute every
metric. Paths are rounded (``PATH_DECIMALS``) *before* the metrics are computed, so recomputing
from the file gives the same numbers.

Appends are crash-safe: one ``write`` per line under an exclusive ``flock`` (so shards and workers
can share one file), then flush + fsync. A torn last line (a process killed mid-write) is skipped
on reading and cut off before the next append.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vitfly.errors import VitflyError

TRIALS_FILE = "trials.jsonl"
RECORD_SCHEMA = "vitfly.trial"
RECORD_VERSION = 1
PATH_DECIMALS = {"time": 6, "position": 4, "velocity": 4, "command": 4}


@dataclass
class TrialRecord:
    """One finished trial. ``key`` (policy, env, speed, trial) identifies it within a sweep."""

    policy: str
    env: str
    speed: float  # desired forward speed, m/s
    trial: int  # index within the sweep at this (env, speed)
    scene_seed: int
    success: bool
    reached_goal: bool
    end_reason: str  # e.g. "goal", "timeout", "out_of_bounds"
    metrics: dict
    path: dict  # time (T,), position/velocity/command (T, 3), contact (T,)
    preset: str = "medium"
    extra: dict = field(default_factory=dict)  # free-form: seeds, policy source, timings

    @property
    def key(self) -> tuple[str, str, float, int]:
        return trial_key(self.policy, self.env, self.speed, self.trial)

    def path_arrays(self) -> dict[str, np.ndarray]:
        """The path as numpy arrays (float64; contact as bool)."""
        out = {k: np.asarray(self.path[k], dtype=np.float64) for k in ("time", "position", "velocity", "command")}
        out["contact"] = np.asarray(self.path["contact"], dtype=bool)
        return out

    def to_json(self) -> str:
        body = {
            "schema": RECORD_SCHEMA,
            "version": RECORD_VERSION,
            "policy": self.policy,
            "env": self.env,
            "preset": self.preset,
            "speed": float(self.speed),
            "trial": int(self.trial),
            "scene_seed": int(self.scene_seed),
            "outcome": {"success": bool(self.success), "reached_goal": bool(self.reached_goal),
                        "end_reason": self.end_reason},
            "metrics": _nan_to_none(self.metrics),
            "path": self.path,
            "extra": _nan_to_none(self.extra),
        }
        return json.dumps(body, separators=(",", ":"), allow_nan=False)

    @classmethod
    def from_json(cls, line: str, where: str = "trial record") -> TrialRecord:
        try:
            d = json.loads(line)
            if d.get("schema") != RECORD_SCHEMA:
                raise VitflyError(f"{where}: field 'schema' is {d.get('schema')!r}, expected {RECORD_SCHEMA!r}")
            if d.get("version") != RECORD_VERSION:
                raise VitflyError(f"{where}: field 'version' is {d.get('version')!r}, expected {RECORD_VERSION}")
            return cls(
                policy=d["policy"], env=d["env"], preset=d.get("preset", "medium"), speed=float(d["speed"]),
                trial=int(d["trial"]), scene_seed=int(d["scene_seed"]), success=bool(d["outcome"]["success"]),
                reached_goal=bool(d["outcome"]["reached_goal"]), end_reason=d["outcome"]["end_reason"],
                metrics={k: (math.nan if v is None else v) for k, v in d["metrics"].items()},
                path=d["path"], extra=d.get("extra", {}),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise VitflyError(f"{where}: not a vitfly trial record ({type(err).__name__}: {err})") from None


def trial_key(policy: str, env: str, speed: float, trial: int) -> tuple[str, str, float, int]:
    return (policy, env, round(float(speed), 6), int(trial))


def round_path(time_s, position, velocity, command, contact) -> dict:
    """The JSON form of a flown path (lists, rounded per ``PATH_DECIMALS``)."""
    arrays = {"time": time_s, "position": position, "velocity": velocity, "command": command}
    out = {k: np.round(np.asarray(v, dtype=np.float64), PATH_DECIMALS[k]).tolist() for k, v in arrays.items()}
    out["contact"] = [bool(c) for c in np.asarray(contact, dtype=bool)]
    return out


def _nan_to_none(value):
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return None if not math.isfinite(value) else float(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def _cut_torn_tail(fd: int) -> None:
    """Truncate a last line without its newline (a writer killed mid-line)."""
    size = os.lseek(fd, 0, os.SEEK_END)
    if size == 0:
        return
    pos, chunk = size, 1 << 16
    while pos > 0:
        start = max(0, pos - chunk)
        data = os.pread(fd, pos - start, start)
        if start + len(data) == size and data.endswith(b"\n"):
            return
        nl = data.rfind(b"\n")
        if nl >= 0:
            os.ftruncate(fd, start + nl + 1)
            return
        pos = start
    os.ftruncate(fd, 0)


def append_record(path: str | Path, record: TrialRecord) -> None:
    """Append one record as one line; durable when this returns (flush + fsync)."""
    data = (record.to_json() + "\n").encode()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        _cut_torn_tail(fd)
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)  # closing releases the lock


def read_records(path: str | Path) -> list[TrialRecord]:
    """All complete records of one trials file (a torn last line is skipped; a later duplicate key wins)."""
    path = Path(path)
    if not path.exists():
        return []
    text = path.read_bytes().decode("utf-8", errors="replace")
    lines = text.split("\n")
    if not text.endswith("\n"):
        lines = lines[:-1]  # torn tail: the trial was in flight
    by_key: dict = {}
    for i, line in enumerate(lines, start=1):
        if line.strip():
            rec = TrialRecord.from_json(line, where=f"{path}: line {i}")
            by_key[rec.key] = rec
    return list(by_key.values())


def iter_trial_files(out_dir: str | Path) -> Iterator[Path]:
    yield from sorted(Path(out_dir).glob("trials*.jsonl"))


def read_sweep(out_dir: str | Path) -> list[TrialRecord]:
    """Every record in ``out_dir`` (``trials*.jsonl``), merged by key."""
    return merge_records(read_records(p) for p in iter_trial_files(out_dir))


def merge_records(groups: Iterable[Iterable[TrialRecord]]) -> list[TrialRecord]:
    """Union of record collections, one record per key (first seen wins), in a stable order."""
    by_key: dict = {}
    for group in groups:
        for rec in group:
            by_key.setdefault(rec.key, rec)
    return sorted(by_key.values(), key=lambda r: (r.policy, r.env, r.speed, r.trial))
