"""Depth camera: metric accuracy, image orientation, attitude, shapes, noise and dropout."""

import math

import numpy as np
import pytest

from vitfly.sim.camera import CameraConfig, DepthCamera
from vitfly.sim.scenes import Scene, make_scene

QUANT = 1.0 / 255.0  # one uint8 step of normalised depth
NO_GROUND = CameraConfig(render_ground=False)
DRONE = np.array([0.0, 0.0, 3.5])
CAM_Z = 3.8  # the default camera sits 0.3 m above the body origin (t_BC = (0, 0, 0.3))

# The original's camera, by hand: Flightmare's pinhole for 320 x 240 at a 70 degree vertical fov has
# f = (240 / 2) / tan(35 deg) = 171.377 px (rgb_camera.cpp, updateCameraIntrinsics), centred on the
# symmetric Unity render; cv2.resize to 90 x 60 scales edge-based image coordinates by 90 / 320 and
# 60 / 240. A point at body-frame offset (x, y, z) from the camera lands at output coordinate
#   column = (160 - f y / x) * 90 / 320,   row = (120 - f z / x) * 60 / 240,
# in the output pixel floor(column), floor(row).
F_SRC = 120.0 / math.tan(math.radians(35.0))


def original_pixel(x: float, y: float, z: float) -> tuple[int, int]:
    """(row, column) of the output pixel the original pinhole + resize puts a camera-frame point in."""
    return math.floor((120.0 - F_SRC * z / x) * 60 / 240), math.floor((160.0 - F_SRC * y / x) * 90 / 320)


def scene(spheres=(), cylinders=(), boxes=()) -> Scene:
    return Scene("spheres", "test", 0, np.array(spheres, float), np.array(cylinders, float), np.array(boxes, float))


