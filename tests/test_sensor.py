"""The sensor travels with the model: dataset attributes -> checkpoint -> `vitfly evaluate`, which flies with it
by default, says so, and refuses a contradicting option in one line."""

from __future__ import annotations

import dataclasses
import json

import h5py
import numpy as np
import pytest
import torch
from test_datamodule import learnable_record, write_dataset

from vitfly.cli import main
from vitfly.datamodules.legacy_import import original_camera
from vitfly.datamodules.schema import TrajectoryWriter, open_trajectories
from vitfly.errors import VitflyError
from vitfly.eval import records
from vitfly.eval.config import SweepConfig
from vitfly.eval.sensor import camera_dict, camera_from_dict, flight_sensor, resolve_sensor
from vitfly.eval.sweep import rollout_config
from vitfly.sim.camera import CameraConfig
from vitfly.training import train_policy
from vitfly.zoo import create_model, save_checkpoint
from vitfly.zoo.checkpoint import load_sensor

# a camera other than the default in a field every version of CameraConfig has
CAMERA = camera_dict(dataclasses.replace(CameraConfig(), horizontal_fov_deg=80.0, max_range_m=20.0))
FAST_FIT = dict(max_epochs=1, batch_size=2, progress_bar=False, policy_kwargs={"tbptt_steps": 8})


def write_sensor_dataset(path, depth_max_m=20.0, camera=CAMERA, control_hz=15.0, lengths=(6, 5, 7, 4)) -> str:
    with TrajectoryWriter(path, {}, depth_max_m=depth_max_m, camera=camera, control_hz=control_hz) as writer:
        for seed, length in enumerate(lengths):
            writer.append(learnable_record(seed, length))
    return str(path)


def test_dataset_attributes_are_read_and_checked(tmp_path):
    path = write_sensor_dataset(tmp_path / "d.h5")
    with h5py.File(path, "r") as f:  # the attribute names and forms other tools write
        assert json.loads(f.attrs["camera"]) == CAMERA and float(f.attrs["control_hz"]) == 15.0
    with open_trajectories(path) as tf:
        assert tf.sensor == {"depth_max_m": 20.0, "camera": CAMERA, "control_hz": 15.0}
    with open_trajectories(write_dataset(tmp_path / "plain.h5", [5, 6])) as tf:
        assert tf.sensor == {"depth_max_m": 10.0, "camera": None, "control_hz": None}
    bad = [
        ("camera", "{not json", "attribute 'camera' must be a JSON object"),
        ("camera", "[1, 2]", "attribute 'camera' must be a JSON object"),
        ("control_hz", -3.0, "attribute 'control_hz' is -3.0, expected a positive"),
    ]
    for attr, value, message in bad:
        with h5py.File(path, "r+") as f:
            f.attrs["camera"], f.attrs["control_hz"] = json.dumps(CAMERA), 15.0
            f.attrs[attr] = value
        with pytest.raises(VitflyError, match=message):
            open_trajectories(path)
    # a writer resuming the file must record the same sensor
    path2 = write_sensor_dataset(tmp_path / "e.h5")
    with pytest.raises(VitflyError, match="attribute 'control_hz' is 15.0 but this writer records 30.0"):
        TrajectoryWriter(path2, {}, depth_max_m=20.0, camera=CAMERA, control_hz=30.0)


def test_fit_stores_the_datasets_sensor_and_a_resume_on_another_sensor_is_refused(tmp_path):
    data = write_sensor_dataset(tmp_path / "d.h5")
    best = train_policy(data, "convnet", tmp_path / "run", **FAST_FIT)
    ckpt = torch.load(best, weights_only=True)
    assert ckpt["sensor"] == {"depth_max_m": 20.0, "camera": CAMERA, "control_hz": 15.0}
    assert load_sensor(best) == ckpt["sensor"]
    # a dataset without the attributes: the range is known, camera and rate are not
    plain = write_dataset(tmp_path / "plain.h5", [6, 5, 7])
    assert load_sensor(train_policy(plain, "convnet", tmp_path / "run2", **FAST_FIT)) == {
        "depth_max_m": 10.0, "camera": None, "control_hz": None}  # fmt: skip
    # the same trajectories recorded with a 10 m range: resuming the 20 m run on them mixes two sensors
    other = write_sensor_dataset(tmp_path / "d10.h5", depth_max_m=10.0, camera={**CAMERA, "max_range_m": 10.0})
    with pytest.raises(VitflyError, match=r"trained on data from another sensor .*depth_max_m: 20.0 vs 10.0"):
        train_policy(other, "convnet", tmp_path / "run", max_epochs=2, batch_size=2, progress_bar=False)


