"""Scenes: determinism, JSON round trip, placement, window opening, expert cover, contact."""

import json

import numpy as np
import pytest

from vitfly.errors import VitflyError
from vitfly.sim.collision import ContactChecker, signed_distances
from vitfly.sim.scenes import ENVS, PRESET_CONFIGS, PRESETS, Scene, load_scene, make_scene, save_scene


@pytest.mark.parametrize("env", ENVS)
def test_same_seed_same_scene_bit_for_bit(env):
    a, b = make_scene(env, "medium", 7), make_scene(env, "medium", 7)
    assert a.equals(b)
    for name in ("spheres", "cylinders", "boxes"):
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes()
    assert not a.equals(make_scene(env, "medium", 8))


@pytest.mark.parametrize("env", ENVS)
def test_json_round_trip_is_exact(env, tmp_path):
    scene = make_scene(env, "hard", 123)
    save_scene(scene, tmp_path / "s.json")
    back = load_scene(tmp_path / "s.json")
    assert back.equals(scene)
    assert (back.env, back.preset, back.seed) == (env, "hard", 123)


def test_spheres_presets_density_and_placement():
    counts = [len(make_scene("spheres", p, 0).spheres) for p in PRESETS]
    assert counts == sorted(counts) and counts[0] < counts[-1]
    s = make_scene("spheres", "medium", 3).spheres
    cfg = PRESET_CONFIGS["spheres"]["medium"]
    assert np.all((s[:, 0] >= 5) & (s[:, 0] <= 60))  # clear zones at start and goal
    assert np.all((s[:, 1] >= -10) & (s[:, 1] <= 10) & (s[:, 2] >= 0) & (s[:, 2] <= 10))
    assert np.all((s[:, 3] >= cfg.radius[0]) & (s[:, 3] <= cfg.radius[1]) & (s[:, 3] <= 1.5))


def test_trees_have_trunks_from_the_ground_with_canopies_on_top():
    sc = make_scene("trees", "medium", 2)
    assert len(sc.cylinders) == len(sc.spheres) > 0
    assert np.all(sc.cylinders[:, 2] == 0.0)
    np.testing.assert_array_equal(sc.spheres[:, 2], sc.cylinders[:, 3])  # canopy centred on the trunk top
    np.testing.assert_array_equal(sc.spheres[:, :2], sc.cylinders[:, :2])


@pytest.mark.parametrize("seed", range(5))
def test_window_wall_has_one_passable_opening(seed):
    sc = make_scene("window", "medium", seed)
    boxes = sc.boxes
    x0, x1 = boxes[0, 0], boxes[0, 3]
    # the opening: between the side boxes in y and between the lower and upper boxes in z
    y_lo, y_hi = boxes[0, 4], boxes[1, 1]
    z_lo, z_hi = boxes[2, 5], boxes[3, 2]
    assert 1.5 <= y_hi - y_lo <= 3.0 and 1.5 <= z_hi - z_lo <= 3.0
    centre = ((x0 + x1) / 2, (y_lo + y_hi) / 2, (z_lo + z_hi) / 2)
    assert signed_distances(centre, sc).min() > 0.5  # the opening's centre is free
    assert signed_distances(((x0 + x1) / 2, y_lo - 0.5, 5.0), sc).min() < 0  # beside it is wall
    # the wall spans the whole corridor: a straight line at z = 3.5 crosses it unless it is in the opening
    assert (signed_distances(((x0 + x1) / 2, 9.0, 3.5), sc) < 0).any()
    # the opening is beside the start line y = 0, its nearer edge 0.5-2 m away: flying straight meets the wall
    # at every height the flight could have, and so does a drone 0.4 m wide
    near_edge = min(abs(y_lo), abs(y_hi))
    assert y_lo * y_hi > 0 and 0.5 <= near_edge <= 2.0
    for y in (-0.2, 0.0, 0.2):
        for z in (1.0, 3.5, 6.0):
            assert signed_distances(((x0 + x1) / 2, y, z), sc).min() < 0


def test_window_openings_are_on_both_sides():
    sides = {np.sign(make_scene("window", "medium", seed).boxes[0, 4]) for seed in range(20)}
    assert sides == {-1.0, 1.0}


@pytest.mark.parametrize("env", ["trees", "window"])
def test_expert_cover_contains_every_obstacle_point(env):
    sc = make_scene(env, "medium", 1)
    cover = sc.expert_obstacles()
    rng = np.random.default_rng(0)
    # random points inside the cylinders / boxes must lie inside some cover sphere
    if env == "trees":
        c = sc.cylinders[rng.integers(0, len(sc.cylinders), 400)]
        ang, rad = rng.uniform(0, 2 * np.pi, 400), np.sqrt(rng.uniform(0, 1, 400)) * c[:, 4]
        pts = np.stack([c[:, 0] + rad * np.cos(ang), c[:, 1] + rad * np.sin(ang), rng.uniform(c[:, 2], c[:, 3])], 1)
    else:
        b = sc.boxes[rng.integers(0, len(sc.boxes), 400)]
        pts = rng.uniform(b[:, :3], b[:, 3:])
    d = np.linalg.norm(pts[:, None, :] - cover[None, :, :3], axis=2) - cover[None, :, 3]
    assert np.all(d.min(axis=1) <= 1e-9)