def yaw(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_sphere_at_known_distance_reads_right_depth():
    cam = DepthCamera(NO_GROUND)
    img = cam.render(scene([[6.0, 0.0, CAM_Z, 1.0]]), DRONE, np.eye(3))
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
    sc = scene([[0.0, 6.0, CAM_Z, 1.0]])  # 6 m to the left of the drone
    assert cam.render(sc, DRONE, np.eye(3)).min() == 1.0  # not visible looking along +x
    turned = cam.render(sc, DRONE, yaw(90))  # turned left: now straight ahead
    assert turned[29:31, 44:46].max() == pytest.approx(0.5, abs=QUANT)
    # pitched nose-down by 20 deg: the sphere straight ahead moves up in the image
    pitch = np.array([[math.cos(0.35), 0, math.sin(0.35)], [0, 1, 0], [-math.sin(0.35), 0, math.cos(0.35)]])
    img = cam.render(scene([[6.0, 0.0, CAM_Z, 0.5]]), DRONE, pitch)
    rows = np.flatnonzero((img < 1).any(axis=1))
    assert rows.max() < 30


def test_planar_depth_of_a_wall_is_constant():
    cam = DepthCamera(NO_GROUND)
    wall = [[8.0, -20.0, -20.0, 9.0, 20.0, 20.0]]  # a box whose near face is the plane x = 8
    img = cam.render(scene(boxes=wall), DRONE, np.eye(3))
    np.testing.assert_allclose(img, 0.8, atol=1e-6)


def test_ground_plane_depth_matches_geometry():
    cam = DepthCamera(CameraConfig())
    img = cam.metric_depth(scene(), DRONE, np.eye(3))
    tan_v = math.tan(math.radians(35))  # 70 degrees high
    v_bottom = tan_v * (1 - 2 * 59.5 / 60)  # tangent of the bottom row's ray below the axis
    assert img[-1, 0] == pytest.approx(CAM_Z / -v_bottom)  # seen from the camera, 3.8 m up
    assert np.all(np.isinf(img[:30]))  # upper half looks at the sky


def test_tree_trunk_depth():
    cam = DepthCamera(NO_GROUND)
    trunk = [[5.5, 0.0, 0.0, 8.0, 0.5]]  # trunk surface 5 m ahead, from the ground to 8 m
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
    tan_v = math.tan(math.radians(35))
    tan_h = tan_v * 320 / 240
    for x in (8.0, 18.0, 30.0):
        body = np.array([x, rng.uniform(-2, 2), rng.uniform(2, 5)])
        rot = yaw(rng.uniform(-20, 20))
        metric = cam.metric_depth(sc, body, rot)
        pos = body + np.array([0.0, 0.0, 0.3])  # the camera centre (yaw keeps body z = world z)
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
    assert cam.vertical_fov_deg == pytest.approx(70.0)
    # 2 atan((320 / 2) / f) = 2 atan(160 / 171.377) = 86.07 degrees across
    assert cam.horizontal_fov_deg == pytest.approx(math.degrees(2 * math.atan(160.0 / F_SRC)))
    assert 86.0 < cam.horizontal_fov_deg < 86.2
    # an explicit horizontal fov overrides the aspect (vitfly's earlier square-pixel camera)
    old = DepthCamera(CameraConfig(horizontal_fov_deg=90.0, vertical_fov_deg=2 * math.degrees(math.atan(2 / 3))))
    assert old.horizontal_fov_deg == pytest.approx(90.0) and old._tan_v == pytest.approx(2 / 3)


def test_pixel_rays_are_where_cv2_resize_samples_the_render():
    # cv2.resize INTER_LINEAR (integer-centred source coordinates): output column j samples source
    # coordinate sx = (j + 0.5) * 320 / 90 - 0.5, between source columns floor(sx) and floor(sx) + 1;
    # source column c of the symmetric 320-wide render looks along tan = (159.5 - c) / f (+ = left).
    # Rows likewise with 240 / 60 (sy = 4 i + 1.5, halfway between source rows 4 i + 1 and 4 i + 2).
    cam = DepthCamera(CameraConfig())
    j = np.arange(90)
    sx = (j + 0.5) * 320 / 90 - 0.5
    np.testing.assert_allclose(cam._u[0], (159.5 - sx) / F_SRC, rtol=0, atol=1e-12)
    i = np.arange(60)
    sy = (i + 0.5) * 240 / 60 - 0.5
    np.testing.assert_allclose(cam._v[:, 0], (119.5 - sy) / F_SRC, rtol=0, atol=1e-12)


def test_small_sphere_straight_ahead_covers_the_four_centre_pixels():
    # the centre pixels' rays are half a pixel off the axis: tangents 0.5 * 2 tan(43.03 deg) / 90 =
    # 0.0104 across and 0.5 * 2 tan(35 deg) / 60 = 0.0117 up; a 10 cm sphere 5 m ahead subtends
    # 0.02, less than the next rays out (0.031, 0.035): exactly rows 29, 30 and columns 44, 45
    depth = DepthCamera(NO_GROUND).metric_depth(scene([[5.0, 0.0, CAM_Z, 0.1]]), DRONE, np.eye(3))
    hit = np.isfinite(depth)
    assert set(np.flatnonzero(hit.any(axis=1))) == {29, 30}
    assert set(np.flatnonzero(hit.any(axis=0))) == {44, 45}


# Edges of walls 1 mm thick (their sides do not show) at camera-frame offsets:
# (axis, side, x, offset, pixel the edge lands in)
EDGES = [
    ("col", "left", 5.0, 2.0, 25),  # (160 - 171.377 * 0.4) * 90 / 320 = 25.72
    ("col", "right", 5.0, -1.2, 56),  # (160 + 171.377 * 0.24) * 90 / 320 = 56.57
    ("row", "above", 5.0, 1.5, 17),  # (120 - 171.377 * 0.3) / 4 = 17.15
    ("row", "below", 7.0, -2.0, 42),  # (120 + 171.377 * 2 / 7) / 4 = 42.24
]


@pytest.mark.parametrize("axis, side, x, offset, pixel", EDGES, ids=[e[1] for e in EDGES])
def test_wall_edges_land_in_the_pixel_of_the_original_pinhole_and_resize(axis, side, x, offset, pixel):
    # a wall covering everything on one side of a straight edge: an output pixel sees it exactly when
    # its centre (index + 0.5) lies on the wall's side of the edge's image coordinate, which the
    # original's formulas give (see original_pixel); the edge falls inside the pixel named above
    big = 50.0
    if axis == "col":
        lo, hi = (offset, big) if side == "left" else (-big, offset)
        box = [x, lo, CAM_Z - big, x + 1e-3, hi, CAM_Z + big]
        edge = (160.0 - F_SRC * offset / x) * 90 / 320
        assert math.floor(edge) == pixel == original_pixel(x, offset, 0.0)[1]
    else:
        lo, hi = (offset, big) if side == "above" else (-big, offset)
        box = [x, -big, CAM_Z + lo, x + 1e-3, big, CAM_Z + hi]
        edge = (120.0 - F_SRC * offset / x) * 60 / 240
        assert math.floor(edge) == pixel == original_pixel(x, 0.0, offset)[0]
    depth = DepthCamera(NO_GROUND).metric_depth(scene(boxes=[box]), DRONE, np.eye(3))
    hit = np.isfinite(depth)
    seen = hit.any(axis=0 if axis == "col" else 1)
    n = 90 if axis == "col" else 60
    centres = np.arange(n) + 0.5
    expected = centres < edge if side in ("left", "above") else centres > edge
    np.testing.assert_array_equal(seen, expected)
    assert hit.all(axis=0 if axis == "col" else 1)[expected].all()  # whole columns / rows


def test_camera_height_offset_centres_a_sphere_0_3m_above_the_drone():
    # drone at z = 3.5, camera at 3.8: a small sphere at z = 3.8, 5 m ahead, covers rows symmetric
    # about the image centre (between rows 29 and 30)
    sc = scene([[5.0, 0.0, 3.8, 0.2]])
    rows = np.flatnonzero(np.isfinite(DepthCamera(NO_GROUND).metric_depth(sc, DRONE, np.eye(3))).any(axis=1))
    assert rows.size and rows.min() + rows.max() == 59
    # a camera at the body origin sees it 0.3 / 5 above the axis: centre at row coordinate
    # 30 - 0.06 / (2 tan 35 / 60) = 27.43, so its rows are centred there instead
    flat = CameraConfig(render_ground=False, mount_offset_m=(0.0, 0.0, 0.0))
    rows0 = np.flatnonzero(np.isfinite(DepthCamera(flat).metric_depth(sc, DRONE, np.eye(3))).any(axis=1))
    assert (rows0.min() + rows0.max() + 1) / 2 == pytest.approx(27.43, abs=0.6)
    # the mount is in the body frame: rolled upside down, the camera is 0.3 m BELOW the body origin
    roll = np.diag([1.0, -1.0, -1.0])
    img = DepthCamera(CameraConfig()).metric_depth(scene(), DRONE, roll)
    assert img[0, 0] == pytest.approx(3.2 / (math.tan(math.radians(35)) * (1 - 1 / 60)))  # now row 0 looks down


def test_bad_camera_config_is_one_clear_error():
    with pytest.raises(ValueError, match="vertical_fov_deg"):
        DepthCamera(CameraConfig(vertical_fov_deg=190.0))
    with pytest.raises(ValueError, match="source_height"):
        DepthCamera(CameraConfig(source_height=0))
