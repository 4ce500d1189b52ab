"""`vitfly dagger`: the mixing schedule, MixturePolicy, labelled rollouts, the optional schema fields, and the tiny
preset end to end (interrupted in a round, resumed, rerun, and refused or recomputed under changed settings)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers import load_benchmark

from vitfly.datamodules.schema import (
    TrajectoryRecord,
    TrajectoryWriter,
    _rebuild_committed,
    open_trajectories,
)
from vitfly.errors import VitflyError
from vitfly.eval import records
from vitfly.eval.sweep import derive_scene_seed
from vitfly.sim.expert import ExpertConfig, ExpertObstacles, expert_command
from vitfly.sim.policies import ExpertPolicy, MixturePolicy, StraightPolicy
from vitfly.sim.rollout import LabelledCommands, run_episodes
from vitfly.sim.scenes import make_scene
from vitfly.workflows.dagger import episode_record, run_dagger
from vitfly.workflows.dagger_config import DaggerSchedule, base_collect, load_dagger_config

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "dagger.yaml"


def tiny(out: Path, **sections) -> object:
    overrides = {"out": str(out), "threads": 1, "data": {"collect_config": str(REPO / "configs/collect/spheres.yaml")}}
    for name, values in sections.items():
        overrides[name] = {**overrides.get(name, {}), **values} if isinstance(values, dict) else values
    return load_dagger_config(CONFIG, "tiny", overrides)


# --- the schedule and the mixture -----------------------------------------------------------------


def test_beta_schedule_by_hand():
    s = DaggerSchedule(rounds=3, beta0=1.0, decay=0.5)
    assert [s.beta(i) for i in range(4)] == [1.0, 0.5, 0.25, 0.125]
    s = DaggerSchedule(beta0=0.8, decay=0.9)
    assert s.beta(0) == pytest.approx(0.8) and s.beta(2) == pytest.approx(0.8 * 0.81)  # 0.648
    assert DaggerSchedule(beta0=1.0, decay=0.0).beta(1) == 0.0  # round 1 on: the student alone


class Constant:
    """A policy that commands the same vector in every env (and counts its calls)."""

    needs_depth = False

    def __init__(self, vector):
        self.vector, self.calls = np.asarray(vector, float), 0

    def reset(self, num_envs):
        self.n = num_envs

    def __call__(self, obs):
        self.calls += 1
        return np.tile(self.vector, (len(obs.active), 1))


def test_mixture_flies_the_expert_iff_the_seeded_draw_is_below_beta():
    expert, student = Constant([1.0, 0.0, 0.0]), Constant([0.0, 1.0, 0.0])
    beta, seeds = 0.4, [11, 12, 13]
    mix = MixturePolicy(expert, student, beta, seeds=seeds)
    mix.reset(3)
    rngs = [np.random.default_rng(s) for s in seeds]  # the draws, by hand
    flown_expert = 0
    for tick in range(40):
        active = np.array([True, tick < 25, tick % 3 != 0])  # env 1 finishes; env 2 skips ticks
        out = mix(SimpleNamespace(active=active))
        assert isinstance(out, LabelledCommands)
        np.testing.assert_array_equal(out.label, np.tile([1.0, 0.0, 0.0], (3, 1)))  # always the expert's
        for i in range(3):
            if not active[i]:
                continue  # an inactive env draws nothing: its stream does not advance
            u = rngs[i].random()
            want = [1.0, 0.0, 0.0] if u < beta else [0.0, 1.0, 0.0]
            np.testing.assert_array_equal(out.command[i], want)
            flown_expert += u < beta
    assert expert.calls == student.calls == 40  # both run at every tick (the student's state follows the flight)
    assert mix.expert_ticks.sum() == flown_expert and mix.ticks.tolist() == [40, 25, 26]


def test_mixture_extremes_and_int_seed():
    for beta, want in ((1.0, [1.0, 0.0, 0.0]), (0.0, [0.0, 1.0, 0.0])):
        mix = MixturePolicy(Constant([1.0, 0, 0]), Constant([0, 1.0, 0]), beta, seeds=5)
        mix.reset(4)
        for _ in range(10):
            np.testing.assert_array_equal(mix(SimpleNamespace(active=np.ones(4, bool))).command, np.tile(want, (4, 1)))
    mix = MixturePolicy(Constant([1.0, 0, 0]), Constant([0, 1.0, 0]), 0.5, seeds=7)
    mix.reset(2)
    u = [np.random.default_rng([7, i]).random() for i in range(2)]  # an int seed s gives env i [s, i]
    out = mix(SimpleNamespace(active=np.ones(2, bool)))
    assert [bool(out.command[i, 0] == 1.0) for i in range(2)] == [x < 0.5 for x in u]
    with pytest.raises(VitflyError, match="beta"):
        MixturePolicy(Constant([1.0, 0, 0]), None, 0.5)
    with pytest.raises(VitflyError, match="probability"):
        MixturePolicy(Constant([1.0, 0, 0]), Constant([0, 1.0, 0]), 1.5)


def test_rollout_records_the_expert_label_and_the_flown_command_separately():
    scene = make_scene("spheres", "medium", seed=3)
    speed = 5.0
    mix = MixturePolicy(ExpertPolicy(), StraightPolicy(), 0.5, seeds=[[9, 0]])
    result = run_episodes([scene], [speed], mix)[0]
    log = result.log
    assert log.label.shape == log.command.shape == (len(log), 3)
    view = ExpertObstacles.from_scene(scene)
    for t in range(len(log)):  # the label is the expert's command at the state the drone was in
        np.testing.assert_allclose(log.label[t], expert_command(log.position[t], view, speed, ExpertConfig()))
    straight = np.all(log.command == [speed, 0.0, 0.0], axis=1)
    expert_flew = np.all(log.command == log.label, axis=1)
    assert np.all(straight | expert_flew) and straight.any() and (~straight & expert_flew).any()
    # a dataset record of it: the label is what training learns, the flown command is kept beside it
    collect_cfg = base_collect(load_dagger_config(CONFIG, "tiny"))
    rec = episode_record(collect_cfg, dataclasses.replace(result, log=dataclasses.replace(
        log, depth=np.zeros((len(log), 60, 90), np.float32))), 2, 0.25)
    rows = collect_cfg.logged_ticks(log.position[:, 0])
    np.testing.assert_array_equal(rec.velocity_cmd, log.label[rows])
    np.testing.assert_array_equal(rec.velocity_cmd_executed, log.command[rows])
    assert (rec.dagger_round, rec.dagger_beta) == (2, 0.25)
    assert run_episodes([scene], [speed], ExpertPolicy())[0].log.label is None  # a plain policy labels nothing


# --- the schema's optional fields -----------------------------------------------------------------


def record(t: int, seed: int, **extra) -> TrajectoryRecord:
    rng = np.random.default_rng(seed)
    return TrajectoryRecord(
        depth=rng.integers(0, 256, (t, 60, 90), dtype=np.uint8), desired_speed=5.0,
        quat=np.tile([1.0, 0, 0, 0], (t, 1)), position=rng.normal(size=(t, 3)), velocity=rng.normal(size=(t, 3)),
        velocity_cmd=rng.normal(size=(t, 3)), time=np.arange(t) / 30.0, collision=np.zeros(t, bool), seed=seed,
        **extra)


def test_optional_fields_round_trip_and_old_files_stay_valid(tmp_path):
    fields = ("velocity_cmd_executed", "dagger_round", "dagger_beta")
    executed = np.full((7, 3), 2.5)
    with TrajectoryWriter(tmp_path / "d.h5", optional_fields=fields) as w:
        w.append(record(7, 1, velocity_cmd_executed=executed, dagger_round=3, dagger_beta=0.125))
        with pytest.raises(VitflyError, match="lacks"):
            w.append(record(4, 2))  # the file holds the fields for every trajectory
    with open_trajectories(tmp_path / "d.h5") as tf:
        rec = tf[0]
        assert tf.meta(0)["dagger_round"] == 3 and tf.meta(0)["dagger_beta"] == 0.125
        np.testing.assert_array_equal(rec.velocity_cmd_executed, executed.astype(np.float32))
        np.testing.assert_array_equal(rec.velocity_cmd, record(7, 1).velocity_cmd.astype(np.float32))
    # a crashed writer's file is rebuilt with its optional fields
    _rebuild_committed(tmp_path / "d.h5", tmp_path / "copy.h5")
    with open_trajectories(tmp_path / "copy.h5") as tf:
        assert tf.optional_fields == fields and tf[0].dagger_round == 3
    # a file without them: valid, its records carry None, and it takes no records that carry them
    with TrajectoryWriter(tmp_path / "old.h5") as w:
        w.append(record(5, 4))
        with pytest.raises(VitflyError, match="does not hold"):
            w.append(record(5, 5, dagger_round=1, dagger_beta=0.5, velocity_cmd_executed=np.zeros((5, 3))))
    with open_trajectories(tmp_path / "old.h5") as tf:
        assert tf.optional_fields == () and set(tf.meta(0)) == {"env", "seed", "desired_speed", "n_collisions",
                                                                 "success"}
        assert tf[0].dagger_round is None and tf[0].velocity_cmd_executed is None
    with pytest.raises(VitflyError, match="'/velocity_cmd_executed' is missing"):
        TrajectoryWriter(tmp_path / "old.h5", optional_fields=fields)
    with pytest.raises(VitflyError, match="probability"):
        TrajectoryWriter(tmp_path / "b.h5", optional_fields=fields).append(
            record(3, 6, velocity_cmd_executed=np.zeros((3, 3)), dagger_round=0, dagger_beta=2.0))


# --- configuration ----------------------------------------------------------------------------------


@pytest.mark.parametrize("sections, message", [
    ({"evaluate": {"seed": 999}}, "evaluate.seed must be >= 1000"),
    ({"data": {"seed": 498}}, r"training flights must stay in \[0, 1000\)"),  # 498 + 500 + 2 rounds = 1000
    ({"schedule": {"beta0": 0.5}}, "set train.init_checkpoint"),
    ({"train": {"init_checkpoint": "pretrained:lstmnet"}}, r"holds lstmnet .*, not train.model convnet"),
    ({"train": {"init_checkpoint": "pretrained:nope"}}, r"pretrained:nope: not in .*manifest.json"),
    ({"schedule": {"decay": 1.5}}, r"schedule.decay must be in \[0, 1\]"),
    ({"data": {"collect": {"trajectories": 5}}}, "use data.expert_trajectories"),
    ({"train": {"colour": 1}}, "unknown field 'colour'"),
    ({"report": {"target_speed": 9.0}}, "not among evaluate.speeds"),
])
def test_bad_config_is_one_line(tmp_path, sections, message):
    with pytest.raises(VitflyError, match=message):
        tiny(tmp_path / "run", **sections)


@pytest.mark.parametrize("preset", ["tiny", "laptop", "laptop_vit_lstm", "paper"])
def test_every_shipped_preset_loads_and_checks(preset):
    cfg = load_dagger_config(CONFIG, preset)  # check_config runs inside: pretrained weights, seeds, speeds
    assert cfg.preset == preset and cfg.out.endswith(preset.replace("laptop_", "laptop-"))
    if preset == "laptop_vit_lstm":  # the target network from the shipped weights, one epoch a round
        assert (cfg.train.model, cfg.train.init_checkpoint) == ("vit_lstm", "pretrained:vit_lstm")
        assert cfg.train.epochs == cfg.train.finetune_epochs == 1


def test_training_seeds_are_disjoint_from_evaluation_seeds():
    cfg = load_dagger_config(CONFIG, "laptop")
    seeds = [cfg.collect_seed(r, baseline) for r in cfg.rounds for baseline in (False, True)]
    assert seeds == [0, 500, 1, 501, 2, 502, 3, 503] and max(seeds) < 1000 <= cfg.evaluate.seed


# --- the tiny preset end to end ---------------------------------------------------------------------


class Killed(Exception):
    pass


def file_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """The tiny preset, interrupted after round 1's first committed flight, then rerun to the end."""
    out = tmp_path_factory.mktemp("dagger") / "run"
    cfg = tiny(out)
    committed = []

    def kill(stage: str, n: int) -> None:
        if stage == "r1.collect":
            committed.append(n)
            raise Killed

    with pytest.raises(Killed):
        run_dagger(cfg, progress=False, on_trajectory=kill)
    with open_trajectories(out / "data/dagger.h5", check_values=False) as tf:
        assert len(tf) == committed[0] == 5  # round 0's 4 flights and round 1's first
        first = tf[4]
    flown = []
    report = run_dagger(cfg, progress=False, on_trajectory=lambda stage, n: flown.append(stage))
    return SimpleNamespace(cfg=cfg, out=out, first=first, flown=flown, report=report)


