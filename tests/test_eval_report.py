"""Records, aggregation, reports and plots on synthetic trials (paths built here, metrics computed for real)."""

import csv
import json
import math

import numpy as np
import pytest

from vitfly.errors import VitflyError
from vitfly.eval import plots, records
from vitfly.eval.aggregate import summarize
from vitfly.eval.fingerprint import Setup
from vitfly.eval.metrics import trial_metrics
from vitfly.eval.report import write_reports


def make_setup(policy_id="a" * 16, sweep_seed=0, preset="medium", rollout_id="r" * 16, scene_id="s" * 16):
    return Setup(policy_id, rollout_id, sweep_seed, preset, scene_id)


def make_record(policy, env, speed, trial, *, swerve=1.0, hit_ticks=(), seed=0, goal=True, setup=None):
    """A synthetic trial: forward flight at ``speed`` with a lateral swerve; contact on ``hit_ticks``."""
    dt, n = 1 / 30, 40
    t = np.arange(n) * dt
    pos = np.zeros((n, 3))
    pos[:, 0] = speed * t * (60.0 / (speed * t[-1]) if goal else 0.5)
    pos[:, 1] = swerve * np.sin(np.linspace(0, np.pi, n))
    pos[:, 2] = 3.5
    vel = np.gradient(pos, dt, axis=0)
    contact = np.zeros(n, bool)
    contact[list(hit_ticks)] = True
    path = records.round_path(t, pos, vel, vel, contact)
    arr = {k: np.asarray(v) for k, v in path.items()}
    m = trial_metrics(arr["time"], arr["position"], arr["velocity"], arr["command"], arr["contact"],
                      desired_speed_mps=speed, goal_x_m=60.0, reached_goal=goal, processing_ms=1.5)
    setup = setup or make_setup()
    return records.TrialRecord(policy=policy, env=env, speed=speed, trial=trial, scene_seed=seed,
                               success_paper=m.success_paper, success_strict=m.success_strict, reached_goal=goal,
                               end_reason="goal" if goal else "timeout", metrics=m.to_dict(), path=path,
                               setup=setup.to_dict(), setup_id=setup.id)


def sweep(policy="expert", env="spheres"):
    recs = []
    for speed in (3.0, 5.0):
        recs.append(make_record(policy, env, speed, 0, seed=11, hit_ticks=[5, 6, 20]))  # 2 collisions
        recs.append(make_record(policy, env, speed, 1, seed=12))
        recs.append(make_record(policy, env, speed, 2, seed=13, goal=False))
    return recs


def test_record_round_trip_and_recomputed_metrics(tmp_path):
    rec = make_record("expert", "spheres", 3.0, 0, hit_ticks=[5, 6])
    f = tmp_path / "trials.jsonl"
    records.append_record(f, rec)
    (back,) = records.read_records(f)
    assert back.key == rec.key and (back.success_paper, back.success_strict) == (False, False)
    assert back.setup == rec.setup and back.setup_id == make_setup().id
    assert back.metrics["collisions"] == 1
    assert back.metrics["time_in_collision_s"] == pytest.approx(2 / 30, rel=1e-4)  # times stored to 1 us
    # metrics recomputed from the stored path equal the stored metrics
    arr = back.path_arrays()
    again = trial_metrics(arr["time"], arr["position"], arr["velocity"], arr["command"], arr["contact"],
                          desired_speed_mps=3.0, goal_x_m=60.0, reached_goal=True, processing_ms=1.5).to_dict()
    for k, v in again.items():
        assert (math.isnan(v) and math.isnan(back.metrics[k])) or v == back.metrics[k], k
    # undefined metrics are JSON null, not NaN
    line = json.loads(f.read_text())
    assert line["metrics"]["time_to_goal_s"] is not None
    assert make_record("expert", "spheres", 3.0, 1).to_json().count("NaN") == 0


def test_torn_last_line_is_skipped_and_cut_before_the_next_append(tmp_path):
    f = tmp_path / "trials.jsonl"
    a, b, c = (make_record("expert", "spheres", 3.0, i) for i in range(3))
    records.append_record(f, a)
    records.append_record(f, b)
    data = f.read_bytes()
    f.write_bytes(data[: len(data) - 200])  # kill -9 in the middle of writing b
    assert [r.trial for r in records.read_records(f)] == [0]
    records.append_record(f, c)
    assert [r.trial for r in records.read_records(f)] == [0, 2]
    assert f.read_bytes().count(b"\n") == 2


