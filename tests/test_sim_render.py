"""`vitfly render` and the reusable plotting helpers."""

import numpy as np
from PIL import Image

from vitfly.cli import main
from vitfly.sim.visualize import arrow_tip, body_command


def test_arrow_points_left_for_plus_y_and_up_for_plus_z():
    col, row = arrow_tip(np.array([3.0, 3.0, 0.0]), 3.0, 60, 90)
    assert col < 45 and row == 30
    col, row = arrow_tip(np.array([3.0, 0.0, 3.0]), 3.0, 60, 90)
    assert col == 45 and row < 30


def test_body_command_undoes_the_attitude():
    yaw_left_90 = np.array([[np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]])  # (w, x, y, z)
    # facing +y, a world +y command is straight ahead in the body frame
    np.testing.assert_allclose(body_command(np.array([[0.0, 2.0, 0.0]]), yaw_left_90), [[2.0, 0.0, 0.0]], atol=1e-12)


def test_render_writes_png_gif_and_a_replayable_scene(tmp_path, capsys):
    png, gif, scene = tmp_path / "t.png", tmp_path / "t.gif", tmp_path / "scene.json"
    args = ["render", "--env", "window", "--seed", "2", "--speed", "7", "--policy", "straight"]
    assert main([*args, "--out", str(png), "--gif", str(gif), "--gif-stride", "10", "--save-scene", str(scene)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert Image.open(png).size[0] > 800
    with Image.open(gif) as im:
        assert im.n_frames > 5 and im.size == (360, 240)
    # replaying the saved scene flies the same trial
    assert main(["render", "--scene", str(scene), "--speed", "7", "--policy", "straight", "--out", str(png)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == first
    assert main(["render", "--scene", str(tmp_path / "missing.json"), "--out", str(png)]) == 2