def test_tiny_end_to_end(tiny_run):
    out = tiny_run.out
    for name in ("dagger.md", "dagger.csv", "dagger.json", "success_vs_frames.png", "paths_spheres.png"):
        assert (out / name).stat().st_size > 0, name
    report = json.loads((out / "dagger.json").read_text())
    assert report["target"]["speed"] == 7.0 and report["target"]["met"] in (True, False)
    recs = records.read_sweep(out / "eval")
    labels = {r.policy for r in recs}
    assert labels == {"bc-r0", "dagger-r1", "bc-r1", "dagger-r2", "bc-r2", "expert"}
    for label in labels:  # 2 speeds x 2 trials, on the same scenes, from seed 1000
        mine = [r for r in recs if r.policy == label]
        assert sorted((r.speed, r.trial) for r in mine) == [(3.0, 0), (3.0, 1), (7.0, 0), (7.0, 1)]
        assert {r.scene_seed for r in mine} == {derive_scene_seed(1000, "spheres", k) for k in (0, 1)}
    md = (out / "dagger.md").read_text()
    assert "| 2 | 0.250 |" in md and "BC (equal frames)" in md and "Target" in md
    assert "expert flights (shared by both methods)" in md  # round 0 from scratch: no "starting from"


def test_datasets_tag_rounds_and_match_frames(tiny_run):
    out = tiny_run.out
    with open_trajectories(out / "data/dagger.h5") as d, open_trajectories(out / "data/bc.h5") as b:
        d_round, b_round = np.asarray(d.table["dagger_round"]), np.asarray(b.table["dagger_round"])
        assert np.bincount(d_round).tolist() == [4, 2, 2]  # expert_trajectories, then 2 per round
        np.testing.assert_allclose(d.table["dagger_beta"], [1.0] * 4 + [0.5] * 2 + [0.25] * 2)
        np.testing.assert_allclose(b.table["dagger_beta"], 1.0)
        for r in (1, 2):  # the baseline holds exactly as many labelled frames after every round
            assert d.lengths[d_round <= r].sum() == b.lengths[b_round <= r].sum()
        for m in range(4):  # round 0 is shared, flight for flight
            assert d.meta(m) == b.meta(m)
            np.testing.assert_array_equal(d.read(m, ("depth",))["depth"], b.read(m, ("depth",))["depth"])
        eval_seeds = {derive_scene_seed(1000, "spheres", k) for k in range(2)}
        assert not (set(d.table["seed"]) | set(b.table["seed"])) & eval_seeds
        # the label is the expert's: equal to the flown command wherever the expert flew (round 0: always),
        # different where the student flew (rounds >= 1)
        for m in range(len(d)):
            rec = d[m]
            same = np.all(rec.velocity_cmd == rec.velocity_cmd_executed, axis=1)
            assert same.all() if d_round[m] == 0 else not same.all()
    for r in (1, 2):  # the baseline trained exactly as many optimiser steps as DAgger, and flies what it ended with
        steps = [json.loads((out / f"manifests/r{r}.{k}.json").read_text())["result"]["steps"]
                 for k in ("train", "bc-train")]
        final = [torch.load(out / f"train/{k}-r{r}/checkpoints/last.ckpt", weights_only=True)["global_step"]
                 for k in ("dagger", "bc")]
        assert steps[0] == steps[1] == final[0] == final[1] > 0
    assert not list(out.glob("train/*/checkpoints/final.ckpt"))  # last.ckpt only, as every other training


