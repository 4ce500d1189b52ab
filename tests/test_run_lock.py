"""One training process per run folder (``vitfly.training.run_lock``): a second process on a run another live
process trains is refused in one line naming that process, writes nothing into the run, and a second
``vitfly reproduce`` on the same study trains the runs the first is not on."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from test_datamodule import write_dataset

from vitfly.training.run_lock import LOCK_NAME, RunBusy, run_lock, training_now, who_holds

REPO = Path(__file__).resolve().parents[1]

HOLD = """
import sys
from vitfly.training.run_lock import run_lock
with run_lock(sys.argv[1]):
    print("held", flush=True)
    sys.stdin.read()  # until the test closes the pipe (or kills this process)
"""


class Holder:
    """Another process holding ``run_dir``'s lock until :meth:`release` (a clean exit) or :meth:`kill`."""

    def __init__(self, run_dir: Path):
        self.proc = subprocess.Popen([sys.executable, "-c", HOLD, str(run_dir)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, cwd=REPO)
        assert self.proc.stdout.readline().strip() == "held"

    def release(self) -> None:
        self.proc.stdin.close()
        assert self.proc.wait(timeout=60) == 0

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=60)


def test_a_second_process_is_told_which_process_trains_the_run(tmp_path):
    run = tmp_path / "run"
    holder = Holder(run)
    try:
        record = json.loads((run / LOCK_NAME).read_text())
        assert record["pid"] == holder.proc.pid
        with pytest.raises(RunBusy, match=rf"{run}: pid {holder.proc.pid} on .*, since .* is training this run"):
            with run_lock(run):
                pass
    finally:
        holder.release()
    assert not (run / LOCK_NAME).exists()  # a clean exit removes the file
    with run_lock(run):  # and the run is free again
        assert json.loads((run / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert not (run / LOCK_NAME).exists()


def test_training_now_names_the_live_holder_and_touches_nothing(tmp_path):
    run = tmp_path / "run"
    assert training_now(run) is None and not run.exists()  # no folder, no file made
    holder = Holder(run)
    try:
        assert training_now(run)["pid"] == holder.proc.pid
        assert training_now(run)["pid"] == holder.proc.pid  # asking twice lets go of nothing it holds
    finally:
        holder.kill()
    assert (run / LOCK_NAME).exists() and training_now(run) is None  # a killed holder's file: nobody trains


def test_a_killed_holder_never_blocks_the_next_training(tmp_path):
    run = tmp_path / "run"
    holder = Holder(run)
    holder.kill()
    assert (run / LOCK_NAME).exists()  # left behind by the kill, but no longer locked
    with run_lock(run):
        assert json.loads((run / LOCK_NAME).read_text())["pid"] == os.getpid()


def test_ddp_ranks_other_than_zero_run_inside_rank_zeros_lock(tmp_path, monkeypatch):
    run = tmp_path / "run"
    holder = Holder(run)
    try:
        monkeypatch.setenv("LOCAL_RANK", "1")  # Lightning's subprocess launcher runs the caller again per rank
        with run_lock(run):
            pass
        monkeypatch.setenv("LOCAL_RANK", "0")
        with pytest.raises(RunBusy):
            with run_lock(run):
                pass
    finally:
        holder.release()


def test_train_policy_on_a_busy_run_writes_nothing(tmp_path):
    from vitfly.training import train_policy

    data = write_dataset(tmp_path / "d.h5", [12, 9, 15, 7, 11])
    run = tmp_path / "run"
    holder = Holder(run)
    try:
        with pytest.raises(RunBusy, match=f"pid {holder.proc.pid}"):
            train_policy(data, "convnet", run, max_epochs=1, batch_size=2, progress_bar=False)
        assert sorted(p.name for p in run.iterdir()) == [LOCK_NAME]  # no split, metrics or checkpoint of ours
    finally:
        holder.release()
    ckpt = train_policy(data, "convnet", run, max_epochs=1, batch_size=2, progress_bar=False)
    assert ckpt.exists() and not (run / LOCK_NAME).exists()


def test_a_second_reproduce_trains_the_runs_the_first_is_not_on(tmp_path, monkeypatch, capsys):
    from vitfly.workflows.reproduce import RunsBusy, run_reproduce
    from vitfly.workflows.reproduce_config import load_reproduce_config

    monkeypatch.chdir(REPO)
    cfg = yaml.safe_load((REPO / "configs" / "reproduce.yaml").read_text())
    cfg["presets"]["tiny"]["train"].update(models=["convnet"], nostate_models=["convnet"], publish_models=[])
    path = tmp_path / "reproduce.yaml"
    path.write_text(yaml.safe_dump(cfg))
    cfg = load_reproduce_config(path, "tiny", {"out": str(tmp_path / "study"), "data": str(tmp_path / "d.h5")})
    run_reproduce(cfg, ["data"], progress=False)
    state, nostate = tmp_path / "study/train/convnet-state", tmp_path / "study/train/convnet-nostate"
    holder = Holder(state)  # the first process is on the state run
    try:
        with pytest.raises(RunsBusy, match=r"train: convnet-state still training in another process"):
            run_reproduce(cfg, ["train", "evaluate"], progress=False)  # evaluate never starts
        assert f"[train] {state}: skipped here, pid {holder.proc.pid} on" in capsys.readouterr().out
        assert (nostate / "done.json").exists() and not (state / "done.json").exists()
        assert not (tmp_path / "study/eval").exists()
    finally:
        holder.release()
    run_reproduce(cfg, ["train"], progress=False)  # run again when the other process has ended
    assert (state / "done.json").exists()
    assert "[train] done before: " + str(nostate) in capsys.readouterr().out


def test_every_message_names_the_holder_alike():
    # RunBusy, gpu.py's status and its unpack refusal all say who holds a run with who_holds
    holder = {"pid": 4242, "host": "lab-3", "since": "2026-11-30 08:00:00"}
    assert who_holds(holder) == "pid 4242 on lab-3, since 2026-11-30 08:00:00"
    assert who_holds({"pid": 7}) == "pid 7 on ?"
    assert who_holds({}) == "another process"  # it holds the lock and has not yet written who it is
    assert str(RunBusy(Path("runs/x"), holder)).startswith("runs/x: pid 4242 on lab-3, since 2026-11-30 08:00:00, is")
