"""Stereo depth sensor model (d435): noise growth, ranges, occlusion band, propellers, delay, seeding, options."""

import math

import numpy as np
import pytest

from vitfly.sim.camera import CameraConfig, DepthCamera
from vitfly.sim.policies import StraightPolicy
from vitfly.sim.rollout import RolloutConfig, run_episodes
from vitfly.sim.scenes import Scene, make_scene
from vitfly.sim.sensor_models import (
    FrameDelay,
    StereoDepthConfig,
    StereoDepthSensor,
    occlusion_mask,
    sensor_from_dict,
)

CAM = CameraConfig()


def _flat(z: float) -> np.ndarray:
    return np.full((CAM.height, CAM.width), z)


def test_noise_std_grows_with_depth_squared():
    # many pixels and ticks of a flat wall at 2 m and 4 m: the std ratio is ~ (4 / 2)^2 = 4
    cfg = StereoDepthConfig(occlusion=False, disparity_step_px=1e-6)
    sensor = StereoDepthSensor(cfg, CAM)
    stds = []
    for z in (2.0, 4.0):
        frames = np.stack([sensor.metric(_flat(z), seed=seed, tick=t) for seed in range(4) for t in range(5)])
        stds.append(frames.std())
        # worked value: sigma_z = z^2 sigma_d / (f b), f = 424 / tan(43.5 deg) = 446.8 px, b = 0.05 m
        expected = z * z * math.hypot(0.08, 0.05) / (446.8 * 0.05)
        assert frames.std() == pytest.approx(expected, rel=0.05)
    assert stds[1] / stds[0] == pytest.approx(4.0, rel=0.08)


def test_disparity_is_quantised():
    cfg = StereoDepthConfig(occlusion=False, subpixel_rms_px=0.0, pattern_rms_px=0.0)
    out = StereoDepthSensor(cfg, CAM).metric(_flat(3.0), 0, 0)
    fb = cfg.focal_px * cfg.baseline_m
    steps = fb / out / cfg.disparity_step_px
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    assert abs(out[0, 0] - 3.0) < 3.0**2 * cfg.disparity_step_px / fb  # within half a step either way


def test_ranges_invalid_and_deployment_values():
    cfg = StereoDepthConfig(occlusion=False)
    sensor = StereoDepthSensor(cfg, CAM)
    depth = _flat(5.0)
    depth[:10] = 0.2  # below the 0.28 m min range
    depth[10:20] = np.inf  # nothing hit
    depth[20:30] = 30.0  # beyond the 10 m max range
    out = sensor.metric(depth, 1, 0)
    assert np.isnan(out[:30]).all() and np.isfinite(out[30:]).all()
    image = sensor.image(depth, 1, 0)
    assert np.all(image[:30] == np.float32(0.8))  # the original's fixed value for no depth
    assert abs(float(image[30:].mean()) - 0.8 * 5.0 / 10.0) < 0.005 and image[30:].max() < 0.5  # 0.8 z / 10


def test_step_edge_invalid_band_has_predicted_width_on_the_left_of_the_near_surface():
    # fronto-parallel step: far wall 6 m on the left half, near wall 1 m from column 45 on
    depth = _flat(6.0)
    depth[:, 45:] = 1.0
    f_out = 0.5 * CAM.width / CAM.tan_half_horizontal
    band = f_out * 0.05 * (1 / 1.0 - 1 / 6.0)  # disparity difference, output pixels
    mask = occlusion_mask(depth, f_out, 0.05)
    assert not mask[:, 45:].any()  # the near surface is seen by both imagers
    width = mask.sum(axis=1)
    assert np.all(width == width[0])
    assert abs(width[0] - band) < 1.0 and width[0] >= 1
    assert mask[0, 45 - width[0] : 45].all()  # adjacent to the edge, in the far surface, on its left
    # the sensor applies it: the band reads "no depth"
    out = StereoDepthSensor(StereoDepthConfig(), CAM).metric(depth, 0, 0)
    assert np.isnan(out[:, 45 - width[0] : 45]).all()
    # a nearer surface casts a wider shadow
    depth[:, 45:] = 0.4
    assert occlusion_mask(depth, f_out, 0.05).sum(axis=1)[0] > width[0]


