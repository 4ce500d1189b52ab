"""Sensor-model domain randomisation in the datamodule: worked frames, seeding, probability, batches.

Worked by hand for the D435 defaults with its noise off: focal length f = 424 / tan(43.5 deg) px, baseline
b = 0.05 m, disparity quantised to 1/32 px, deployed as 0.8 x z / 10 m, no depth -> 0.8.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from test_augment_mirror import record_batches
from test_datamodule import write_dataset

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.dataset import TrajectoryDataset
from vitfly.datamodules.sensor_augment import SensorRandomisation, check_sensor, sensor_coins
from vitfly.errors import VitflyError
from vitfly.sensors.stereo import ImageGeometry
from vitfly.sim.camera import CAMERA_PRESETS, CameraConfig

QUIET = {"model": "d435", "subpixel_rms_px": 0.0, "pattern_rms_px": 0.0, "occlusion": False}


def hand_d435(z_m: float) -> float:
    """The deployed value of a noiseless D435 reading of a surface at z_m, worked out step by step."""
    fb = 424.0 / math.tan(math.radians(43.5)) * 0.05  # 22.34 px m
    measured = fb / (round(fb / z_m * 32) / 32)
    return 0.8 if measured > 10.0 else 0.8 * measured / 10.0


def randomiser(values, prob=1.0) -> SensorRandomisation:
    return SensorRandomisation(check_sensor(values, prob), prob, None, 10.0)


def test_stored_frame_worked_by_hand():
    # stored uint8 51 -> 2.0 m, 128 -> 5.0196 m; 255 (the clip) and 0 read "no depth"; 5 = 0.196 m < min-Z
    stored = np.array([[51, 128, 255, 0, 5]], dtype=np.float64) / 255.0
    unit = np.tile(stored, (60, 18))
    out = randomiser(QUIET).frames(unit[None], seed=3, first_tick=0)[0]
    assert out.dtype == np.float32 and out.shape == (60, 90)
    expected = [hand_d435(2.0), hand_d435(128 / 255 * 10), 0.8, 0.8, 0.8]
    np.testing.assert_allclose(out[7, 10:15], expected, rtol=1e-6)
    assert hand_d435(2.0) == pytest.approx(0.8 * 2.00249 / 10, rel=1e-4)  # 357/32 px instead of 11.17 px


def test_seeded_by_trajectory_epoch_and_tick():
    rng = np.random.default_rng(0)
    batch = {"depth": torch.from_numpy(rng.integers(20, 200, (3, 5, 1, 60, 90), dtype=np.uint8)),
             "mask": torch.tensor([[1, 1, 1, 1, 1], [1, 1, 1, 0, 0], [1, 1, 1, 1, 0]], dtype=torch.bool),
             "traj_index": torch.tensor([4, 7, 9]), "start": torch.tensor([0, 0, 32])}
    batch["depth"][~batch["mask"]] = 0  # padding, as collated
    model = randomiser({"model": "d435"})
    first, again = model(batch, seed=1, epoch=2), model(batch, seed=1, epoch=2)
    assert torch.equal(first["depth"], again["depth"])  # reproducible
    assert not torch.equal(first["depth"], model(batch, seed=1, epoch=3)["depth"])  # a new draw per epoch
    assert batch["depth"].dtype == torch.uint8  # the input is not changed
    assert float(first["depth"][1, 3:].abs().sum()) == 0.0 and float(first["depth"][2, 4:].abs().sum()) == 0.0
    # the window starting at tick 32 is ticks 32.. of its trajectory: the same frame as a whole item from 0
    window = batch["depth"][2, :4, 0].numpy() / 255.0
    whole = model.frames(window, 123, 32)
    shifted = model.frames(np.concatenate([np.zeros((32, 60, 90)), window]), 123, 0)[32:]
    np.testing.assert_array_equal(whole, shifted)


def test_probability_zero_is_identity_and_coins_are_seeded():
    batch = {"depth": torch.full((2, 3, 1, 60, 90), 77, dtype=torch.uint8), "mask": torch.ones(2, 3, dtype=torch.bool),
             "traj_index": torch.tensor([0, 1]), "start": torch.tensor([0, 0])}
    assert randomiser({"model": "d435"}, prob=0.0)(batch, 0, 0) is batch
    traj, start = torch.arange(400), torch.zeros(400, dtype=torch.long)
    coins = sensor_coins(traj, start, 0.3, seed=0, epoch=1)
    assert 0.22 < coins.float().mean() < 0.38 and torch.equal(coins, sensor_coins(traj, start, 0.3, 0, 1))
    assert sensor_coins(traj, start, 1.0, 0, 0).all() and not sensor_coins(traj, start, 0.0, 0, 0).any()


def test_frame_delay_shows_earlier_ticks():
    unit = np.stack([np.full((60, 90), z / 10) for z in (2.0, 3.0, 4.0, 5.0)])
    out = randomiser({**QUIET, "delay_ticks": 2}).frames(unit, seed=0, first_tick=0)
    np.testing.assert_allclose(out[:, 0, 0], [hand_d435(2.0), hand_d435(2.0), hand_d435(2.0), hand_d435(3.0)],
                               rtol=1e-6)


def test_geometry_from_recorded_camera_matches_the_camera():
    for name in (None, *CAMERA_PRESETS):
        camera = CameraConfig() if name is None else CameraConfig.from_preset(name)
        values = {k: getattr(camera, k) for k in ("height", "width", "vertical_fov_deg", "horizontal_fov_deg",
                                                   "source_width", "source_height", "max_range_m")}
        geometry = ImageGeometry.from_camera_values(values)
        assert geometry.tan_half_horizontal == pytest.approx(camera.tan_half_horizontal, rel=1e-12)
        assert (geometry.height, geometry.width, geometry.max_range_m) == (camera.height, camera.width,
                                                                           camera.max_range_m)
    assert ImageGeometry() == ImageGeometry.from_camera_values(None)
    assert ImageGeometry().tan_half_horizontal == pytest.approx(CameraConfig().tan_half_horizontal, rel=1e-12)


@pytest.mark.parametrize("kwargs, message", [
    ({"sensor_prob": 1.5, "sensor": {"model": "d435"}}, r"data.sensor_prob: expected a probability in \[0, 1\]"),
    ({"sensor_prob": 0.5}, r"data.sensor: sensor_prob is 0.5 but no sensor model is set"),
    ({"sensor_prob": 0.5, "sensor": {"model": "d435", "baseline": 1}}, r"unknown field data.sensor.baseline"),
    ({"sensor_prob": 0.5, "sensor": {"model": "kinect"}}, r"field data.sensor.model is 'kinect'"),
])
def test_bad_settings_are_one_line(tmp_path, kwargs, message):
    with pytest.raises(VitflyError, match=message):
        TrajectoryDataModule(str(tmp_path / "x.h5"), **kwargs)


def test_dataset_of_modelled_frames_is_refused(tmp_path):
    import h5py

    path = write_dataset(tmp_path / "d.h5", [4, 5, 6])
    with h5py.File(path, "a") as f:
        f.attrs["config"] = json.dumps({"collect": {"sensor": {"model": "d435"}}})
    dm = TrajectoryDataModule(path, val_fraction=0.34, sensor_prob=0.5, sensor={"model": "d435"})
    with pytest.raises(VitflyError, match=r"d.h5: field config.collect.sensor is 'd435': its frames are already"):
        dm.setup("fit")
    TrajectoryDataModule(path, val_fraction=0.34).setup("fit")  # without randomisation it trains as before


@pytest.mark.parametrize("resident", [False, True])
def test_datamodule_models_training_batches_only(tmp_path, one_torch_thread, resident):
    path = write_dataset(tmp_path / "d.h5", [6, 9, 4, 7, 5])
    ds = TrajectoryDataset(path)
    dm = TrajectoryDataModule(path, batch_size=2, val_fraction=0.4, cache_mb=8, mirror_prob=1.0, sensor_prob=1.0,
                              sensor=QUIET, resident=resident)
    record = record_batches(dm, tmp_path)
    assert record.train and record.val
    expected_value = np.vectorize(lambda u: 0.8 if u in (0, 255) or u / 25.5 < 0.28 else hand_d435(u / 25.5))
    for batches, modelled in ((record.train, True), (record.val, False)):
        for batch in batches:
            for i, m in enumerate(batch["traj_index"].tolist()):
                raw = ds[m]["depth"].numpy()
                n = raw.shape[0]
                if modelled:  # mirrored first, then modelled (noise off: pixel by pixel)
                    expected = expected_value(raw[:, :, ::-1]).astype(np.float32)
                else:
                    expected = raw / np.float32(255.0)
                np.testing.assert_allclose(batch["depth"][i, :n, 0].numpy(), expected, rtol=1e-5, atol=1e-7)