def test_corrupt_line_names_file_and_line(tmp_path):
    f = tmp_path / "trials.jsonl"
    f.write_text('{"schema": "something else"}\n')
    with pytest.raises(Exception, match=r"trials.jsonl: line 1.*schema"):
        records.read_records(f)
    # records of version 1 were keyed by the label alone: refused, with what to do
    f.write_text('{"schema": "vitfly.trial", "version": 1}\n')
    with pytest.raises(VitflyError, match=r"trials.jsonl: line 1: a trial record of version 1.*new --out"):
        records.read_records(f)


def test_records_are_keyed_by_setup_and_labels_must_not_mix_setups(tmp_path):
    old, new = make_setup("a" * 16), make_setup("b" * 16)
    a = make_record("convnet", "spheres", 3.0, 0, setup=old)
    b = make_record("convnet", "spheres", 3.0, 0, setup=new)
    assert a.key != b.key  # the same label, env, speed and trial, but another policy: another trial
    f = tmp_path / "trials.jsonl"
    for rec in (a, b, make_record("expert", "spheres", 3.0, 0, setup=make_setup("e" * 16))):
        records.append_record(f, rec)
    recs = records.read_sweep(tmp_path)
    assert len(recs) == 3
    with pytest.raises(VitflyError, match=r"'convnet' holds trials flown with different setups \(policy content \(a+, "
                                          r"now b+\)\)"):
        records.check_consistent(recs, str(tmp_path))
    # another seed in another env is a mix too (one label, one sweep)
    c = make_record("convnet", "trees", 3.0, 0, setup=make_setup("a" * 16, sweep_seed=1))
    with pytest.raises(VitflyError, match=r"--seed \(0, now 1\)"):
        records.check_consistent([a, c], "dir")
    # removing the stale ones leaves a consistent store; the rewrite keeps the other lines byte for byte
    keep_lines = [x for x in f.read_text().splitlines() if '"bbbb' not in x]
    assert records.remove_records(f, lambda r: r.setup_id == new.id) == 1
    assert f.read_text().splitlines() == keep_lines
    records.check_consistent(records.read_sweep(tmp_path), str(tmp_path))
    assert records.remove_records(f, lambda r: False) == 0


def test_summary_rows_and_csv(tmp_path):
    recs = sweep("expert") + sweep("straight")
    rows = summarize(recs)
    assert [(r["policy"], r["speed"]) for r in rows] == [("expert", 3.0), ("expert", 5.0), ("straight", 3.0),
                                                          ("straight", 5.0)]
    r = rows[0]
    assert r["trials"] == 3 and r["policy_id"] == "a" * 16
    # trial 0 collides (twice), trial 1 is clean at the goal, trial 2 is clean but timed out
    assert r["success_paper_rate"] == pytest.approx(2 / 3)  # no collision: trials 1 and 2
    assert r["success_strict_rate"] == pytest.approx(1 / 3)  # goal and no collision: trial 1
    assert r["reached_goal_rate"] == pytest.approx(2 / 3)
    assert r["collisions_mean"] == pytest.approx(2 / 3)  # 2, 0, 0
    assert r["collisions_std"] == pytest.approx(np.std([2, 0, 0], ddof=1))
    # trial 0: 3 ticks of 1/30 s / 2 collisions = 0.05 s; the paper's mean runs over all trials: 0.05 / 3
    assert r["time_in_collision_mean"] == pytest.approx(0.05 / 3, rel=1e-4)
    assert r["time_in_collision_colliding_mean"] == pytest.approx(0.05, rel=1e-4)  # trial 0 alone
    paths = write_reports(tmp_path, rows)
    with open(paths["csv"]) as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 4
    for col in ("policy", "policy_id", "env", "speed", "trials", "success_paper_rate", "success_strict_rate",
                "collisions_mean", "time_in_collision_mean", "time_in_collision_colliding_mean", "energy_cost_mean",
                "cmd_acc_mean", "time_to_goal_mean"):
        assert col in table[0]
    assert "success_rate" not in table[0]  # every success column names its definition
    assert float(table[0]["energy_cost_mean"]) > 0
    assert table[2]["time_in_collision_colliding_std"] == "0.0"  # one colliding trial
    assert float(table[2]["time_in_collision_std"]) == pytest.approx(np.std([0.05, 0, 0], ddof=1), rel=1e-4)
    md = paths["markdown"].read_text()
    # 2 of 3 with its 95 % Wilson interval, by hand: (p + z²/2n ± z sqrt(p(1-p)/n + z²/4n²)) / (1 + z²/n),
    # z = 1.96: (0.6667 + 0.6403 ± 0.8334) / 2.2805 = 0.208 to 0.939
    assert "| expert | spheres | 3 | 3 | 67 (21-94) | 33 |" in md
    assert "Brackets: the 95 % Wilson interval of the paper's success rate" in md
    assert "success % (paper) | success % (strict)" in md
    assert "success (paper) = no collision" in md and "success (strict) = goal reached and no collision" in md
    assert md.startswith("| policy") and md.count("\n| ") == 4  # 4 rows under the header