def test_labels_are_the_experts_commands_at_the_logged_states(tiny_run):
    with open_trajectories(tiny_run.out / "data/dagger.h5") as d:
        for m in np.flatnonzero(np.asarray(d.table["dagger_round"]) > 0):
            rec = d[m]
            view = ExpertObstacles.from_scene(make_scene("spheres", "medium", int(rec.seed)))
            speed = float(rec.desired_speed[0])
            want = np.array([expert_command(p.astype(np.float64), view, speed, ExpertConfig()) for p in rec.position])
            # positions are stored as float32: a waypoint on a blocking boundary may flip for a tick, no more
            close = np.all(np.abs(want - rec.velocity_cmd) < 1e-3, axis=1)
            assert close.mean() > 0.95
            assert not np.all(np.abs(want - rec.velocity_cmd_executed) < 1e-3)


def test_resume_mid_round_keeps_committed_flights(tiny_run):
    first = tiny_run.first
    # after the interruption, round 1 flew only what was missing: 1 of its 2 flights, then the later rounds
    assert tiny_run.flown.count("r1.collect") == 1 and tiny_run.flown.count("r0.collect") == 0
    with open_trajectories(tiny_run.out / "data/dagger.h5") as d:
        again = d[4]  # round 1's first flight, committed before the interruption
        assert again.seed == first.seed
        np.testing.assert_array_equal(again.depth, first.depth)
        np.testing.assert_array_equal(again.velocity_cmd, first.velocity_cmd)


