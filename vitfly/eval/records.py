"""Trial records: one JSON line per finished trial in ``DIR/trials.jsonl``.

A line holds who flew (policy label), what exactly was flown (``setup``: the policy's content hash,
the rollout settings' hash, the sweep seed, the preset and the scene generator's hash; see
``vitfly.eval.fingerprint``) and its hash ``setup_id``, where (env, scene seed), how fast (desired
speed, m/s), the outcome (``success_paper``: no collision; ``success_strict``: goal reached and no
collision; ``reached_goal``; why the trial ended), the metrics (``vitfly.eval.metrics.TrialMetrics``,
undefined values as ``null``) and the flown path per control tick (``time`` s, world-frame
``position`` m, ``velocity`` m/s, ``command`` m/s, ``contact`` bool) plus ``end``, the state at the
physics step that ended the trial (``time`` s, ``position`` m), enough to recompute every metric.
Paths are rounded (``PATH_DECIMALS``) *before* the metrics are computed, so recomputing from the
file gives the same numbers.

A trial's key is (label, setup_id, env, speed, trial index): a rerun resumes only the trials flown
with the same policy content, seed, preset and rollout settings. Within one directory, every record
of a label must share one setup per env (``check_consistent``), so reports never mix two policies
under one name.

Appends are crash-safe: one ``write`` per line under an exclusive ``flock`` (so shards and workers
can share one file), then flush + fsync. A torn last line (a process killed mid-write) is skipped
on reading and cut off before the next append. ``remove_records`` rewrites a file under the same
lock (temporary file + rename; appenders waiting for the lock then reopen the new file).

``OUTCOMES_FILE`` (``outcomes.jsonl.gz``, written with every report) holds the same records without
their paths and stored scenes: about 150 bytes a trial (gzipped) where ``trials.jsonl`` takes tens of
kilobytes, small enough to commit beside a published table, and enough for summaries and paired
statistics (``read_records`` reads it); plots and path metrics need ``trials.jsonl``. A directory that holds
only an outcomes file (a published table) is reported from it (``report_files``).
"""

from __future__ import annotations

import dataclasses
import fcntl
import gzip
import json
import math
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vitfly.atomic import write_bytes
from vitfly.errors import VitflyError
from vitfly.eval.fingerprint import differences

TRIALS_FILE = "trials.jsonl"
OUTCOMES_FILE = "outcomes.jsonl.gz"  # the records without their paths: what a published table commits
RECORD_SCHEMA = "vitfly.trial"
RECORD_VERSION = 2  # 2: keyed by setup_id; success_paper / success_strict; the path's end state
PATH_DECIMALS = {"time": 6, "position": 4, "velocity": 4, "command": 4}