def test_shard_files_merge(tmp_path):
    a, b = sweep("expert")[:3], sweep("expert")[2:]
    for rec in a:
        records.append_record(tmp_path / "trials.jsonl", rec)
    for rec in b:
        records.append_record(tmp_path / "trials-part2.jsonl", rec)
    merged = records.read_sweep(tmp_path)
    assert len(merged) == 6
    assert len({r.key for r in merged}) == 6


def test_standard_plots_are_written(tmp_path):
    from types import SimpleNamespace

    recs = sweep("expert") + sweep("convnet") + sweep("straight") + sweep("expert", "trees")
    rows = summarize(recs)
    scene = SimpleNamespace(spheres=np.array([[20.0, 1.0, 3.5, 1.0]]), cylinders=np.array([[40.0, -2, 0, 6, 0.3]]),
                            boxes=np.zeros((0, 6)))
    written = plots.write_standard_plots(tmp_path, rows, recs, scene_loader=lambda env, preset, seed: scene)
    assert set(written) >= {"rates_vs_speed", "time_in_collision_vs_speed", "energy_vs_speed", "paths_spheres",
                            "paths_trees"}
    for p in written.values():
        assert p.exists() and p.stat().st_size > 10_000
        assert p.read_bytes()[:4] == b"\x89PNG"
    seed, same_scene = plots.scene_for_paths(recs, "spheres")
    assert seed == 11 and {r.policy for r in same_scene} == {"expert", "convnet", "straight"}


def test_wandb_offline_run_holds_table_plots_and_gif(tmp_path, monkeypatch):
    from PIL import Image

    from vitfly.eval.wandb_log import log_evaluation

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    recs = sweep("expert") + sweep("straight")
    rows = summarize(recs)
    images = plots.write_standard_plots(tmp_path, rows, recs)
    gif = tmp_path / "depth.gif"
    frames = [Image.new("RGB", (90, 60), (i * 40, 0, 0)) for i in range(3)]
    frames[0].save(gif, save_all=True, append_images=frames[1:], duration=33)
    run_dir = log_evaluation("vitfly-test", rows, {**images, "depth": gif}, tmp_path, run_name="t")
    media = {p.parent.name + "/" + p.name.split("_0_")[0] for p in (tmp_path / "wandb").rglob("media/*/*")}
    assert {"images/rates_vs_speed", "images/energy_vs_speed", "table/summary", "videos/depth"} <= media
    assert "offline-run" in run_dir


