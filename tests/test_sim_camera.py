"""Depth camera: metric accuracy, image orientation, attitude, shapes, noise and dropout."""

import math

import numpy as np
import pytest

from vitfly.sim.camera import CameraConfig, DepthCamera, expand_camera_preset
from vitfly.sim.scenes import Scene, make_scene

QUANT = 1.0 / 255.0  # one uint8 step of normalised depth
NO_GROUND = CameraConfig(render_ground=False)
DRONE = np.array([0.0, 0.0, 3.5])
# the default camera sits 0.3 m in front of the body origin (t_BC = (0.3, 0, 0), vision/config.yaml)
CAM = DRONE + np.array([0.3, 0.0, 0.0])
CAM_X, CAM_Z = CAM[0], CAM[2]

# The original's camera, by hand: Flightmare's pinhole for 640 x 480 at a 100 degree vertical fov has
# f = (480 / 2) / tan(50 deg) = 201.384 px (rgb_camera.cpp, updateCameraIntrinsics), centred on the
# symmetric Unity render; cv2.resize to 90 x 60 scales edge-based image coordinates by 90 / 640 and
# 60 / 480. A point at body-frame offset (x, y, z) from the camera lands at output coordinate
#   column = (320 - f y / x) * 90 / 640,   row = (240 - f z / x) * 60 / 480,
# in the output pixel floor(column), floor(row).
F_SRC = 240.0 / math.tan(math.radians(50.0))


def original_pixel(x: float, y: float, z: float) -> tuple[int, int]:
    """(row, column) of the output pixel the original pinhole + resize puts a camera-frame point in."""
    return math.floor((240.0 - F_SRC * z / x) * 60 / 480), math.floor((320.0 - F_SRC * y / x) * 90 / 640)


def scene(spheres=(), cylinders=(), boxes=()) -> Scene:
    return Scene("spheres", "test", 0, np.array(spheres, float), np.array(cylinders, float), np.array(boxes, float))