def cfg_for(**kwargs) -> SweepConfig:
    return SweepConfig(policy="x.ckpt", **kwargs)


def test_resolve_flies_the_checkpoints_sensor_and_refuses_contradictions():
    trained = {"depth_max_m": 20.0, "camera": CAMERA, "control_hz": 15.0}
    cfg, note = resolve_sensor(cfg_for(), trained, "x.ckpt")
    rollout = rollout_config(cfg)
    assert rollout.camera == camera_from_dict(CAMERA, "test") and rollout.control_hz == 15.0
    assert rollout.camera.max_range_m == 20.0 and rollout.camera.horizontal_fov_deg == 80.0
    assert note.startswith("sensor: flying x.ckpt with the sensor it was trained with: depth range 20 m, control 15")
    # options that agree are fine; a contradicting one is one line naming the option and both values
    assert resolve_sensor(cfg_for(control_hz=15.0), trained, "x.ckpt")[0].control_hz == 15.0
    with pytest.raises(VitflyError, match=r"^--control-hz contradicts x.ckpt.*control_hz: 15.0 vs 30.0"):
        resolve_sensor(cfg_for(control_hz=30.0), trained, "x.ckpt")
    with pytest.raises(VitflyError, match=r"^--camera contradicts .*camera.horizontal_fov_deg: 80.0 vs 70"):
        resolve_sensor(cfg_for(camera={"horizontal_fov_deg": 70}), trained, "x.ckpt")
    with pytest.raises(VitflyError, match=r"^--depth-max-m contradicts .*depth_max_m: 20.0 vs 10.0"):
        resolve_sensor(cfg_for(depth_max_m=10.0), trained, "x.ckpt")
    # ... unless asked for, and then the note says so
    cfg, note = resolve_sensor(cfg_for(control_hz=30.0, override_sensor=True), trained, "x.ckpt")
    assert rollout_config(cfg).control_hz == 30.0 and note.startswith("sensor: --override-sensor: flying x.ckpt")
    # camera and rate unknown (a dataset without the attributes): the defaults, and the note says which
    cfg, note = resolve_sensor(cfg_for(), {"depth_max_m": 12.0, "camera": None, "control_hz": None}, "y.ckpt")
    default_camera, default_rate = flight_sensor(SweepConfig())
    assert rollout_config(cfg).camera == dataclasses.replace(default_camera, max_range_m=12.0)
    assert rollout_config(cfg).control_hz == default_rate
    assert "y.ckpt records its depth range but not its camera or control_hz" in note
    cfg, note = resolve_sensor(cfg_for(control_hz=20.0), None, "z.pth")  # nothing recorded: options + defaults
    assert rollout_config(cfg).control_hz == 20.0 and "does not record the sensor" in note and "control_hz" in note


def test_camera_settings_that_do_not_fit_are_one_line():
    with pytest.raises(VitflyError, match="x.ckpt \\(sensor.camera\\): camera field 'lens_model' is not a setting"):
        resolve_sensor(cfg_for(), {"depth_max_m": 10.0, "camera": {"lens_model": "fisheye"}, "control_hz": None},
                       "x.ckpt")  # fmt: skip
    with pytest.raises(VitflyError, match="--control-hz: physics_hz \\(240.0\\) must be a multiple of control_hz"):
        resolve_sensor(cfg_for(control_hz=7.0), None, "x.ckpt")
    # JSON lists come back as the tuples the dataclass holds
    assert camera_from_dict(camera_dict(CameraConfig()), "t") == CameraConfig()