def test_flat_and_ground_scenes_have_no_occlusion():
    cam = DepthCamera(CAM)
    depth = cam.metric_depth(Scene("spheres", "x", 0, np.zeros((0, 4)), np.zeros((0, 5)), np.zeros((0, 6))),
                             (0, 0, 3.5), np.eye(3))
    assert not occlusion_mask(depth, 28.0, 0.05).any()


def test_same_seed_same_frame_other_seed_or_tick_differs():
    sensor = StereoDepthSensor(StereoDepthConfig(), CAM)
    cam = DepthCamera(CAM)
    depth = cam.metric_depth(make_scene("spheres", "medium", 3), (8.0, 0.0, 3.5), np.eye(3))
    a, b = sensor.image(depth, 3, 5), sensor.image(depth, 3, 5)
    assert a.tobytes() == b.tobytes()
    assert not np.array_equal(a, sensor.image(depth, 3, 6))
    assert not np.array_equal(a, sensor.image(depth, 4, 5))


def test_propeller_corners_and_frame_delay():
    sensor = StereoDepthSensor(StereoDepthConfig(propellers="top", occlusion=False), CAM)
    out = sensor.metric(_flat(5.0), 0, 0)
    assert np.isnan(out[0, 0]) and np.isnan(out[0, -1]) and np.isfinite(out[-1, 0]) and np.isfinite(out[30, 45])
    near = StereoDepthSensor(StereoDepthConfig(propellers="bottom", propeller_reads="near"), CAM).metric(
        _flat(5.0), 0, 0)
    assert near[-1, 0] == 0.28 and near[-1, -1] == 0.28
    delay = FrameDelay(2)
    frames = [np.full(2, k) for k in range(5)]
    assert [int(delay(f)[0]) for f in frames] == [0, 0, 0, 1, 2]


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"model": "d455"}, "sensor.model is 'd455'; expected one of d435"),
        ({"model": "d435", "baseline": 0.05}, "unknown field sensor.baseline"),
        ({"model": "d435", "min_range_m": 20.0}, "min_range_m (20.0) must be below max_range_m"),
        ({"model": "d435", "delay_ticks": 1.5}, "sensor.delay_ticks has 1.5; expected a whole number"),
        ({"model": "d435", "propellers": "left"}, "sensor.propellers is 'left'"),
        ({"model": "d435", "baseline_m": "5cm"}, "sensor.baseline_m has '5cm'; expected float"),
    ],
)
def test_bad_options_are_one_line(values, message):
    with pytest.raises(ValueError, match=None) as err:
        sensor_from_dict(values)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_from_dict_and_none():
    assert sensor_from_dict(None) is None and sensor_from_dict({"model": "none"}) is None
    cfg = sensor_from_dict({"model": "d435", "delay_ticks": 1, "baseline_m": 0.05})
    assert cfg == StereoDepthConfig(delay_ticks=1)


def test_rollout_with_sensor_is_seeded_and_differs_from_the_ideal_camera():
    scene = make_scene("spheres", "medium", 2)
    cfg = RolloutConfig(sensor=StereoDepthConfig(delay_ticks=1), record_depth=True,
                        task=RolloutConfig().task.__class__(timeout_s=0.5, timeout_speed_factor=0.0))
    a = run_episodes([scene], [3.0], StraightPolicy(), cfg)[0].log.depth
    b = run_episodes([scene], [3.0], StraightPolicy(), cfg)[0].log.depth
    assert a.tobytes() == b.tobytes()
    np.testing.assert_array_equal(a[0], a[1])  # delay: the first frame stands in for tick 1
    ideal = run_episodes([scene], [3.0], StraightPolicy(), RolloutConfig(record_depth=True, task=cfg.task))[0]
    assert not np.array_equal(a, ideal.log.depth)
    with pytest.raises(ValueError, match="replaces the camera's noise_std_m"):
        RolloutConfig(sensor=StereoDepthConfig(), camera=CameraConfig(noise_std_m=0.1))