@dataclass
class TrialRecord:
    """One finished trial. ``key`` (policy label, setup_id, env, speed, trial) identifies it."""

    policy: str
    env: str
    speed: float  # desired forward speed, m/s
    trial: int  # index within the sweep at this (env, speed)
    scene_seed: int
    success_paper: bool  # no collision (the paper's definition)
    success_strict: bool  # goal reached and no collision
    reached_goal: bool
    end_reason: str  # e.g. "goal", "timeout", "out_of_bounds"
    metrics: dict
    path: dict  # time (T,), position/velocity/command (T, 3), contact (T,), end {time, position}
    setup: dict  # vitfly.eval.fingerprint.Setup as a dict: what was flown
    setup_id: str
    preset: str = "medium"
    extra: dict = field(default_factory=dict)  # free-form: seeds, policy source, timings

    @property
    def key(self) -> tuple[str, str, str, float, int]:
        return trial_key(self.policy, self.setup_id, self.env, self.speed, self.trial)

    @property
    def has_path(self) -> bool:
        """False for a record read from ``OUTCOMES_FILE``: only the end state of its path is kept."""
        return "time" in self.path

    def path_arrays(self) -> dict[str, np.ndarray]:
        """The path as numpy arrays (float64; contact as bool); ``end_time`` (s) and ``end_position`` (3,)
        are the trial's end state (nan when not stored)."""
        if not self.has_path:
            raise VitflyError(f"trial {self.key}: the record holds no flown path (read from {OUTCOMES_FILE}?); "
                              f"plots and path metrics need {TRIALS_FILE}")
        out = {k: np.asarray(self.path[k], dtype=np.float64) for k in ("time", "position", "velocity", "command")}
        out["contact"] = np.asarray(self.path["contact"], dtype=bool)
        end = self.path.get("end") or {}
        out["end_time"] = np.float64(end.get("time", math.nan))
        out["end_position"] = np.asarray(end.get("position", [math.nan] * 3), dtype=np.float64)
        return out

    def to_json(self) -> str:
        body = {
            "schema": RECORD_SCHEMA,
            "version": RECORD_VERSION,
            "policy": self.policy,
            "setup_id": self.setup_id,
            "setup": self.setup,
            "env": self.env,
            "preset": self.preset,
            "speed": float(self.speed),
            "trial": int(self.trial),
            "scene_seed": int(self.scene_seed),
            "outcome": {"success_paper": bool(self.success_paper), "success_strict": bool(self.success_strict),
                        "reached_goal": bool(self.reached_goal), "end_reason": self.end_reason},
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
            if d.get("version") == 1:
                raise VitflyError(f"{where}: a trial record of version 1, written before trials were keyed by "
                                  "what was flown; evaluate into a new --out")
            if d.get("version") != RECORD_VERSION:
                raise VitflyError(f"{where}: field 'version' is {d.get('version')!r}, expected {RECORD_VERSION}")
            outcome = d["outcome"]
            return cls(
                policy=d["policy"], env=d["env"], preset=d["preset"], speed=float(d["speed"]),
                trial=int(d["trial"]), scene_seed=int(d["scene_seed"]),
                success_paper=bool(outcome["success_paper"]), success_strict=bool(outcome["success_strict"]),
                reached_goal=bool(outcome["reached_goal"]), end_reason=outcome["end_reason"],
                metrics={k: (math.nan if v is None else v) for k, v in d["metrics"].items()},
                path=d["path"], setup=dict(d["setup"]), setup_id=str(d["setup_id"]), extra=d.get("extra", {}),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise VitflyError(f"{where}: not a vitfly trial record ({type(err).__name__}: {err})") from None

    def without_path(self) -> TrialRecord:
        """This record as ``OUTCOMES_FILE`` stores it: the path reduced to its end state, no stored scene."""
        end = {"end": self.path["end"]} if "end" in self.path else {}
        return dataclasses.replace(self, path=end, extra={k: v for k, v in self.extra.items() if k != "scene"})


def trial_key(policy: str, setup_id: str, env: str, speed: float, trial: int) -> tuple[str, str, str, float, int]:
    return (policy, setup_id, env, round(float(speed), 6), int(trial))


def round_path(time_s, position, velocity, command, contact, end_time_s: float | None = None,
               end_position=None) -> dict:
    """The JSON form of a flown path (lists, rounded per ``PATH_DECIMALS``), with its end state when given."""
    arrays = {"time": time_s, "position": position, "velocity": velocity, "command": command}
    out = {k: np.round(np.asarray(v, dtype=np.float64), PATH_DECIMALS[k]).tolist() for k, v in arrays.items()}
    out["contact"] = [bool(c) for c in np.asarray(contact, dtype=bool)]
    if end_time_s is not None and end_position is not None:
        out["end"] = {"time": round(float(end_time_s), PATH_DECIMALS["time"]),
                      "position": np.round(np.asarray(end_position, dtype=np.float64),
                                           PATH_DECIMALS["position"]).tolist()}
    return out


def check_consistent(recs: Iterable[TrialRecord], where: str) -> None:
    """One line if a label holds trials flown with different setups in one env, or different policies,
    rollout settings, seeds or presets across envs (a report would mix them under one name)."""
    by_env: dict[tuple[str, str], TrialRecord] = {}
    by_label: dict[str, TrialRecord] = {}
    shared = ("policy_id", "rollout_id", "sweep_seed", "preset")
    for rec in recs:
        first = by_env.setdefault((rec.policy, rec.env), rec)
        other = by_label.setdefault(rec.policy, rec)
        if first.setup_id != rec.setup_id:
            diff = differences(first.setup, rec.setup)
        elif any(other.setup.get(k) != rec.setup.get(k) for k in shared):
            diff = differences({k: other.setup.get(k) for k in shared}, {k: rec.setup.get(k) for k in shared})
        else:
            continue
        raise VitflyError(f"{where}: policy label {rec.policy!r} holds trials flown with different setups "
                          f"({'; '.join(diff) or 'setup id'}); give each its own --name or --out")


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


def _open_locked(path: str | Path) -> int:
    """Open ``path`` for appending under an exclusive flock, retrying if it was replaced while we waited."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)  # renamed over (remove_records) while we waited: open the new file


def append_record(path: str | Path, record: TrialRecord) -> None:
    """Append one record as one line; durable when this returns (flush + fsync)."""
    data = (record.to_json() + "\n").encode()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fd = _open_locked(path)
    try:
        _cut_torn_tail(fd)
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)  # closing releases the lock


def write_outcomes(path: str | Path, recs: Iterable[TrialRecord]) -> None:
    """``recs`` without their paths (``TrialRecord.without_path``), sorted by key, gzipped, atomically; the same
    records give the same bytes."""
    lines = "".join(r.without_path().to_json() + "\n" for r in sorted(recs, key=lambda r: r.key))
    write_bytes(path, gzip.compress(lines.encode(), mtime=0))


def read_records(path: str | Path) -> list[TrialRecord]:
    """All complete records of one trials file, or of an outcomes file (``*.gz``); a torn last line is skipped,
    a later duplicate key wins."""
    path = Path(path)
    if not path.exists():
        return []
    data = path.read_bytes()
    if path.suffix == ".gz":
        try:
            data = gzip.decompress(data)
        except (OSError, EOFError) as err:
            raise VitflyError(f"{path}: not a gzipped trials file ({err})") from None
    text = data.decode("utf-8", errors="replace")
    lines = text.split("\n")
    if not text.endswith("\n"):
        lines = lines[:-1]  # torn tail: the trial was in flight
    by_key: dict = {}
    for i, line in enumerate(lines, start=1):
        if line.strip():
            rec = TrialRecord.from_json(line, where=f"{path}: line {i}")
            by_key[rec.key] = rec
    return list(by_key.values())


def remove_records(path: str | Path, drop: Callable[[TrialRecord], bool]) -> int:
    """Rewrite one trials file without the records for which ``drop`` is true; returns how many went.

    Under the file's lock: the kept lines go to a temporary file, fsynced, renamed over the original
    (a kill leaves either the old or the new file, never half of one).
    """
    path = Path(path)
    if not path.exists():
        return 0
    fd = _open_locked(path)
    try:
        text = os.pread(fd, os.fstat(fd).st_size, 0).decode("utf-8", errors="replace")
        lines = text.split("\n")
        if not text.endswith("\n"):
            lines = lines[:-1]  # torn tail: dropped as on reading
        keep, removed = [], 0
        for i, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            if drop(TrialRecord.from_json(line, where=f"{path}: line {i}")):
                removed += 1
            else:
                keep.append(line + "\n")
        if removed:
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            with open(tmp, "w") as fh:
                fh.writelines(keep)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
            dir_fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
        return removed
    finally:
        os.close(fd)


def iter_trial_files(out_dir: str | Path) -> Iterator[Path]:
    yield from sorted(Path(out_dir).glob("trials*.jsonl"))


def report_files(out_dir: str | Path) -> list[Path]:
    """What the reports of ``out_dir`` are made from: its ``trials*.jsonl``, else its ``OUTCOMES_FILE`` alone.

    Never both: the outcomes file is written from the trial files, and still holds the records a rerun has
    since replaced (another setup under the same label)."""
    trial_files = list(iter_trial_files(out_dir))
    outcomes = Path(out_dir) / OUTCOMES_FILE
    return trial_files or ([outcomes] if outcomes.exists() else [])


def read_report_records(out_dir: str | Path) -> list[TrialRecord]:
    """The records the reports of ``out_dir`` are made from (``report_files``), merged by key."""
    return merge_records(read_records(p) for p in report_files(out_dir))


def only_outcomes(out_dir: str | Path) -> bool:
    """True for a folder whose reports come from its ``OUTCOMES_FILE`` alone (a published table: no trials)."""
    return report_files(out_dir) == [Path(out_dir) / OUTCOMES_FILE]


def read_sweep(out_dir: str | Path) -> list[TrialRecord]:
    """Every record in ``out_dir`` (``trials*.jsonl``), merged by key."""
    return merge_records(read_records(p) for p in iter_trial_files(out_dir))


def merge_records(groups: Iterable[Iterable[TrialRecord]]) -> list[TrialRecord]:
    """Union of record collections, one record per key (first seen wins), in a stable order."""
    by_key: dict = {}
    for group in groups:
        for rec in group:
            by_key.setdefault(rec.key, rec)
    return sorted(by_key.values(), key=lambda r: (r.policy, r.setup_id, r.env, r.speed, r.trial))