def test_point_and_body_radius_contact():
    sc = Scene("spheres", "t", 0, np.array([[10.0, 0.0, 3.5, 1.0]]), np.zeros((0, 5)), np.zeros((0, 6)))
    point, body = ContactChecker(sc), ContactChecker(sc, body_radius_m=0.125)
    near = point.nearby((10.0, 0.0, 3.5), 5.0)
    assert point.in_contact((10.0, 0.0, 4.4), near)  # centre inside
    assert not point.in_contact((10.0, 0.0, 4.6), near)  # 0.1 m outside
    assert body.in_contact((10.0, 0.0, 4.6), near)  # but the 0.125 m body touches
    assert not body.in_contact((10.0, 0.0, 4.7), near)
    assert point.nearby((30.0, 0.0, 3.5), 1.0) == []


def test_contact_with_trunks_and_boxes_matches_signed_distance():
    rng = np.random.default_rng(2)
    for env in ("trees", "window"):
        sc = make_scene(env, "hard", 5)
        checker = ContactChecker(sc, body_radius_m=0.125)
        for p in rng.uniform([5, -10, 0], [60, 10, 10], (300, 3)):
            expected = signed_distances(p, sc).min() < 0.125
            assert checker.in_contact(tuple(p), checker.nearby(p, 0.0)) == expected


def test_bad_scene_files_give_one_line_errors(tmp_path):
    with pytest.raises(VitflyError, match="not found"):
        load_scene(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(VitflyError, match="not valid JSON"):
        load_scene(tmp_path / "bad.json")
    data = make_scene("spheres", "easy", 0).to_dict()
    data["spheres"][0][3] = float("nan")
    (tmp_path / "nan.json").write_text(json.dumps(data))
    with pytest.raises(VitflyError, match="spheres"):
        load_scene(tmp_path / "nan.json")
    with pytest.raises(VitflyError, match="unknown env"):
        make_scene("forest", "medium", 0)
    with pytest.raises(VitflyError, match="unknown preset"):
        make_scene("spheres", "extreme", 0)


@pytest.mark.parametrize("preset", ["single", "gap", "multi", "medium"])
def test_course_is_seeded_and_stands_in_the_arena(preset):
    a = make_scene("course", preset, 4)
    assert a.equals(make_scene("course", preset, 4)) and not a.equals(make_scene("course", preset, 5))
    assert len(a.spheres) == 0 and a.num_obstacles >= 1
    assert np.all(a.cylinders[:, 2] == 0) and np.all(a.boxes[:, 2] == 0)  # free-standing on the floor
    cfg = PRESET_CONFIGS["course"][preset]
    xs = np.concatenate([a.cylinders[:, 0], (a.boxes[:, 0] + a.boxes[:, 3]) / 2])
    assert np.all((xs >= cfg.obstacle_x[0]) & (xs <= cfg.obstacle_x[1]))


def _course_sites(scene):
    """(y_lo, y_hi) of each obstacle of a course scene."""
    cyl = [(y - r, y + r) for _, y, _, _, r in scene.cylinders]
    return cyl + [(b[1], b[4]) for b in scene.boxes]


@pytest.mark.parametrize("seed", range(8))
def test_course_layouts(seed):
    single = make_scene("course", "single", seed)
    assert single.num_obstacles == 1
    (lo, hi), = _course_sites(single)
    assert lo < 0 < hi  # on the start line: flying straight meets it
    gap = make_scene("course", "gap", seed)
    (a_lo, a_hi), (b_lo, b_hi) = sorted(_course_sites(gap))
    assert 1.6 <= b_lo - a_hi <= 2.4  # a passable gap between the two surfaces
    assert (a_lo < 0 < a_hi) or (b_lo < 0 < b_hi)  # beside the line: one of them stands on it
    multi = make_scene("course", "multi", seed)
    assert 3 <= multi.num_obstacles <= 6 and len(multi.cylinders) + len(multi.boxes) == multi.num_obstacles
    assert np.all(multi.boxes[:, 1] >= -4) and np.all(multi.boxes[:, 4] <= 4)
    assert np.all(np.abs(multi.cylinders[:, 1]) + multi.cylinders[:, 4] <= 4 + 1e-9)


def test_course_shapes_reach_the_expert():
    scene = make_scene("course", "multi", 1)
    spheres, objects, lo, hi = scene.expert_objects()
    assert len(lo) == scene.num_obstacles == len(np.unique(objects))
    for x, y, z0, z1, r in scene.cylinders:  # every cylinder is covered along its height
        near = spheres[np.hypot(spheres[:, 0] - x, spheres[:, 1] - y) < 1e-9]
        assert len(near) and near[:, 2].min() < z0 + 0.5 and near[:, 2].max() > z1 - 0.5 and near[0, 3] >= r
    for box in scene.boxes:
        centre = (box[:3] + box[3:]) / 2
        assert signed_distances(centre, scene).min() < 0
        inside = np.all((spheres[:, :3] >= box[:3]) & (spheres[:, :3] <= box[3:]), axis=1)
        assert inside.sum() >= 1


def test_course_bad_preset_names_the_course_presets():
    with pytest.raises(VitflyError, match="single, gap, multi"):
        make_scene("course", "dense", 0)
