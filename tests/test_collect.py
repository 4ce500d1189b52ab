"""`vitfly collect` end to end: the file it writes, worker invariance, kill -9 resume, bad config."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from vitfly.cli import main
from vitfly.datamodules.schema import CAMERA_ATTR, CONTROL_HZ_ATTR, open_trajectories
from vitfly.sim.camera import CameraConfig
from vitfly.sim.collect import fly_trajectory, load_collect_config, trajectory_spec

TINY = """\
env: spheres
preset: medium
trajectories: 3
speeds: [6.5, 7.0]
seed: 11
camera:
  max_range_m: 10.0
"""


def read_all(path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        out = {}
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def assert_same_data(a, b):
    da, db = read_all(a), read_all(b)
    assert sorted(da) == sorted(db)
    for name in da:
        np.testing.assert_array_equal(da[name], db[name], err_msg=name)


@pytest.fixture(scope="module")
def tiny_config(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "tiny.yaml"
    path.write_text(TINY)
    return path


@pytest.fixture(scope="module")
def reference(tiny_config, tmp_path_factory):
    """Four trajectories collected in one process, in one go."""
    out = tmp_path_factory.mktemp("ref") / "ref.h5"
    assert (
        main(["collect", "--config", str(tiny_config), "--out", str(out), "--trajectories", "4", "--no-progress"]) == 0
    )
    return out


def test_collect_writes_the_schema(reference, capsys):
    cfg = load_collect_config(None, {"seed": 11, "speeds": [6.5, 7.0]})
    with open_trajectories(reference) as data:
        assert len(data) == 4
        for m in range(4):
            meta = data.meta(m)
            seed, speed = trajectory_spec(11, m, cfg.speeds)
            assert int(meta["seed"]) == seed
            assert float(meta["desired_speed"]) == pytest.approx(speed, abs=1e-5)
            rec = data[m]
            t = rec.length
            assert t > 200  # 58 m at <= 7 m/s, 30 Hz
            # only the original's window is logged: 2 < x < 60 m
            assert rec.position[:, 0].min() > 2.0 and rec.position[:, 0].max() < 60.0
            assert rec.depth.shape == (t, 60, 90) and rec.depth.dtype == np.uint8
            assert rec.depth.min() < 255  # obstacles or ground in view
            np.testing.assert_allclose(np.diff(rec.time), 1 / 30, atol=1e-9)
            # the per-trajectory flags agree with the rows
            if meta["success"]:
                assert rec.position[-1, 0] > 59.0 and not rec.collision.any() and meta["n_collisions"] == 0
            assert int(meta["n_collisions"]) >= int(np.any(rec.collision))
            # labels are the expert's commands: desired speed in cruise, unless every waypoint was
            # blocked (the drone within an inflated obstacle) and it fell back to (0.5, 0, 0.25)
            cruise = (rec.position[:, 0] >= 2) & (rec.position[:, 2] >= 2)
            fallback = np.all(np.isclose(rec.velocity_cmd, [0.5, 0.0, 0.25]), axis=1)
            assert fallback.mean() < 0.1
            norms = np.linalg.norm(rec.velocity_cmd[cruise & ~fallback], axis=1)
            np.testing.assert_allclose(norms, speed, rtol=1e-5)
    with h5py.File(reference, "r") as f:
        assert float(f.attrs["depth_max_m"]) == 10.0
        # the sensor travels with the data: the default camera (vision/config.yaml's rgb_camera: 100 deg
        # vertical, 640 x 480 aspect, 0.3 m in front of the body origin) and the 30 Hz control rate
        camera = json.loads(f.attrs[CAMERA_ATTR])
        assert camera == json.loads(json.dumps(dataclasses.asdict(CameraConfig())))
        assert camera["vertical_fov_deg"] == 100.0 and camera["mount_offset_m"] == [0.3, 0.0, 0.0]
        assert (camera["source_width"], camera["source_height"]) == (640, 480)
        assert float(f.attrs[CONTROL_HZ_ATTR]) == 30.0


def test_window_drops_only_ticks_outside_2_to_60_m_and_flight_fields_describe_the_whole_flight():
    windowed = load_collect_config(None, {"seed": 11, "speeds": [6.5, 7.0]})
    every = load_collect_config(None, {"seed": 11, "speeds": [6.5, 7.0], "log_every_tick": True})
    a, b = fly_trajectory(windowed, 1), fly_trajectory(every, 1)
    # the same flight: every tick starts at the start, x = 0, and runs to the goal
    assert b.position[0, 0] == 0.0 and b.position[-1, 0] > 59.5
    keep = (b.position[:, 0] > 2.0) & (b.position[:, 0] < 60.0)
    assert 0 < keep.sum() < b.length and a.length == keep.sum()
    for name in ("position", "velocity", "quat", "velocity_cmd", "time", "collision", "depth"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name)[keep], err_msg=name)
    # per-trajectory fields are the flight's, not the window's
    assert (a.n_collisions, a.success, a.seed) == (b.n_collisions, b.success, b.seed)
    # what is dropped is the take-off (x <= 2 m; the goal is crossed between ticks, so no logged x >= 60)
    assert np.all(b.position[~keep, 0] <= 2.0) and np.all(np.diff(np.flatnonzero(~keep)) == 1)


def test_log_every_tick_flag(tiny_config, tmp_path, capsys):
    out = tmp_path / "every.h5"
    args = ["collect", "--config", str(tiny_config), "--out", str(out), "--trajectories", "1", "--no-progress"]
    assert main([*args, "--log-every-tick"]) == 0
    with open_trajectories(out) as data:
        rec = data[0]
        assert rec.position[0, 0] == 0.0 and rec.position[-1, 0] >= 59.0
        assert data.config["collect"]["log_every_tick"] is True


def test_output_is_the_same_whatever_the_workers_and_storage(reference, tiny_config, tmp_path, capsys):
    out = tmp_path / "w2.h5"
    args = ["collect", "--config", str(tiny_config), "--out", str(out), "--trajectories", "4", "--workers", "2"]
    assert main([*args, "--depth-compression", "gzip", "--no-progress"]) == 0
    assert_same_data(reference, out)
    with h5py.File(reference, "r") as ref, h5py.File(out, "r") as gz:
        assert (ref["depth"].compression, gz["depth"].compression) == (None, "gzip")
    printed = capsys.readouterr().out
    assert "4 trajectories" in printed and "expert success" in printed


def test_kill_9_then_rerun_resumes_to_the_same_file(reference, tiny_config, tmp_path):
    out = tmp_path / "killed.h5"
    cmd = [sys.executable, "-m", "vitfly.cli", "collect", "--config", str(tiny_config), "--out", str(out)]
    cmd += ["--trajectories", "4", "--workers", "2", "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        committed = 0
        while committed < 1 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
            if out.exists():
                try:
                    with open_trajectories(out, check_values=False) as data:
                        committed = len(data)
                except Exception:  # noqa: BLE001 - the writer may be mid-creation
                    committed = 0
        assert proc.poll() is None, "collect finished before it could be killed; make the test config longer"
        workers = children(proc.pid)
        assert len(workers) == 2
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        # the worker processes die with it (no orphans flying trajectories nobody will write)
        deadline = time.monotonic() + 10
        while any(alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(alive(p) for p in workers)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    with open_trajectories(out, check_values=False) as data:
        survived = len(data)
    assert 1 <= survived < 4
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert f"({4 - survived} new)" in result.stdout
    assert_same_data(reference, out)


def children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(p) for p in f.read().split()]
    except OSError:
        return []


def alive(pid: int) -> bool:
    """Running (not gone, not a zombie waiting to be reaped)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_unknown_config_key_is_one_line_error_and_no_output(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(TINY + "colour: blue\n")
    out = tmp_path / "never.h5"
    assert main(["collect", "--config", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "colour" in err and str(cfg) in err
    assert not out.exists()
    cfg.write_text(TINY.replace("max_range_m: 10.0", "max_range: 10.0"))
    assert main(["collect", "--config", str(cfg), "--out", str(out)]) == 2
    assert "camera.max_range" in capsys.readouterr().err
    assert main(["collect", "--config", str(tiny_config_path(tmp_path)), "--out", str(out), "--speeds", "5", "2"]) == 2
    assert "speeds" in capsys.readouterr().err
    cfg.write_text(TINY + "  vertical_fov_deg: 190\n")
    assert main(["collect", "--config", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "field camera.vertical_fov_deg is 190.0" in err and str(cfg) in err
    cfg.write_text(TINY + "  preset: agile\n")
    assert main(["collect", "--config", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "field camera.preset is 'agile'" in err and str(cfg) in err
    cfg.write_text(TINY + "depth_compression: lz4\n")
    assert main(["collect", "--config", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "depth_compression is 'lz4'" in err and str(cfg) in err
    assert not out.exists()


def tiny_config_path(tmp_path):
    p = tmp_path / "ok.yaml"
    p.write_text(TINY)
    return p


def test_resume_with_other_settings_is_refused(reference, tiny_config, tmp_path, capsys):
    out = tmp_path / "copy.h5"
    out.write_bytes(reference.read_bytes())
    assert main(["collect", "--config", str(tiny_config), "--out", str(out), "--seed", "12", "--no-progress"]) == 2
    assert "different settings" in capsys.readouterr().err


def test_shipped_collect_config_spells_the_default_camera_and_a_preset_selects_the_other(tmp_path):
    # configs/collect/spheres.yaml writes the default camera out field by field
    assert load_collect_config("configs/collect/spheres.yaml").camera == CameraConfig()
    # camera: {preset: camera_config_yaml} is camera_config.yaml's 320 x 240 / 70 deg / 0.3 m-above camera;
    # fields given beside the preset win
    path = tmp_path / "alt.yaml"
    path.write_text(TINY + "  preset: camera_config_yaml\n  noise_std_m: 0.02\n")
    camera = load_collect_config(path).camera
    assert camera == CameraConfig(vertical_fov_deg=70.0, source_width=320, source_height=240,
                                  mount_offset_m=(0.0, 0.0, 0.3), noise_std_m=0.02)  # fmt: skip