def test_rerun_recomputes_nothing_and_changed_settings_are_refused(tiny_run, capsys):
    out, cfg = tiny_run.out, tiny_run.cfg
    watched = [out / "data/dagger.h5", out / "data/bc.h5", *sorted(out.glob("train/*/checkpoints/last.ckpt")),
               out / "eval/trials.jsonl"]
    before = {p: (file_hash(p), p.stat().st_mtime_ns) for p in watched}
    capsys.readouterr()
    run_dagger(cfg, progress=False)
    text = capsys.readouterr().out
    stage_lines = [line for line in text.splitlines() if line.startswith(("[r", "[paths]"))]
    assert len(stage_lines) == 14 and all(line.endswith("] done before") for line in stage_lines)
    assert {p: (file_hash(p), p.stat().st_mtime_ns) for p in watched} == before
    # other settings that made the flights: refused before anything runs, naming what differs
    with pytest.raises(VitflyError, match=r"round 1 flights \(r1.collect\) were made with other settings "
                                          r"\(differs: beta\)"):
        run_dagger(tiny(out, schedule={"decay": 0.7}), progress=False)
    with pytest.raises(VitflyError, match=r"round 2 flights \(r2.collect\).*\(differs: student\)"):
        run_dagger(tiny(out, train={"finetune_epochs": 2}), progress=False)
    assert {p: (file_hash(p), p.stat().st_mtime_ns) for p in watched} == before