def test_outcomes_file_is_small_and_gives_the_same_paired_statistics(tmp_path):
    from vitfly.eval.evaluation import write_outputs
    from vitfly.eval.paired import paired_difference

    clean = [make_record("convnet", "spheres", speed, trial, seed=seed)  # no contact: every trial a success
             for speed in (3.0, 5.0) for trial, seed in enumerate((11, 12, 13))]
    full = sweep("expert") + clean
    for rec in full:
        rec.extra["scene"] = {"spheres": [[float(i), 0.0, 3.0, 1.0] for i in range(200)]}  # as sweeps store it
        rec.path["end"] = {"time": 1.3, "position": [60.0, rec.trial / 10, 3.5]}
        records.append_record(tmp_path / "trials.jsonl", rec)
    _, files = write_outputs(tmp_path, with_plots=False)
    slim = records.read_records(files["outcomes"])
    assert files["outcomes"].name == "outcomes.jsonl.gz"
    assert files["outcomes"].stat().st_size * 10 < (tmp_path / "trials.jsonl").stat().st_size
    assert sorted(r.key for r in slim) == sorted(r.key for r in full)
    by_key = {r.key: r for r in records.read_records(tmp_path / "trials.jsonl")}
    for rec in slim:
        assert rec.to_json() == by_key[rec.key].without_path().to_json()  # outcome, metrics, setup as flown
        assert rec.path == {"end": {"time": 1.3, "position": [60.0, rec.trial / 10, 3.5]}} and "scene" not in rec.extra
    # by hand: the expert collides on scene 11 at both speeds (2 of 6 pairs), convnet never: +1/3
    for recs in (full, slim):
        d = paired_difference(recs, "convnet", "expert", "spheres", "success")
        assert (d.pairs, d.diff) == (6, pytest.approx(1 / 3))
    # the same records give the same bytes; a path is asked for in one clear line
    again = tmp_path / "again.jsonl.gz"
    records.write_outcomes(again, reversed(records.read_records(tmp_path / "trials.jsonl")))
    assert again.read_bytes() == files["outcomes"].read_bytes()
    with pytest.raises(VitflyError, match="no flown path .*trials.jsonl"):
        slim[0].path_arrays()
    again.write_bytes(b"not gzip")
    with pytest.raises(VitflyError, match="again.jsonl.gz: not a gzipped trials file"):
        records.read_records(again)


def test_a_published_outcomes_file_alone_gives_the_same_reports(tmp_path):
    import shutil

    from vitfly.eval.config import SweepConfig
    from vitfly.eval.evaluation import merge_into, run_evaluation, write_outputs

    flown, published = tmp_path / "flown", tmp_path / "published"
    flown.mkdir(), published.mkdir()
    for rec in sweep("expert") + sweep("convnet"):
        records.append_record(flown / "trials.jsonl", rec)
    _, files = write_outputs(flown, with_plots=False)  # plots: the published copy draws them below
    shutil.copy(files["outcomes"], published)  # what a results page commits
    mtime = (published / records.OUTCOMES_FILE).stat().st_mtime_ns
    _, again = write_outputs(published, with_plots=True)
    for name in ("csv", "markdown", "paired"):
        assert again[name].read_bytes() == files[name].read_bytes()
    # the source itself is not rewritten; paths cannot be drawn from records without them
    assert (published / records.OUTCOMES_FILE).stat().st_mtime_ns == mtime
    assert "rates_vs_speed" in again and not any(name.startswith("paths_") for name in again)
    # flying into it would drop the published trials from its outcomes file: refused before any trial
    with pytest.raises(VitflyError, match="published outcomes.jsonl.gz and no trials"):
        run_evaluation(SweepConfig(policy="straight", env=["spheres"], speeds=[3.0], trials=1, out=str(published)))
    with pytest.raises(VitflyError, match="--merge .*published: holds only outcomes.jsonl.gz"):
        merge_into(tmp_path / "merged", [flown, published])
    assert not list(published.glob("trials*.jsonl")) and not (tmp_path / "merged").exists()
    with pytest.raises(VitflyError, match="no finished trials"):
        write_outputs(tmp_path / "empty")


