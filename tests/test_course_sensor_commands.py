"""The course and the d435 sensor model through the real commands: evaluate --env course, collect with a sensor."""

import json

import h5py
import numpy as np
import pytest

from vitfly.cli import main
from vitfly.sim.collect import load_collect_config


def test_one_trial_evaluate_in_the_course_flies(tmp_path, capsys):
    out = tmp_path / "eval"
    args = ["evaluate", "--policy", "expert", "--env", "course", "--speeds", "3", "--trials", "1", "--out", str(out),
            "--no-gif", "--no-plots", "--no-progress", "--sensor", "d435", "delay_ticks=1"]
    assert main(args) == 0
    (record,) = [json.loads(line) for line in (out / "trials.jsonl").read_text().splitlines()]
    outcome = record["outcome"]
    assert record["env"] == "course" and outcome["end_reason"] == "goal" and outcome["success_strict"]
    assert record["extra"]["scene"]["env"] == "course"
    assert record["path"]["end"]["position"][0] >= 60.0  # through the arena to the task's goal


def test_bad_sensor_flag_is_one_line(tmp_path, capsys):
    assert main(["evaluate", "--policy", "expert", "--out", str(tmp_path), "--sensor", "d435", "baseline=5"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown field sensor.baseline" in err and len(err.splitlines()) == 1


def test_collect_with_the_sensor_records_it_and_its_frames(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("env: course\npreset: single\ntrajectories: 1\ntimeout_s: 1.0\nlog_every_tick: true\n"
                   "sensor: {model: d435, propellers: top}\n")
    config = load_collect_config(cfg)
    assert config.sensor is not None and config.content_key()["sensor"]["propellers"] == "top"
    assert "sensor" not in load_collect_config(None).content_key()  # the ideal camera's key is unchanged
    out = tmp_path / "d.h5"
    assert main(["collect", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    with h5py.File(out) as f:
        depth = f["depth"][:]
        stored = json.loads(f.attrs["config"])
    assert stored["collect"]["sensor"]["model"] == "d435"
    assert np.all(depth[:, 0, 0] == round(255 * 0.8))  # the propeller corner reads the original's fixed value


@pytest.mark.parametrize("bad", ["sensor: {model: d455}", "sensor: d435"])
def test_collect_bad_sensor_yaml(tmp_path, bad):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(bad + "\n")
    assert main(["collect", "--config", str(cfg), "--out", str(tmp_path / "d.h5"), "--no-progress"]) == 2
