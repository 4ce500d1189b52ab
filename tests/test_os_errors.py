"""Errors of the operating system are bad input too: one `vitfly: error:` line naming the path, exit 2, no
traceback; a collect or evaluate that meets a full disk keeps what it committed and resumes once space is back."""

import errno
import json
from pathlib import Path

import h5py
import pytest

from vitfly.cli import main, os_error_line
from vitfly.eval import records

REPO = Path(__file__).resolve().parents[1]


def one_error_line(capsys, path: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vitfly: error: ") and "Traceback" not in err[0], err
    assert path in err[0]
    return err[0]


@pytest.mark.parametrize("argv, path", [
    (["collect", "--out", "/proc/x.h5", "--trajectories", "1", "--no-progress"], "/proc/x.h5"),
    (["evaluate", "--policy", "straight", "--trials", "1", "--speeds", "3", "--out", "/proc/nope"], "/proc/nope"),
    (["export", str(REPO / "weights/convnet.safetensors"), "--out", "/proc/x.onnx"], "/proc/x.onnx"),
])
def test_unwritable_outputs_are_one_line(argv, path, capsys):
    assert main(argv) == 2
    line = one_error_line(capsys, path)
    assert "No such file or directory" in line and ".tmp" not in line


def test_fit_into_an_unwritable_root_is_one_line(capsys, tmp_path):
    assert main(["fit", "--config", str(REPO / "configs/fit/convnet.yaml"), "--trainer.default_root_dir", "/proc/nope",
                 "--data.data_path", str(tmp_path / "missing.h5")]) == 2
    one_error_line(capsys, "/proc/nope")


def test_os_error_lines():
    assert os_error_line(OSError(errno.ENOSPC, "No space left on device", "/data/x.h5")) == (
        "/data/x.h5: No space left on device; free some space and rerun the same command to resume")
    assert os_error_line(PermissionError(errno.EACCES, "Permission denied", "/srv/.out.h5.tmp-123")) == (
        "/srv/out.h5: Permission denied; choose a location you may write to")
    h5 = FileNotFoundError(errno.ENOENT, "Unable to synchronously create file (unable to open file: name = "
                           "'/proc/.x.h5.tmp-14', errno = 2, error message = 'No such file or directory', flags = 13)")
    assert os_error_line(h5) == "/proc/x.h5: No such file or directory; check that the folder exists and is writable"


def _full_disk(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


TINY = "env: spheres\npreset: medium\ntrajectories: 3\nspeeds: [6.5, 7.0]\nseed: 11\n"


def test_collect_meets_a_full_disk_and_resumes(tmp_path, capsys, monkeypatch):
    from test_collect import assert_same_data

    from vitfly.datamodules.schema import TrajectoryWriter, open_trajectories

    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY)
    args = ["collect", "--config", str(cfg), "--trajectories", "3", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "ref.h5")]) == 0
    real_append, calls = TrajectoryWriter.append, []

    def disk_fills_in_third(self, rec):
        calls.append(rec)
        if len(calls) == 3:  # the rows are written, then the disk is full before the commit
            monkeypatch.setattr(h5py.File, "flush", _full_disk)
        real_append(self, rec)

    monkeypatch.setattr(TrajectoryWriter, "append", disk_fills_in_third)
    out = tmp_path / "out.h5"
    assert main([*args, "--out", str(out)]) == 2
    assert "No space left on device; free some space" in one_error_line(capsys, "")
    monkeypatch.undo()  # space is back
    with open_trajectories(out) as tf:
        assert len(tf) == 2  # everything committed before the full disk is kept
    assert main([*args, "--out", str(out)]) == 0
    assert_same_data(out, tmp_path / "ref.h5")


def test_evaluate_meets_a_full_disk_and_resumes(tmp_path, capsys, monkeypatch):
    from test_eval_sweep import FAST

    real_append, calls = records.append_record, []

    def disk_fills_in_third(path, rec):
        calls.append(rec)
        if len(calls) == 3:  # half the line reaches the file, then the disk is full
            with open(path, "ab") as f:
                f.write(rec.to_json().encode()[:100])
            _full_disk()
        real_append(path, rec)

    monkeypatch.setattr(records, "append_record", disk_fills_in_third)
    out = tmp_path / "eval"
    argv = ["evaluate", "--out", str(out), *FAST, "--policy", "straight", "--speeds", "3", "6", "--trials", "2"]
    assert main(argv) == 2
    assert "No space left on device" in one_error_line(capsys, "")
    assert len(records.read_sweep(out)) == 2 and not (out / "summary.csv").exists()
    monkeypatch.undo()
    assert main(argv) == 0
    flown = records.read_sweep(out)
    assert len(flown) == 4 and len({r.key for r in flown}) == 4
    assert all(json.loads(line) for line in (out / "trials.jsonl").read_text().splitlines())