def test_changed_training_settings_retrain_when_no_flights_depend_on_them(tmp_path, capsys):
    out = tmp_path / "run"
    run_dagger(tiny(out), stop_after="r0.train", progress=False)
    ckpt = out / "train/r0/checkpoints/last.ckpt"
    steps = torch.load(ckpt, weights_only=True)["global_step"]
    capsys.readouterr()
    run_dagger(tiny(out, train={"epochs": 2}), stop_after="r0.train", progress=False)
    text = capsys.readouterr().out
    assert "[r0.collect] done before" in text and "retraining from the start" in text
    assert torch.load(ckpt, weights_only=True)["global_step"] > steps  # two epochs now


def test_init_weights_start_a_fine_tune_from_a_checkpoint(tiny_run, tmp_path):
    from vitfly.training import train_policy
    from vitfly.zoo import load_network

    init = tiny_run.out / "train/r0/checkpoints/last.ckpt"
    kwargs = dict(max_epochs=-1, batch_size=2, progress_bar=False,
                  policy_kwargs={"lr": 0.0, "warmup_epochs": 0, "cpu_threads": 1},
                  trainer_kwargs={"max_steps": 1, "limit_val_batches": 0, "enable_model_summary": False})
    train_policy(tiny_run.out / "data/dagger.h5", "convnet", tmp_path / "ft", init_weights=init, **kwargs)
    got = load_network(tmp_path / "ft/checkpoints/last.ckpt").state_dict()
    want = load_network(init).state_dict()
    for k, v in want.items():  # lr 0: the network is still the one it started from (batch-norm buffers aside)
        if "running" not in k and "num_batches" not in k:
            torch.testing.assert_close(got[k], v, msg=k)
    with pytest.raises(VitflyError, match="init_weights holds model 'convnet'"):
        train_policy(tiny_run.out / "data/dagger.h5", "lstmnet", tmp_path / "other", init_weights=init, **kwargs)


