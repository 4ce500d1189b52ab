"""Evaluation sweeps end to end: the real simulator, real policies, the real `vitfly evaluate` command."""

import csv
import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from vitfly.cli import main
from vitfly.eval import records
from vitfly.eval.config import SweepConfig, load_sweep_config
from vitfly.eval.sweep import derive_scene_seed, make_batches, plan_trials, select_shard

# short trials: a 1.5 s timeout ends each one after ~45 control ticks
FAST = ["--timeout", "1.5", "--no-gif", "--no-plots", "--no-progress", "--num-envs", "4"]


def evaluate(out, *args):
    return main(["evaluate", "--out", str(out), *FAST, *args])


def lines(path):
    return [json.loads(x) for x in path.read_text().splitlines()]


def test_trial_plan_seeds_shards_and_batches():
    cfg = SweepConfig(env=["spheres", "trees"], speeds=[3.0, 5.0], trials=3, seed=7)
    plan = plan_trials(cfg)
    assert len(plan) == 12
    # a trial's scene depends on (seed, env, trial) only: the same at every speed, for every policy
    assert {s.scene_seed for s in plan if s.env == "spheres" and s.trial == 1} == {derive_scene_seed(7, "spheres", 1)}
    assert len({s.scene_seed for s in plan}) == 6
    assert derive_scene_seed(8, "spheres", 1) != derive_scene_seed(7, "spheres", 1)
    shards = [select_shard(plan, i, 3) for i in range(3)]
    assert sorted(map(repr, sum(shards, []))) == sorted(map(repr, plan))
    batches = make_batches(plan, 4)
    assert [len(b) for b in batches] == [4, 4, 4]  # full batches, slow trials first, then fast ones
    assert [[s.speed for s in b] for b in batches] == [[3.0] * 4, [3.0, 3.0, 5.0, 5.0], [5.0] * 4]


def test_config_file_and_overrides(tmp_path):
    f = tmp_path / "eval.yaml"
    f.write_text("env: trees\nspeeds: [3, 7]\ntrials: 4\n")
    cfg = load_sweep_config(f, {"trials": 2, "seed": None})
    assert (cfg.env, cfg.speeds, cfg.trials, cfg.seed) == (["trees"], [3.0, 7.0], 2, 0)
    f.write_text("trails: 4\n")
    with pytest.raises(Exception, match="eval.yaml: unknown field 'trails'"):
        load_sweep_config(f)
    with pytest.raises(Exception, match="shard"):
        load_sweep_config(None, {"shard": "2/2"})


def test_evaluate_resumes_and_shards_merge(tmp_path, capsys):
    full, a, b, merged = (tmp_path / n for n in ("full", "a", "b", "merged"))
    assert evaluate(full, "--policy", "straight", "--speeds", "3", "6", "--trials", "2") == 0
    recs = lines(full / "trials.jsonl")
    assert len(recs) == 4
    r = recs[0]
    assert r["policy"] == "straight" and r["outcome"]["end_reason"] == "timeout"
    assert set(r["path"]) == {"time", "position", "velocity", "command", "contact", "end"}
    assert r["path"]["end"]["time"] > r["path"]["time"][-1]  # the state after the last tick's physics steps
    assert len(r["path"]["time"]) == len(r["path"]["position"]) >= 40
    assert r["path"]["command"][5] == [r["speed"], 0.0, 0.0]  # straight ahead at the desired speed
    assert r["extra"]["scene"]["env"] == "spheres"
    with open(full / "summary.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(x["policy"], x["speed"], x["trials"]) for x in rows] == [("straight", "3.0", "2"),
                                                                      ("straight", "6.0", "2")]

    # rerun: nothing to fly, file untouched
    before = (full / "trials.jsonl").read_bytes()
    capsys.readouterr()
    assert evaluate(full, "--policy", "straight", "--speeds", "3", "6", "--trials", "2") == 0
    assert "0 trials flown, 4 already done" in capsys.readouterr().out
    assert (full / "trials.jsonl").read_bytes() == before

    # a kill in the middle of the last trial's line: that trial is flown again, the others are not
    data = before.splitlines(keepends=True)
    (full / "trials.jsonl").write_bytes(b"".join(data[:3]) + data[3][:500])
    assert evaluate(full, "--policy", "straight", "--speeds", "3", "6", "--trials", "2") == 0
    assert "1 trials flown, 3 already done" in capsys.readouterr().out
    assert len(records.read_records(full / "trials.jsonl")) == 4

    # two shards in separate directories, merged, give the same trials as the unsharded sweep
    for out, shard in ((a, "0/2"), (b, "1/2")):
        assert evaluate(out, "--policy", "straight", "--speeds", "3", "6", "--trials", "2", "--shard", shard) == 0
    assert len(lines(a / "trials.jsonl")) == len(lines(b / "trials.jsonl")) == 2
    assert main(["evaluate", "--out", str(merged), "--merge", str(a), str(b), "--no-plots"]) == 0
    got = {x.key: x for x in records.read_sweep(merged)}
    want = {x.key: x for x in records.read_sweep(full)}
    assert got.keys() == want.keys()
    for key, rec in want.items():  # the simulator is deterministic: the same paths whatever the batching
        assert got[key].path == rec.path
        for name, value in rec.metrics.items():
            if name != "processing_ms":  # wall time
                assert got[key].metrics[name] == pytest.approx(value, nan_ok=True), name


