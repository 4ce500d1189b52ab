"""Depth camera: metric accuracy, image orientation, attitude, shapes, noise and dropout."""

import math

import numpy as np
import pytest

from vitfly.sim.camera import CameraConfig, DepthCamera
from vitfly.sim.scenes import Scene, make_scene

QUANT = 1.0 / 255.0  # one uint8 step of normalised depth
NO_GROUND = CameraConfig(render_ground=False)


def scene(spheres=(), cylinders=(), boxes=()) -> Scene:
    return Scene("spheres", "test", 0, np.array(spheres, float), np.array(cylinders, float), np.array(boxes, float))


def yaw(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_sphere_at_known_distance_reads_right_depth():
    cam = DepthCamera(NO_GROUND)
    img = cam.render(scene([[6.0, 0.0, 3.5, 1.0]]), (0.0, 0.0, 3.5), np.eye(3))
    assert img.shape == (60, 90) and img.dtype == np.float32
    # the four centre pixels look almost straight at the sphere's nearest point, 5 m away
    assert np.all(np.abs(img[29:31, 44:46] - 0.5) <= QUANT)
    assert img.min() == pytest.approx(0.5, abs=QUANT)
    # nothing else in range: the background reads 1
    assert img[0, 0] == 1.0 and img[-1, -1] == 1.0


def test_obstacle_to_the_left_is_in_the_left_half_and_above_in_the_top_half():
    cam = DepthCamera(NO_GROUND)
    left = cam.render(scene([[6.0, 3.0, 3.5, 0.8]]), (0.0, 0.0, 3.5), np.eye(3))
    cols = np.flatnonzero((left < 1).any(axis=0))
    assert cols.size and cols.max() < 45
    above = cam.render(scene([[6.0, 0.0, 6.0, 0.8]]), (0.0, 0.0, 3.5), np.eye(3))
    rows = np.flatnonzero((above < 1).any(axis=1))
    assert rows.size and rows.max() < 30


def test_camera_rotates_with_the_body():
    cam = DepthCamera(NO_GROUND)
    sc = scene([[0.0, 6.0, 3.5, 1.0]])  # 6 m to the left of the drone
    assert cam.render(sc, (0, 0, 3.5), np.eye(3)).min() == 1.0  # not visible looking along +x
    turned = cam.render(sc, (0, 0, 3.5), yaw(90))  # turned left: now straight ahead
    assert turned[29:31, 44:46].max() == pytest.approx(0.5, abs=QUANT)
    # pitched nose-down by 20 deg: the sphere straight ahead moves up in the image
    pitch = np.array([[math.cos(0.35), 0, math.sin(0.35)], [0, 1, 0], [-math.sin(0.35), 0, math.cos(0.35)]])
    img = cam.render(scene([[6.0, 0.0, 3.5, 0.5]]), (0, 0, 3.5), pitch)
    rows = np.flatnonzero((img < 1).any(axis=1))
    assert rows.max() < 30


def test_planar_depth_of_a_wall_is_constant():
    cam = DepthCamera(NO_GROUND)
    wall = [[8.0, -20.0, -20.0, 9.0, 20.0, 20.0]]  # a box whose near face is the plane x = 8
    img = cam.render(scene(boxes=wall), (0.0, 0.0, 3.5), np.eye(3))
    np.testing.assert_allclose(img, 0.8, atol=1e-6)


def test_ground_plane_depth_matches_geometry():
    cam = DepthCamera(CameraConfig())
    img = cam.metric_depth(scene(), (0.0, 0.0, 3.5), np.eye(3))
    tan_v = math.tan(math.radians(45)) * 60 / 90
    v_bottom = tan_v * (1 - 2 * 59.5 / 60)  # tangent of the bottom row's ray below the axis
    assert img[-1, 0] == pytest.approx(3.5 / -v_bottom)
    assert np.all(np.isinf(img[:30]))  # upper half looks at the sky


def test_tree_trunk_depth():
    cam = DepthCamera(NO_GROUND)
    trunk = [[5.5, 0.0, 0.0, 8.0, 0.5]]  # trunk surface 5 m ahead, from the ground to 8 m
    img = cam.render(scene(cylinders=trunk), (0.0, 0.0, 3.5), np.eye(3))
    assert np.all(np.abs(img[:, 44:46] - 0.5) <= 2 * QUANT)  # the whole column: near face at x = 5
    assert img[:, 0].min() == 1.0  # thin trunk: the image edges are clear


def brute_force_spheres(cam: DepthCamera, spheres: np.ndarray, pos, rot) -> np.ndarray:
    """Every pixel against every sphere, no culling: the reference for the windowed renderer."""
    cfg = cam.config
    tan_h = math.tan(math.radians(cfg.horizontal_fov_deg) / 2)
    tan_v = tan_h * cfg.height / cfg.width
    u = tan_h * (1 - 2 * (np.arange(cfg.width) + 0.5) / cfg.width)
    v = tan_v * (1 - 2 * (np.arange(cfg.height) + 0.5) / cfg.height)
    vv, uu = np.meshgrid(v, u, indexing="ij")
    d = np.stack([np.ones_like(uu), uu, vv], axis=-1) @ rot.T  # world directions, (H, W, 3)
    best = np.full(uu.shape, np.inf)
    for x, y, z, r in spheres:
        oc = np.array([x, y, z]) - pos
        a = np.sum(d * d, axis=-1)
        b = d @ oc
        c = oc @ oc - r * r
        disc = b * b - a * c
        root = np.sqrt(np.maximum(disc, 0))
        t = (b - root) / a if c > 0 else (b + root) / a  # from inside, the far side
        best = np.where((disc >= 0) & (t > 0) & (t < best), t, best)
    return np.minimum(best / cfg.max_range_m, 1.0)


def test_windowed_rendering_equals_brute_force():
    cam = DepthCamera(NO_GROUND)
    sc = make_scene("spheres", "hard", seed=4)
    rot = np.array([[0.98, -0.1, 0.17], [0.1, 0.995, 0.0], [-0.17, 0.017, 0.985]])
    rot, _ = np.linalg.qr(rot)  # a proper rotation near the identity
    rot *= np.sign(np.diag(rot))
    for x in (5.0, 20.0, 35.0):
        pos = np.array([x, 0.5, 4.0])
        np.testing.assert_allclose(cam.render(sc, pos, rot), brute_force_spheres(cam, sc.spheres, pos, rot), atol=1e-6)


def test_noise_and_dropout_are_seeded():
    cfg = CameraConfig(noise_std_m=0.05, dropout_prob=0.1)
    cam = DepthCamera(cfg)
    sc = make_scene("spheres", "medium", seed=1)
    a = cam.render(sc, (10.0, 0.0, 3.5), np.eye(3), np.random.default_rng(3))
    b = cam.render(sc, (10.0, 0.0, 3.5), np.eye(3), np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    assert 0.07 < np.mean(a == 0.0) < 0.13
    clean = DepthCamera(CameraConfig()).render(sc, (10.0, 0.0, 3.5), np.eye(3))
    valid = (a > 0) & (clean < 1)
    assert 0.002 < np.std(a[valid] - clean[valid]) < 0.008  # 0.05 m / 10 m
    with pytest.raises(ValueError, match="rng"):
        cam.render(sc, (10.0, 0.0, 3.5), np.eye(3))


@pytest.mark.parametrize("env", ["trees", "window"])
def test_trunk_and_wall_depths_lie_on_surfaces_with_nothing_nearer(env):
    """Each reading is a point on an obstacle (or the ground), and marching along the ray finds no
    obstacle before it: catches culling or windowing that drops or misplaces a shape."""
    from vitfly.sim.collision import signed_distances

    cam = DepthCamera(CameraConfig())
    sc = make_scene(env, "hard", 3)
    rng = np.random.default_rng(0)
    tan_h = 1.0
    tan_v = tan_h * 60 / 90
    for x in (8.0, 18.0, 30.0):
        pos = np.array([x, rng.uniform(-2, 2), rng.uniform(2, 5)])
        rot = yaw(rng.uniform(-20, 20))
        metric = cam.metric_depth(sc, pos, rot)
        for row, col in zip(rng.integers(0, 60, 40), rng.integers(0, 90, 40), strict=True):
            u = tan_h * (1 - 2 * (col + 0.5) / 90)
            v = tan_v * (1 - 2 * (row + 0.5) / 60)
            d = rot @ np.array([1.0, u, v])
            t = metric[row, col]
            end = t if np.isfinite(t) else 10.0
            for s in np.arange(0.05, end - 0.05, 0.05):  # nothing in front of the reading
                assert signed_distances(pos + s * d, sc).min() > -1e-9
            if np.isfinite(t):
                hit = pos + t * d
                surface = min(abs(signed_distances(hit, sc).min()), abs(hit[2]))
                assert surface < 1e-6