def test_round_zero_can_start_from_the_shipped_weights(tmp_path):
    from vitfly.workflows.dagger import _load_student, plan_stages
    from vitfly.zoo.pretrained import manifest_entry

    cfg = tiny(tmp_path / "run", schedule={"beta0": 0.5}, train={"init_checkpoint": "pretrained:convnet"})
    student = _load_student(cfg, "pretrained:convnet")  # what round 0 flies beside the expert
    assert type(student.net).__name__ == "ConvNet"
    # the stages are keyed by the shipped file's hash: other weights under the same name start a new run
    key = json.dumps([s.key for s in plan_stages(cfg)], default=str)
    assert manifest_entry("convnet")["sha256"][:16] in key


# --- the batched engine -------------------------------------------------------------------------------


def flights(path: Path) -> tuple[list, dict]:
    with open_trajectories(path, check_values=False) as tf:
        return [tf[m] for m in range(len(tf))], tf.config


def assert_same_flights(ref: list, got: list) -> None:
    assert len(ref) == len(got) > 0
    for a, b in zip(ref, got, strict=True):
        assert (a.seed, a.length, a.n_collisions, a.success, a.dagger_round, a.dagger_beta) == (
            b.seed, b.length, b.n_collisions, b.success, b.dagger_round, b.dagger_beta)
        np.testing.assert_array_equal(a.depth, b.depth)  # uint8: the same pixels
        for name in ("position", "velocity", "quat", "velocity_cmd", "velocity_cmd_executed"):
            np.testing.assert_allclose(getattr(b, name), getattr(a, name), rtol=0, atol=1e-6, err_msg=name)