def test_expert_and_learned_policy_share_scenes_and_report(tmp_path, capsys):
    from vitfly.zoo import create_model, save_checkpoint

    torch.manual_seed(0)
    ckpt = tmp_path / "tiny_convnet.ckpt"
    save_checkpoint(create_model("convnet"), "convnet", True, ckpt)
    out = tmp_path / "eval"
    assert evaluate(out, "--policy", "expert", "--speeds", "4", "--trials", "2") == 0
    # 3 s: long enough to leave the take-off ramp (x < 2 m) behind
    args = ["--speeds", "4", "--trials", "2", "--threads", "1", "--timeout", "3"]
    assert evaluate(out, "--policy", str(ckpt), *args) == 0
    table = capsys.readouterr().out
    assert "tiny_convnet" in table and "expert" in table
    recs = records.read_sweep(out)
    assert {r.policy for r in recs} == {"expert", "tiny_convnet"}
    seeds = {p: sorted(r.scene_seed for r in recs if r.policy == p) for p in ("expert", "tiny_convnet")}
    assert seeds["expert"] == seeds["tiny_convnet"]
    # two policies on the same scenes: paired.csv compares them scene by scene (success, collisions)
    paired = (out / "paired.csv").read_text().splitlines()
    assert paired[0].startswith("env,metric,a,b,speed,pairs") and len(paired) == 3
    assert paired[1].startswith("spheres,success,expert,tiny_convnet,4,2,2,")
    learned = [r for r in recs if r.policy == "tiny_convnet"]
    assert all(r.metrics["processing_ms"] > 0 for r in learned)
    assert all(r.extra["backend"] == "eager" for r in learned)
    # commands are the paper's deployment: norm = desired speed once past the take-off ramp (x >= 2 m), and
    # vx = max(1, x / 2 * 4 m/s) on it
    path = learned[0].path_arrays()
    cmd, x = path["command"], path["position"][:, 0]
    past = x >= 2.0
    assert past.any() and (~past).any()
    assert (cmd[past] ** 2).sum(axis=1) ** 0.5 == pytest.approx(4.0, abs=1e-3)
    assert cmd[~past, 0] == pytest.approx(np.maximum(1.0, x[~past] / 2.0 * 4.0), abs=1e-3)


