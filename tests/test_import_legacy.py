"""`vitfly import-legacy`: original PNG + data.csv folders (built here with Pillow) into HDF5 schema v1."""

from __future__ import annotations

import csv

import h5py
import numpy as np
import pytest
from PIL import Image

from vitfly.cli import main
from vitfly.datamodules.legacy_import import import_legacy
from vitfly.datamodules.schema import open_trajectories
from vitfly.errors import VitflyError

HEADER = [
    "", "timestamp", "desired_vel", "quat_1", "quat_2", "quat_3", "quat_4", "pos_x", "pos_y", "pos_z",
    "vel_x", "vel_y", "vel_z", "velcmd_x", "velcmd_y", "velcmd_z", "ct_cmd", "br_cmd_x", "br_cmd_y", "br_cmd_z",
    "is_collide",
]  # fmt: skip


def make_folder(root, name, n_rows, n_images=None, shape=(60, 90), seed=0, nan_rows=(), collide=()):
    """One original trajectory folder; returns (images uint8 (n_images, H, W), telemetry rows as floats)."""
    rng = np.random.default_rng(seed)
    folder = root / name
    folder.mkdir(parents=True)
    n_images = n_rows if n_images is None else n_images
    t0 = 1_700_000_000.0 + seed
    stamps = t0 + np.arange(max(n_rows, n_images)) / 30.0
    images = rng.integers(0, 256, size=(n_images, *shape), dtype=np.uint8)
    for i in range(n_images):
        Image.fromarray(images[i], mode="L").save(folder / f"{stamps[i]:.6f}.png")
    rows = []
    with open(folder / "data.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(HEADER)
        for i in range(n_rows):
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            values = [stamps[i], 3.0 + seed, *q, *rng.normal(size=9), *rng.normal(size=4)]
            rows.append(values)
            cells = [repr(float(v)) for v in values]
            if i in nan_rows:
                cells[5] = ""  # pandas writes NaN as an empty cell
            writer.writerow([i, *cells, "True" if i in collide else "False"])
    return images, np.asarray(rows)


@pytest.fixture
def legacy_dir(tmp_path):
    root = tmp_path / "legacy"
    folders = {}
    folders["a_good"] = make_folder(root, "a_good", 8, seed=1, collide=(2, 3, 6))
    folders["b_extra_image"] = make_folder(root, "b_extra_image", 6, n_images=7, seed=2)
    folders["c_nan"] = make_folder(root, "c_nan", 7, seed=3, nan_rows=(0, 4))
    folders["d_big"] = make_folder(root, "d_big", 5, shape=(120, 180), seed=4)
    make_folder(root, "e_mismatch", 9, n_images=5, seed=5)
    (root / "f_empty").mkdir()
    make_folder(root, "g_no_csv", 3, seed=7)
    (root / "g_no_csv" / "data.csv").unlink()
    return root, folders


def test_import_handles_the_original_quirks(legacy_dir, tmp_path, capsys):
    root, folders = legacy_dir
    out = tmp_path / "legacy.h5"
    assert main(["import-legacy", str(root), "--out", str(out), "--depth-compression", "gzip"]) == 0
    printed = capsys.readouterr().out
    with h5py.File(out, "r") as f:
        assert f["depth"].compression == "gzip"  # lossless too: the depth checks below still hold
    assert "imported 4 trajectories" in printed and "folders skipped: 3" in printed
    assert "e_mismatch: 5 images but 9 telemetry rows" in printed
    assert "f_empty: no images" in printed and "g_no_csv: no data.csv" in printed
    assert "extra trailing images dropped: 1" in printed and "telemetry rows with NaN dropped: 2" in printed
    with open_trajectories(out) as tf:
        assert len(tf) == 4
        assert tf.config["folders"][:4] == ["a_good", "b_extra_image", "c_nan", "d_big"]
        assert tf.lengths.tolist() == [8, 6, 5, 5]
        a = tf[0]
        images, rows = folders["a_good"]
        np.testing.assert_array_equal(a.depth, images)  # PNG / 255 stored as round(255 * x): lossless
        np.testing.assert_allclose(a.quat, rows[:, 2:6], rtol=1e-6)
        np.testing.assert_allclose(a.desired_speed, rows[:, 1])
        np.testing.assert_allclose(a.position, rows[:, 6:9], rtol=1e-6)
        np.testing.assert_allclose(a.velocity, rows[:, 9:12], rtol=1e-6)
        np.testing.assert_allclose(a.velocity_cmd, rows[:, 12:15], rtol=1e-6)
        np.testing.assert_allclose(a.time, np.arange(8) / 30.0, atol=1e-5)
        assert a.collision.tolist() == [False, False, True, True, False, False, True, False]
        assert (a.env, a.seed, a.n_collisions, a.success) == ("legacy", 0, 2, False)
        b = tf[1]
        np.testing.assert_array_equal(b.depth, folders["b_extra_image"][0][:6])  # the trailing image is gone
        assert b.success
        c = tf[2]
        keep = [1, 2, 3, 5, 6]
        np.testing.assert_array_equal(c.depth, folders["c_nan"][0][keep])  # NaN rows dropped with their images
        np.testing.assert_allclose(c.velocity_cmd, folders["c_nan"][1][keep, 12:15], rtol=1e-6)
        d = tf[3]
        assert d.depth.shape == (5, 60, 90) and tf.meta(3)["seed"] == 3


def test_other_image_sizes_are_resized_bilinearly(tmp_path):
    root = tmp_path / "legacy"
    folder = root / "t"
    folder.mkdir(parents=True)
    small = np.random.default_rng(0).integers(0, 256, size=(60, 90), dtype=np.uint8)
    big = np.kron(small, np.ones((2, 2), np.uint8))  # each pixel a 2 x 2 block: a half-pixel bilinear halving
    Image.fromarray(big, mode="L").save(folder / "100.000000.png")
    with open(folder / "data.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(HEADER)
        writer.writerow([0, 99.0, 3.0, 1, 0, 0, 0, *([0.5] * 9), *([0.0] * 4), "False"])
    import_legacy(root, tmp_path / "out.h5")
    with open_trajectories(tmp_path / "out.h5") as tf:
        np.testing.assert_array_equal(tf[0].depth[0], small)


def test_rerun_resumes_without_duplicates(legacy_dir, tmp_path):
    root, _ = legacy_dir
    out = tmp_path / "legacy.h5"
    first = import_legacy(root, out)
    second = import_legacy(root, out)
    assert first.imported == 4 and second.imported == 0 and second.already_present == 4
    with open_trajectories(out) as tf:
        assert len(tf) == 4


def test_bad_inputs_fail_with_one_line_and_leave_no_file(tmp_path, capsys):
    out = tmp_path / "out.h5"
    assert main(["import-legacy", str(tmp_path / "missing"), "--out", str(out)]) == 2
    assert "missing: not a directory" in capsys.readouterr().err
    root = tmp_path / "only_bad"
    make_folder(root, "x", 4, n_images=2)
    (root / "y").mkdir()
    assert main(["import-legacy", str(root), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("vitfly: error: ") and "no folder could be imported" in err[-1]
    assert not out.exists()
    with pytest.raises(VitflyError, match="holds no trajectory folders"):
        import_legacy(tmp_path / "only_bad" / "y", out)