def test_a_camera_preset_stands_for_its_fields():
    # --camera preset=camera_config_yaml with nothing recorded: camera_config.yaml's camera is flown
    cfg, _ = resolve_sensor(cfg_for(camera={"preset": "camera_config_yaml"}), None, "z.pth")
    assert rollout_config(cfg).camera == CameraConfig.from_preset("camera_config_yaml")
    # against a checkpoint trained with the default camera its fields contradict, each named
    trained = {"depth_max_m": 10.0, "camera": camera_dict(CameraConfig()), "control_hz": 30.0}
    with pytest.raises(VitflyError, match=r"^--camera contradicts .*camera.mount_offset_m: \[0.3, 0.0, 0.0\] vs "
                                          r"\[0.0, 0.0, 0.3\].*camera.vertical_fov_deg: 100.0 vs 70.0"):  # fmt: skip
        resolve_sensor(cfg_for(camera={"preset": "camera_config_yaml"}), trained, "x.ckpt")
    # the default's own name agrees with it
    cfg, _ = resolve_sensor(cfg_for(camera={"preset": "vision_config_yaml"}), trained, "x.ckpt")
    assert cfg.camera == camera_dict(CameraConfig())
    with pytest.raises(VitflyError, match=r"^--camera: field camera.preset is 'agile'; expected one of"):
        resolve_sensor(cfg_for(camera={"preset": "agile"}), None, "z.pth")


def test_legacy_import_records_the_original_camera_and_no_rate(tmp_path):
    from test_import_legacy import make_folder

    from vitfly.datamodules.legacy_import import import_legacy

    make_folder(tmp_path / "src", "a", 6, seed=1)
    import_legacy(tmp_path / "src", tmp_path / "legacy.h5", depth_max_m=10.0)
    with open_trajectories(tmp_path / "legacy.h5") as tf:
        # the camera visionsim_node rendered with (vision/config.yaml's rgb_camera; its camera_config.yaml is
        # skipped): 640 x 480 at 100 degrees vertical, 0.3 m in front of the body origin, resized to 90 x 60
        assert tf.sensor["camera"] == {
            "height": 60,
            "width": 90,
            "vertical_fov_deg": 100.0,
            "source_width": 640,
            "source_height": 480,
            "mount_offset_m": [0.3, 0.0, 0.0],
            "max_range_m": 10.0,
        }
        assert tf.sensor["control_hz"] is None  # the original's logging rate is not a known constant


@pytest.mark.skipif("vertical_fov_deg" not in {f.name for f in dataclasses.fields(CameraConfig)},
                    reason="this CameraConfig does not model the original camera yet")  # fmt: skip
def test_the_original_camera_is_the_simulators_default_camera():
    assert camera_from_dict(original_camera(10.0), "legacy") == CameraConfig()


FAST_EVAL = ["--speeds", "3", "--trials", "1", "--timeout", "1.0", "--no-gif", "--no-plots", "--no-progress",
             "--threads", "1"]  # fmt: skip


def test_evaluate_flies_with_the_checkpoints_rate_and_says_so(tmp_path, capsys):
    torch.manual_seed(0)
    ckpt = tmp_path / "net.ckpt"
    sensor = {"depth_max_m": 20.0, "camera": CAMERA, "control_hz": 15.0}
    save_checkpoint(create_model("convnet"), "convnet", True, ckpt, sensor=sensor)
    assert main(["evaluate", "--policy", str(ckpt), "--out", str(tmp_path / "a"), *FAST_EVAL]) == 0
    out = capsys.readouterr().out
    assert f"sensor: flying {ckpt} with the sensor it was trained with: depth range 20 m, control 15 Hz" in out
    (rec,) = records.read_sweep(tmp_path / "a")
    np.testing.assert_allclose(np.diff(rec.path_arrays()["time"]), 1 / 15, atol=1e-3)  # one tick = 1 / 15 s
    # a contradicting option: one line, nothing flown
    assert main(["evaluate", "--policy", str(ckpt), "--out", str(tmp_path / "b"), "--control-hz", "30",
                 *FAST_EVAL]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vitfly: error: --control-hz contradicts") and "15.0 vs 30.0" in err[0]
    assert not (tmp_path / "b").exists()
    # --camera reaches the presets: camera_config.yaml's camera contradicts the checkpoint's (horizontal fov 80)
    assert main(["evaluate", "--policy", str(ckpt), "--out", str(tmp_path / "b"), "--camera",
                 "preset=camera_config_yaml", *FAST_EVAL]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vitfly: error: --camera contradicts") and "70.0" in err[0]
    assert main(["evaluate", "--policy", str(ckpt), "--out", str(tmp_path / "c"), "--control-hz", "30",
                 "--override-sensor", *FAST_EVAL]) == 0  # fmt: skip
    (rec,) = records.read_sweep(tmp_path / "c")
    np.testing.assert_allclose(np.diff(rec.path_arrays()["time"]), 1 / 30, atol=1e-3)