def yaw(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_sphere_at_known_distance_reads_right_depth():
    cam = DepthCamera(NO_GROUND)
    img = cam.render(scene([[CAM_X + 6.0, 0.0, CAM_Z, 1.0]]), DRONE, np.eye(3))
    assert img.shape == (60, 90) and img.dtype == np.float32
    # the four centre pixels look almost straight at the sphere's nearest point, 5 m away
    assert np.all(np.abs(img[29:31, 44:46] - 0.5) <= QUANT)
    assert img.min() == pytest.approx(0.5, abs=QUANT)
    # nothing else in range: the background reads 1
    assert img[0, 0] == 1.0 and img[-1, -1] == 1.0


def test_obstacle_to_the_left_is_in_the_left_half_and_above_in_the_top_half():
    cam = DepthCamera(NO_GROUND)
    left = cam.render(scene([[6.0, 3.0, CAM_Z, 0.8]]), DRONE, np.eye(3))
    cols = np.flatnonzero((left < 1).any(axis=0))
    assert cols.size and cols.max() < 45
    above = cam.render(scene([[6.0, 0.0, 6.0, 0.8]]), DRONE, np.eye(3))
    rows = np.flatnonzero((above < 1).any(axis=1))
    assert rows.size and rows.max() < 30


def test_camera_rotates_with_the_body():
    cam = DepthCamera(NO_GROUND)
    sc = scene([[0.0, 6.3, CAM_Z, 1.0]])  # 6.3 m to the left of the drone
    assert cam.render(sc, DRONE, np.eye(3)).min() == 1.0  # not visible looking along +x
    turned = cam.render(sc, DRONE, yaw(90))  # turned left: now straight ahead, the camera 0.3 m nearer
    assert turned[29:31, 44:46].max() == pytest.approx(0.5, abs=QUANT)
    # pitched nose-down by 20 deg: the sphere straight ahead moves up in the image
    pitch = np.array([[math.cos(0.35), 0, math.sin(0.35)], [0, 1, 0], [-math.sin(0.35), 0, math.cos(0.35)]])
    img = cam.render(scene([[6.0, 0.0, CAM_Z, 0.5]]), DRONE, pitch)
    rows = np.flatnonzero((img < 1).any(axis=1))
    assert rows.max() < 30


def test_planar_depth_of_a_wall_is_constant():
    cam = DepthCamera(NO_GROUND)
    wall = [[8.3, -20.0, -20.0, 9.0, 20.0, 20.0]]  # a box whose near face is 8 m ahead of the camera
    img = cam.render(scene(boxes=wall), DRONE, np.eye(3))
    np.testing.assert_allclose(img, 0.8, atol=1e-6)


def test_ground_plane_depth_matches_geometry():
    cam = DepthCamera(CameraConfig())
    img = cam.metric_depth(scene(), DRONE, np.eye(3))
    tan_v = math.tan(math.radians(50))  # 100 degrees high
    v_bottom = tan_v * (1 - 2 * 59.5 / 60)  # tangent of the bottom row's ray below the axis
    assert img[-1, 0] == pytest.approx(CAM_Z / -v_bottom)  # seen from the camera, 3.5 m up
    assert np.all(np.isinf(img[:30]))  # upper half looks at the sky


def test_tree_trunk_depth():
    cam = DepthCamera(NO_GROUND)
    # trunk surface 5 m ahead of the camera, tall enough for the 100 degree column (+-6 m at 5 m)
    trunk = [[CAM_X + 5.5, 0.0, -10.0, 15.0, 0.5]]
    img = cam.render(scene(cylinders=trunk), DRONE, np.eye(3))
    assert np.all(np.abs(img[:, 44:46] - 0.5) <= 2 * QUANT)  # the whole column: near face at x = 5
    assert img[:, 0].min() == 1.0  # thin trunk: the image edges are clear


def brute_force_spheres(cam: DepthCamera, spheres: np.ndarray, pos, rot) -> np.ndarray:
    """Every pixel against every sphere, no culling: the reference for the windowed renderer."""
    cfg = cam.config
    tan_v = math.tan(math.radians(cfg.vertical_fov_deg) / 2)
    tan_h = tan_v * cfg.source_width / cfg.source_height
    pos = pos + rot @ np.asarray(cfg.mount_offset_m)  # the camera centre
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
    tan_v = math.tan(math.radians(50))
    tan_h = tan_v * 640 / 480
    for x in (8.0, 18.0, 30.0):
        body = np.array([x, rng.uniform(-2, 2), rng.uniform(2, 5)])
        rot = yaw(rng.uniform(-20, 20))
        metric = cam.metric_depth(sc, body, rot)
        pos = body + rot @ np.array([0.3, 0.0, 0.0])  # the camera centre, 0.3 m along the body's x
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


# -- the original's camera: pinhole + resize, by hand --------------------------------------------


def test_fields_of_view_are_the_originals():
    cam = DepthCamera(CameraConfig())
    assert cam.vertical_fov_deg == pytest.approx(100.0)
    # 2 atan((640 / 2) / f) = 2 atan(320 / 201.384) = 2 atan(4/3 tan 50 deg) = 115.63 degrees across
    assert cam.horizontal_fov_deg == pytest.approx(math.degrees(2 * math.atan(320.0 / F_SRC)))
    assert 115.6 < cam.horizontal_fov_deg < 115.7
    # camera_config.yaml's camera: 2 atan(4/3 tan 35 deg) = 86.07 degrees across, 70 high
    alt = DepthCamera(CameraConfig.from_preset("camera_config_yaml"))
    assert alt.vertical_fov_deg == pytest.approx(70.0) and 86.0 < alt.horizontal_fov_deg < 86.2
    # an explicit horizontal fov overrides the aspect (vitfly's earlier square-pixel camera)
    old = DepthCamera(CameraConfig(horizontal_fov_deg=90.0, vertical_fov_deg=2 * math.degrees(math.atan(2 / 3))))
    assert old.horizontal_fov_deg == pytest.approx(90.0) and old._tan_v == pytest.approx(2 / 3)


def test_presets_name_the_originals_two_camera_files():
    # the default is vision/config.yaml's rgb_camera, the one visionsim_node actually rendered with
    assert CameraConfig() == CameraConfig.from_preset("vision_config_yaml")
    assert CameraConfig.from_preset("camera_config_yaml") == CameraConfig(
        vertical_fov_deg=70.0, source_width=320, source_height=240, mount_offset_m=(0.0, 0.0, 0.3)
    )
    # fields given beside a preset win; the preset fixes only the geometry
    cfg = CameraConfig.from_preset("camera_config_yaml", max_range_m=20.0, vertical_fov_deg=60.0)
    assert cfg.max_range_m == 20.0 and cfg.vertical_fov_deg == 60.0 and cfg.source_width == 320
    assert expand_camera_preset({"width": 45}) == {"width": 45}  # no preset: unchanged
    with pytest.raises(ValueError, match="field camera.preset is 'agile'; expected one of vision_config_yaml"):
        expand_camera_preset({"preset": "agile"}, "camera.")


def test_pixel_rays_are_where_cv2_resize_samples_the_render():
    # cv2.resize INTER_LINEAR (integer-centred source coordinates): output column j samples source
    # coordinate sx = (j + 0.5) * 640 / 90 - 0.5, between source columns floor(sx) and floor(sx) + 1;
    # source column c of the symmetric 640-wide render looks along tan = (319.5 - c) / f (+ = left).
    # Rows likewise with 480 / 60 (sy = 8 i + 3.5, halfway between source rows 8 i + 3 and 8 i + 4).
    cam = DepthCamera(CameraConfig())
    j = np.arange(90)
    sx = (j + 0.5) * 640 / 90 - 0.5
    np.testing.assert_allclose(cam._u[0], (319.5 - sx) / F_SRC, rtol=0, atol=1e-12)
    i = np.arange(60)
    sy = (i + 0.5) * 480 / 60 - 0.5
    np.testing.assert_allclose(cam._v[:, 0], (239.5 - sy) / F_SRC, rtol=0, atol=1e-12)


def test_small_sphere_straight_ahead_covers_the_four_centre_pixels():
    # the centre pixels' rays are half a pixel off the axis: tangents 0.5 * 2 tan(57.82 deg) / 90 =
    # 0.01766 across and 0.5 * 2 tan(50 deg) / 60 = 0.01986 up, 0.0266 off the axis together; the next
    # rays out are 0.0566 (a column further) and 0.0622 (a row further) off it. A 20 cm sphere whose centre
    # is 5 m straight ahead of the camera (0.3 m in front of the body origin, at its height) spans
    # asin(0.04) = 0.0400 rad about the axis: exactly rows 29, 30 and columns 44, 45
    sc = scene([[CAM_X + 5.0, 0.0, CAM_Z, 0.2]])
    depth = DepthCamera(NO_GROUND).metric_depth(sc, DRONE, np.eye(3))
    hit = np.isfinite(depth)
    assert set(np.flatnonzero(hit.any(axis=1))) == {29, 30}
    assert set(np.flatnonzero(hit.any(axis=0))) == {44, 45}
    # camera_config.yaml's camera sits 0.3 m above the body origin: the same sphere is 0.3 m below its axis,
    # its centre at row coordinate 30 + (0.3 / 5.3) / (2 tan 35 deg / 60) = 32.43 (tangents from 5.3 m away)
    alt = CameraConfig.from_preset("camera_config_yaml", render_ground=False)
    rows = np.flatnonzero(np.isfinite(DepthCamera(alt).metric_depth(sc, DRONE, np.eye(3))).any(axis=1))
    assert (rows.min() + rows.max() + 1) / 2 == pytest.approx(32.43, abs=0.6)


# Edges of walls 1 mm thick (their sides do not show) at camera-frame offsets:
# (axis, side, x, offset, pixel the edge lands in)
EDGES = [
    ("col", "left", 5.0, 2.0, 33),  # (320 - 201.384 * 0.4) * 90 / 640 = 33.67
    ("col", "right", 5.0, -1.2, 51),  # (320 + 201.384 * 0.24) * 90 / 640 = 51.80
    ("row", "above", 5.0, 1.2, 23),  # (240 - 201.384 * 0.24) / 8 = 23.96
    ("row", "below", 7.0, -2.0, 37),  # (240 + 201.384 * 2 / 7) / 8 = 37.19
]


@pytest.mark.parametrize("axis, side, x, offset, pixel", EDGES, ids=[e[1] for e in EDGES])
def test_wall_edges_land_in_the_pixel_of_the_original_pinhole_and_resize(axis, side, x, offset, pixel):
    # a wall covering everything on one side of a straight edge: an output pixel sees it exactly when
    # its centre (index + 0.5) lies on the wall's side of the edge's image coordinate, which the
    # original's formulas give (see original_pixel); the edge falls inside the pixel named above
    big = 50.0
    if axis == "col":
        lo, hi = (offset, big) if side == "left" else (-big, offset)
        box = [CAM_X + x, lo, CAM_Z - big, CAM_X + x + 1e-3, hi, CAM_Z + big]
        edge = (320.0 - F_SRC * offset / x) * 90 / 640
        assert math.floor(edge) == pixel == original_pixel(x, offset, 0.0)[1]
    else:
        lo, hi = (offset, big) if side == "above" else (-big, offset)
        box = [CAM_X + x, -big, CAM_Z + lo, CAM_X + x + 1e-3, big, CAM_Z + hi]
        edge = (240.0 - F_SRC * offset / x) * 60 / 480
        assert math.floor(edge) == pixel == original_pixel(x, 0.0, offset)[0]
    depth = DepthCamera(NO_GROUND).metric_depth(scene(boxes=[box]), DRONE, np.eye(3))
    hit = np.isfinite(depth)
    seen = hit.any(axis=0 if axis == "col" else 1)
    n = 90 if axis == "col" else 60
    centres = np.arange(n) + 0.5
    expected = centres < edge if side in ("left", "above") else centres > edge
    np.testing.assert_array_equal(seen, expected)
    assert hit.all(axis=0 if axis == "col" else 1)[expected].all()  # whole columns / rows


def thin_wall(x0: float) -> Scene:
    """A 1 cm thick wall across the whole view, its near face at world x = x0."""
    return scene(boxes=[[x0, -50.0, -50.0, x0 + 0.01, 50.0, 50.0]])


def test_camera_sits_0_3m_in_front_of_the_body_origin():
    # the drone at x = 0, the camera at x = 0.3 (t_BC = (0.3, 0, 0)): a thin wall at 0.25..0.26 m lies
    # between the body origin and the camera, behind the image plane: unseen
    cam = DepthCamera(NO_GROUND)
    assert np.all(np.isinf(cam.metric_depth(thin_wall(0.25), DRONE, np.eye(3))))
    # at 0.35 m it is 0.05 m in front of the camera: every pixel reads planar depth 0.05 m
    np.testing.assert_allclose(cam.metric_depth(thin_wall(0.35), DRONE, np.eye(3)), 0.05, rtol=0, atol=1e-9)
    # a camera at the body origin sees the wall at 0.25 m, 0.25 m away
    at_origin = DepthCamera(CameraConfig(render_ground=False, mount_offset_m=(0.0, 0.0, 0.0)))
    np.testing.assert_allclose(at_origin.metric_depth(thin_wall(0.25), DRONE, np.eye(3)), 0.25, rtol=0, atol=1e-9)
    # the mount is in the body frame: turned round (yaw 180 deg) the camera is at world x = -0.3, looking
    # along -x: the wall whose far face is x = -0.35 is 0.05 m ahead, the one at 0.25 m behind it
    turned = yaw(180)
    np.testing.assert_allclose(cam.metric_depth(thin_wall(-0.36), DRONE, turned), 0.05, rtol=0, atol=1e-9)
    assert np.all(np.isinf(cam.metric_depth(thin_wall(0.25), DRONE, turned)))


def test_camera_config_yaml_preset_sits_0_3m_above_the_body_origin():
    # camera_config.yaml's camera: drone at z = 3.5, camera at 3.8: a small sphere at z = 3.8, 5 m ahead,
    # covers rows symmetric about the image centre (between rows 29 and 30)
    alt = CameraConfig.from_preset("camera_config_yaml", render_ground=False)
    sc = scene([[5.0, 0.0, 3.8, 0.2]])
    rows = np.flatnonzero(np.isfinite(DepthCamera(alt).metric_depth(sc, DRONE, np.eye(3))).any(axis=1))
    assert rows.size and rows.min() + rows.max() == 59
    # rolled upside down, that camera is 0.3 m BELOW the body origin: row 0 now looks down at the ground
    # from 3.2 m, its ray tan 35 deg * (1 - 1/60) below the axis
    roll = np.diag([1.0, -1.0, -1.0])
    img = DepthCamera(CameraConfig.from_preset("camera_config_yaml")).metric_depth(scene(), DRONE, roll)
    assert img[0, 0] == pytest.approx(3.2 / (math.tan(math.radians(35)) * (1 - 1 / 60)))


def test_bad_camera_config_is_one_clear_error():
    with pytest.raises(ValueError, match="vertical_fov_deg"):
        DepthCamera(CameraConfig(vertical_fov_deg=190.0))
    with pytest.raises(ValueError, match="source_height"):
        DepthCamera(CameraConfig(source_height=0))