def test_a_round_with_a_student_flies_alike_on_the_batched_engine(tmp_path):
    """A round that mixes a student (the shipped ConvNet) with the expert, on the batched engine in float64 on the
    CPU: the numpy engine's flights, labels and flown commands, the engine stored with the data."""
    mixed = {"schedule": {"beta0": 0.5}, "train": {"init_checkpoint": "pretrained:convnet"}}
    numpy_cfg = tiny(tmp_path / "numpy", **mixed, data={"expert_trajectories": 2})
    batched_cfg = tiny(tmp_path / "batched", **mixed, data={"expert_trajectories": 2, "collect": {"sim": "batched"}})
    for cfg in (numpy_cfg, batched_cfg):
        run_dagger(cfg, stop_after="r0.collect", progress=False)
    ref, ref_config = flights(tmp_path / "numpy/data/dagger.h5")
    got, got_config = flights(tmp_path / "batched/data/dagger.h5")
    assert_same_flights(ref, got)
    assert any(np.abs(r.velocity_cmd_executed - r.velocity_cmd).max() > 0 for r in got)  # the student flew too
    assert "sim" not in ref_config["collect"]
    assert got_config["collect"]["sim"] == {"engine": "batched", "device": "cpu", "dtype": "float64", "compile": False}
    shares = [json.loads((tmp_path / f"{name}/manifests/r0.collect.json").read_text())["result"]["expert_tick_share"]
              for name in ("numpy", "batched")]
    assert shares[0] == shares[1] and 0 < shares[0] < 1


def test_the_command_line_flies_every_flight_on_the_batched_engine(tiny_run, tmp_path, capsys):
    """``vitfly dagger --sim batched``: round 0's expert flights (the numpy run's, row for row) and the sweeps'
    engine; a resume with the other engine is refused before anything runs."""
    from vitfly.cli import main
    from vitfly.workflows.dagger_config import eval_stage

    out = tmp_path / "run"
    common = ["dagger", "--config", str(CONFIG), "--preset", "tiny", "--out", str(out), "--threads", "1",
              "--no-progress"]
    assert main([*common, "--sim", "batched", "--stop-after", "r0.collect"]) == 0
    got, config = flights(out / "data/dagger.h5")
    ref, _ = flights(tiny_run.out / "data/dagger.h5")
    assert_same_flights([r for r in ref if r.dagger_round == 0], got)
    assert config["collect"]["sim"]["engine"] == "batched"
    batched = tiny(out, data={"collect": {"sim": "batched"}}, evaluate={"sim": "batched", "sim_dtype": "float32"})
    stage = eval_stage(batched)
    assert (stage.sim, stage.sim_dtype, stage.physics) == ("batched", "float32", "native")
    capsys.readouterr()
    assert main(common) == 2  # the numpy engine over flights the batched one made
    assert "round 0" in capsys.readouterr().err
    # a preset whose expert flights take worker processes (the paper's 8) flies them in this one instead
    import argparse

    from vitfly.commands import dagger as command

    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    args = parser.parse_args(["--config", str(CONFIG), "--preset", "paper", "--sim", "batched", "--sim-dtype",
                              "float32"])
    paper = load_dagger_config(CONFIG, "paper", command.config_overrides(args))
    assert (paper.data.workers, paper.evaluate.sim, paper.evaluate.sim_dtype) == (1, "batched", "float32")
    assert base_collect(paper).engine.dtype == "float32"
    assert load_dagger_config(CONFIG, "paper").data.workers == 8


@pytest.mark.slow
def test_the_round_benchmark_flies_both_engines_alike(tmp_path, capsys):
    # benchmarks/dagger_round.py, two flights: float64 on the CPU, both engines write the same frames and the
    # expert flies the same share of ticks
    bench = load_benchmark("dagger_round")
    out = tmp_path / "rows.json"
    assert bench.main(["--flights", "2", "--settings", "numpy", "batched", "--json", str(out)]) == 0
    numpy_row, batched_row = json.loads(out.read_text())
    assert [numpy_row["setting"], batched_row["setting"]] == ["numpy", "batched"]
    assert numpy_row["frames"] == batched_row["frames"] > 0
    assert numpy_row["expert_tick_share"] == batched_row["expert_tick_share"]
    assert "| batched |" in capsys.readouterr().out