def test_bad_policy_is_one_line_and_no_output(tmp_path, capsys):
    out = tmp_path / "x"
    assert evaluate(out, "--policy", str(tmp_path / "missing.ckpt")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.ckpt" in err[0] and err[0].startswith("vitfly: error:")
    assert not out.exists()


def test_worker_processes_give_the_same_trials(tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    args = ["--policy", "expert", "--speeds", "5", "--trials", "2", "--num-envs", "1"]
    assert evaluate(one, *args) == 0
    assert evaluate(two, *args, "--workers", "2") == 0
    a = {r.key: r for r in records.read_sweep(one)}
    b = {r.key: r for r in records.read_sweep(two)}
    assert a.keys() == b.keys() and len(a) == 2
    assert all(a[k].path == b[k].path for k in a)


@pytest.mark.parametrize("name", ["spheres", "trees", "window"])
def test_shipped_eval_configs_load(name):
    cfg = load_sweep_config(f"configs/eval/{name}.yaml", {"policy": "straight"})
    assert cfg.env == [name] and cfg.speeds == [3.0, 4.0, 5.0, 6.0, 7.0] and cfg.policy == "straight"


LEGACY = Path(os.environ.get("VITFLY_LEGACY_FIXTURES",
                             Path(__file__).resolve().parents[1] / ".." / "shared/fixtures/legacy"))


@pytest.mark.skipif(not (LEGACY / "convnet.pth").exists(), reason=f"original checkpoints not found in {LEGACY}")
def test_original_checkpoint_with_arch(tmp_path, capsys):
    out = tmp_path / "legacy"
    assert evaluate(out, "--policy", str(LEGACY / "convnet.pth"), "--arch", "convnet", "--speeds", "3",
                    "--trials", "1") == 0
    (rec,) = records.read_sweep(out)
    assert rec.policy == "convnet" and rec.extra["arch"] == "convnet"
    capsys.readouterr()
    assert evaluate(tmp_path / "bad", "--policy", str(LEGACY / "convnet.pth"), "--arch", "vit", "--trials", "1") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "convnet.pth" in err[0]
    assert not (tmp_path / "bad").exists()


def _tiny_checkpoint(path, seed):
    from vitfly.zoo import create_model, save_checkpoint

    torch.manual_seed(seed)
    save_checkpoint(create_model("convnet"), "convnet", True, path)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vitfly: error:"), err
    return err[0]


def test_trials_are_keyed_by_what_was_flown(tmp_path, capsys):
    out, ckpt = tmp_path / "eval", tmp_path / "net.ckpt"
    _tiny_checkpoint(ckpt, seed=0)
    args = ["--policy", str(ckpt), "--name", "net", "--speeds", "4", "--trials", "2"]
    assert evaluate(out, *args) == 0
    first = records.read_sweep(out)
    assert len(first) == 2 and len({r.setup["policy_id"] for r in first}) == 1
    # an identical rerun resumes: nothing is flown again
    capsys.readouterr()
    assert evaluate(out, *args) == 0
    assert "0 trials flown, 2 already done" in capsys.readouterr().out
    before = (out / "trials.jsonl").read_bytes()

    # another checkpoint under the same path and label (a retrain): refused, one line, nothing written
    _tiny_checkpoint(ckpt, seed=1)
    assert evaluate(out, *args) == 2
    line = one_error_line(capsys)
    assert "2 trials of 'net' there were flown with another policy content (" in line and "--overwrite" in line
    assert (out / "trials.jsonl").read_bytes() == before
    # ... flown anew with --overwrite: the stale trials are replaced, not mixed with the new ones
    assert evaluate(out, *args, "--overwrite") == 0
    assert "2 trials flown, 0 already done, 2 of another setup replaced" in capsys.readouterr().out
    second = records.read_sweep(out)
    assert len(second) == 2 and {r.setup["policy_id"] for r in second} != {r.setup["policy_id"] for r in first}
    assert {r.scene_seed for r in second} == {r.scene_seed for r in first}  # the same scenes, flown again

    # another --seed, another preset, other rollout settings under the same label: refused, saying which
    for extra, what in ((["--seed", "1"], "--seed (0, now 1)"), (["--preset", "hard"], "--preset (medium, now hard)"),
                        (["--timeout", "2.0"], "rollout settings")):
        assert evaluate(out, *args, *extra) == 2, extra
        assert what in one_error_line(capsys)
    # under another label they fly beside the others
    assert evaluate(out, *args, "--seed", "1", "--name", "net-seed1") == 0
    recs = records.read_sweep(out)
    assert {r.policy for r in recs} == {"net", "net-seed1"} and len(recs) == 4
    with open(out / "summary.csv") as fh:
        assert {row["policy"] for row in csv.DictReader(fh)} == {"net", "net-seed1"}


def test_merge_refuses_two_setups_under_one_label(tmp_path, capsys):
    a, b, merged = tmp_path / "a", tmp_path / "b", tmp_path / "merged"
    assert evaluate(a, "--policy", "straight", "--speeds", "3", "--trials", "1") == 0
    assert evaluate(b, "--policy", "straight", "--speeds", "3", "--trials", "1", "--seed", "5") == 0
    capsys.readouterr()
    assert main(["evaluate", "--out", str(merged), "--merge", str(a), str(b), "--no-plots"]) == 2
    assert "'straight' holds trials flown with different setups (--seed (0, now 5))" in one_error_line(capsys)
    assert not (merged / "trials.jsonl").exists()


def test_goal_crossing_defines_time_to_goal(tmp_path):
    out = tmp_path / "goal"
    # straight flight reaches x = 60 m (obstacles do not stop it); no control tick lies at or beyond the goal
    assert main(["evaluate", "--out", str(out), "--policy", "straight", "--speeds", "7", "--trials", "2",
                 "--no-gif", "--no-plots", "--no-progress"]) == 0
    for rec in records.read_sweep(out):
        assert rec.end_reason == "goal" and rec.path["position"][-1][0] < 60.0 <= rec.path["end"]["position"][0]
        # about 59.5 m at a little under 7 m/s
        assert 59.5 / 7.0 < rec.metrics["time_to_goal_s"] < 59.5 / 6.0


def test_killed_sweep_resumes(tmp_path, capsys):
    import subprocess
    import sys
    import time

    out = tmp_path / "killed"
    args = ["--policy", "straight", "--speeds", "3", "--trials", "12", "--num-envs", "1", "--timeout", "3.0",
            "--no-gif", "--no-plots", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen([sys.executable, "-m", "vitfly.cli", "evaluate", "--out", str(out), *args], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            f = out / "trials.jsonl"
            if f.exists() and f.read_bytes().count(b"\n") >= 2:
                break
            time.sleep(0.05)
    finally:
        proc.kill()  # SIGKILL: no cleanup of any kind
        proc.wait()
    done = len(records.read_records(out / "trials.jsonl"))
    assert 2 <= done < 12, done
    assert main(["evaluate", "--out", str(out), *args]) == 0
    assert f"{12 - done} trials flown, {done} already done" in capsys.readouterr().out
    recs = records.read_sweep(out)
    assert sorted(r.trial for r in recs) == list(range(12))


def test_int8_backend_flies_and_cuda_absent_is_one_line(tmp_path, capsys):
    from vitfly.zoo import create_model, save_checkpoint

    torch.manual_seed(0)
    ckpt = tmp_path / "tiny_convnet.ckpt"
    save_checkpoint(create_model("convnet"), "convnet", True, ckpt)
    out = tmp_path / "int8"
    assert evaluate(out, "--policy", str(ckpt), "--speeds", "4", "--trials", "1", "--backend", "onnxruntime-int8") == 0
    (rec,) = records.read_sweep(out)
    assert rec.extra["backend"] == "onnxruntime-int8" and len(rec.path_arrays()["command"]) > 10
    capsys.readouterr()
    if torch.cuda.is_available():
        pytest.skip("CUDA is present: the missing-CUDA error cannot be shown here")
    assert evaluate(tmp_path / "gpu", "--policy", str(ckpt), "--trials", "1", "--device", "cuda") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["vitfly: error: --device is 'cuda' but torch sees no CUDA device here; use cpu"]
    assert not (tmp_path / "gpu").exists()


def test_compiled_backend_wraps_the_encoder(tmp_path):
    # --backend compiled: the same network with its encoder behind torch.compile (compiled lazily, on the first
    # call, so building the policy here compiles nothing); eager outputs are the compile path's reference
    from vitfly.eval.policy_source import PolicySource
    from vitfly.zoo import create_model, save_checkpoint
    from vitfly.zoo.compiled import _CompiledOrEager

    ckpt = tmp_path / "c.ckpt"
    save_checkpoint(create_model("convnet"), "convnet", True, ckpt)
    policy = PolicySource(str(ckpt), backend="compiled").build()
    assert isinstance(policy.net.encode, _CompiledOrEager)
    assert not isinstance(PolicySource(str(ckpt)).build().net.encode, _CompiledOrEager)