def test_a_sweep_merges_into_a_published_folder_keeping_its_title(tmp_path, capsys):
    """``vitfly evaluate --out <published> --merge <sweep>``: the new policy's records join the outcomes file
    without their paths, and the reports are those of one sweep that flew both policies, under the old title."""
    import gzip

    from vitfly.cli import main
    from vitfly.eval.evaluation import write_outputs

    both, flown, published = tmp_path / "both", tmp_path / "flown", tmp_path / "published"
    for folder, recs in ((both, sweep("expert") + sweep("convnet")), (flown, sweep("convnet")),
                         (published, sweep("expert"))):
        folder.mkdir()
        for rec in recs:
            records.append_record(folder / "trials.jsonl", rec)
    expected = write_outputs(both, with_plots=False, title="reproduce (paper): spheres")[1]
    write_outputs(published, with_plots=False, title="reproduce (paper): spheres")
    (published / "trials.jsonl").unlink()  # what a results page commits: the outcomes file and the tables

    assert main(["evaluate", "--out", str(published), "--merge", str(flown), "--no-plots"]) == 0
    assert f"{published}: merged 6 new trials" in capsys.readouterr().out
    assert not list(published.glob("trials*.jsonl"))
    for key, name in (("outcomes", "outcomes.jsonl.gz"), ("csv", "summary.csv"), ("markdown", "summary.md"),
                      ("paired", "paired.csv")):
        assert (published / name).read_bytes() == expected[key].read_bytes(), name
    lines = gzip.decompress((published / "outcomes.jsonl.gz").read_bytes()).decode().splitlines()
    assert len(lines) == 12 and all('"position"' not in line for line in lines)  # 6 + 6, no paths
    # merging again adds nothing and leaves the bytes alone
    before = (published / "outcomes.jsonl.gz").stat().st_mtime_ns
    assert main(["evaluate", "--out", str(published), "--merge", str(flown), "--no-plots"]) == 0
    assert f"{published}: merged 0 new trials" in capsys.readouterr().out
    assert (published / "outcomes.jsonl.gz").stat().st_mtime_ns == before
    # a label flown with another setup: one line, the published folder untouched
    other = tmp_path / "other"
    other.mkdir()
    records.append_record(other / "trials.jsonl",
                          make_record("convnet", "spheres", 7.0, 0, setup=make_setup(policy_id="b" * 16)))
    assert main(["evaluate", "--out", str(published), "--merge", str(other), "--no-plots"]) == 2
    assert "convnet" in capsys.readouterr().err
    assert (published / "outcomes.jsonl.gz").stat().st_mtime_ns == before


def test_summary_title_reads_back_the_title_reports_were_written_with(tmp_path):
    from vitfly.eval.report import summary_title

    rows = summarize(sweep("expert"))
    assert summary_title(tmp_path) is None  # no summary.md yet
    write_reports(tmp_path, rows, "reproduce (paper): trees")
    assert summary_title(tmp_path) == "reproduce (paper): trees"
    write_reports(tmp_path, rows)  # untitled, as the ablation folders
    assert summary_title(tmp_path) is None


def test_reports_are_written_again_only_when_their_inputs_change(tmp_path, monkeypatch):
    from vitfly.eval.evaluation import REPORTS_STAMP, write_outputs

    drawn = []
    real = plots.write_standard_plots
    monkeypatch.setattr(plots, "write_standard_plots", lambda *a, **k: drawn.append(1) or real(*a, **k))
    for rec in sweep("expert") + sweep("convnet"):
        records.append_record(tmp_path / "trials.jsonl", rec)
    rows, files = write_outputs(tmp_path, title="first")
    assert set(files) >= {"csv", "markdown", "paired", "rates_vs_speed", "paths_spheres"} and len(drawn) == 1
    stamp = json.loads((tmp_path / REPORTS_STAMP).read_text())
    assert stamp["files"]["paths_spheres"] == "paths_spheres.png" and stamp["key"]["title"] == "first"
    mtimes = {name: p.stat().st_mtime_ns for name, p in files.items()}

    # nothing new: the same files, untouched, nothing drawn
    again_rows, again = write_outputs(tmp_path, title="first")
    assert again == files and again_rows == rows and len(drawn) == 1
    assert {name: p.stat().st_mtime_ns for name, p in files.items()} == mtimes
    # plots no longer wanted, another title, a missing file, a new record: written again (without plots: cheaper)
    _, files = write_outputs(tmp_path, with_plots=False, title="first")
    assert set(files) == {"csv", "markdown", "paired", "outcomes"}
    write_outputs(tmp_path, with_plots=False, title="second")
    assert "second" in files["markdown"].read_text()
    markdown = files["markdown"].stat().st_mtime_ns
    assert write_outputs(tmp_path, with_plots=False, title="second")[1] == files
    assert files["markdown"].stat().st_mtime_ns == markdown
    files["csv"].unlink()
    write_outputs(tmp_path, with_plots=False, title="second")
    assert files["csv"].exists()
    records.append_record(tmp_path / "trials-part2.jsonl", make_record("straight", "spheres", 3.0, 0, seed=11))
    rows, files = write_outputs(tmp_path, with_plots=False, title="second")
    assert len(rows) == 5 and "straight" in files["csv"].read_text() and len(drawn) == 1
