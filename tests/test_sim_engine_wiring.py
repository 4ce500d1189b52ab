"""The batched engine wired into `vitfly evaluate` and `vitfly collect` (``--sim batched``): the same trials and
data as the numpy engine in float64 on the CPU, the engine in every record and dataset and in the keys,
and one line for a bad setting."""

import dataclasses
import json

import h5py
import numpy as np
import pytest
import torch

from vitfly.cli import main
from vitfly.eval import records
from vitfly.sim.engine import SimEngine

# 3 s trials at 7 m/s: about 20 m, through the first obstacles of a hard spheres scene
FAST = ["--timeout", "3.0", "--speeds", "7", "--trials", "2", "--preset", "hard", "--physics", "native",
        "--no-gif", "--no-plots", "--no-progress", "--num-envs", "2"]
TIMING = {"processing_ms"}  # wall-clock metrics: differ between any two runs


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def evaluate(out, *args):
    return main(["evaluate", "--out", str(out), *FAST, *args])


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vitfly: error:"), err
    return err[0]


def tiny_checkpoint(path):
    from vitfly.zoo import create_model, save_checkpoint

    torch.manual_seed(0)
    save_checkpoint(create_model("convnet"), "convnet", True, path)
    return str(path)


def assert_same_trials(ref, got):
    assert [(r.env, r.speed, r.trial, r.scene_seed) for r in ref] == [(r.env, r.speed, r.trial, r.scene_seed)
                                                                       for r in got]
    for a, b in zip(ref, got, strict=True):
        assert (a.end_reason, a.success_paper, a.success_strict, a.reached_goal) == (
            b.end_reason, b.success_paper, b.success_strict, b.reached_goal)
        assert a.path["contact"] == b.path["contact"]
        for name in ("time", "position", "velocity", "command"):  # rounded as stored: equal, or one last digit
            assert np.allclose(a.path[name], b.path[name], rtol=0, atol=1.5e-6), name
        for name, value in a.metrics.items():
            if name not in TIMING:
                assert np.isclose(value, b.metrics[name], rtol=1e-6, atol=1e-6, equal_nan=True), name
        assert {k: v for k, v in a.extra.items() if k not in ("sim", "batch_call_ms")} == {
            k: v for k, v in b.extra.items() if k not in ("sim", "batch_call_ms")}


@pytest.mark.parametrize("policy", ["expert", "straight", "net"])
def test_a_batched_sweep_flies_the_numpy_sweep(tmp_path, policy):
    if policy == "net":
        policy = tiny_checkpoint(tmp_path / "net.ckpt")
    assert evaluate(tmp_path / "numpy", "--policy", policy) == 0
    assert evaluate(tmp_path / "batched", "--policy", policy, "--sim", "batched") == 0
    ref, got = records.read_sweep(tmp_path / "numpy"), records.read_sweep(tmp_path / "batched")
    assert len(got) == 2
    assert_same_trials(ref, got)
    assert {r.extra["sim"]["engine"] for r in ref} == {"numpy"} and {r.extra["physics"] for r in ref} == {"native"}
    assert [r.extra["sim"] for r in got] == [{"engine": "batched", "device": "cpu", "dtype": "float64",
                                              "compile": False}] * 2
    assert {r.extra["physics"] for r in got} == {"native"}
    if "straight" in policy:
        assert sum(r.metrics["collisions"] for r in got) >= 1  # the flights meet obstacles, counted alike
    assert {r.setup["rollout_id"] for r in ref}.isdisjoint({r.setup["rollout_id"] for r in got})


def test_the_engine_keys_the_trials(tmp_path, capsys):
    out = tmp_path / "eval"
    assert evaluate(out, "--policy", "straight") == 0
    capsys.readouterr()
    # the other engine under the same label: refused, saying which engine flew the trials there
    assert evaluate(out, "--policy", "straight", "--sim", "batched") == 2
    line = one_error_line(capsys)
    assert "rollout settings" in line and "(simulator numpy, now batched cpu float64)" in line
    # float32 is another setup of the batched engine too; --overwrite flies anew
    assert evaluate(out, "--policy", "straight", "--sim", "batched", "--sim-dtype", "float32", "--overwrite") == 0
    assert "2 trials flown, 0 already done, 2 of another setup replaced" in capsys.readouterr().out
    assert evaluate(out, "--policy", "straight", "--sim", "batched", "--sim-dtype", "float32") == 0
    assert "0 trials flown, 2 already done" in capsys.readouterr().out
    assert evaluate(out, "--policy", "straight", "--sim", "batched") == 2
    assert "(simulator batched cpu float32, now batched cpu float64)" in one_error_line(capsys)


def test_the_numpy_engine_keeps_its_keys():
    # sweeps flown before the engine choice existed resume: the numpy engine adds nothing to the rollout id
    from vitfly.eval.fingerprint import rollout_fingerprint
    from vitfly.sim.rollout import RolloutConfig

    cfg = RolloutConfig(physics="native")
    assert rollout_fingerprint(cfg, SimEngine().key()) == rollout_fingerprint(cfg)
    assert rollout_fingerprint(cfg, SimEngine("batched").key()) != rollout_fingerprint(cfg)
    assert SimEngine("batched", "cpu").key() == SimEngine("batched", "cpu:0").key()


@pytest.mark.parametrize("args, expected", [
    (["--sim-device", "cuda"], "field 'sim_device' is 'cuda' but 'sim' is 'numpy'"),
    (["--sim", "batched", "--sim-device", "tpu"], "field 'sim_device' is 'tpu'; expected cpu, cuda or cuda:N"),
    (["--sim", "batched", "--physics", "pybullet"], "'pybullet' with the batched engine"),
])
def test_bad_engine_settings_are_one_line(tmp_path, capsys, args, expected):
    fast = [a for a in FAST if a not in ("--physics", "native")]
    assert main(["evaluate", "--out", str(tmp_path / "x"), *fast, "--policy", "straight", *args]) == 2
    assert expected in one_error_line(capsys)
    assert not (tmp_path / "x").exists()


def test_yaml_fields_and_a_missing_cuda(tmp_path):
    from vitfly.errors import VitflyError
    from vitfly.eval.config import load_sweep_config

    f = tmp_path / "eval.yaml"
    f.write_text("sim: batched\nsim_dtype: float32\n")
    cfg = load_sweep_config(f)
    assert cfg.engine == SimEngine("batched", "cpu", "float32") and cfg.physics == "native"
    f.write_text("sim_compile: true\n")
    with pytest.raises(VitflyError, match="field 'sim_compile' is True but 'sim' is 'numpy'"):
        load_sweep_config(f)
    f.write_text("sim: torch\n")
    with pytest.raises(VitflyError, match=r"eval.yaml: field 'sim' is 'torch'; expected one of numpy, batched"):
        load_sweep_config(f)
    if not torch.cuda.is_available():
        with pytest.raises(VitflyError, match="torch sees no CUDA device here"):
            load_sweep_config(None, {"sim": "batched", "sim_device": "cuda"})


COLLECT = ["--trajectories", "3", "--speeds", "6", "7", "--seed", "3", "--no-progress", "--physics", "native"]


def collect_file(tmp_path, name, *args):
    out = tmp_path / f"{name}.h5"
    cfg = tmp_path / "short.yaml"
    cfg.write_text("preset: hard\ntimeout_s: 3.0\nlog_every_tick: true\n")
    assert main(["collect", "--config", str(cfg), "--out", str(out), *COLLECT, *args]) == 0
    return out


def test_collect_batched_writes_the_numpy_dataset(tmp_path, capsys):
    ref = collect_file(tmp_path, "numpy")
    got = collect_file(tmp_path, "batched", "--sim", "batched", "--num-envs", "2")
    with h5py.File(ref) as a, h5py.File(got) as b:
        config_a, config_b = json.loads(a.attrs["config"]), json.loads(b.attrs["config"])
        assert "sim" not in config_a["collect"]  # a numpy dataset's bytes are those of before the engine choice
        assert config_b["collect"].pop("sim") == {"engine": "batched", "device": "cpu", "dtype": "float64",
                                                  "compile": False}
        assert config_a == config_b
        for name in ("desired_speed", "time", "collision", "traj_offsets", "trajectories/seed",
                     "trajectories/n_collisions", "trajectories/success"):
            assert np.array_equal(a[name][()], b[name][()]), name
        for name in ("quat", "position", "velocity", "velocity_cmd"):  # float32 of values 1e-13 apart
            assert np.allclose(a[name][()], b[name][()], rtol=1e-6, atol=1e-6), name
        depth = np.abs(a["depth"][()].astype(int) - b["depth"][()].astype(int))
        assert depth.max() <= 1 and (depth > 0).mean() < 1e-4  # a uint8 level at most, at a rounding edge
    # the engine is part of the dataset's settings: resuming with the other engine is refused
    capsys.readouterr()
    cfg = tmp_path / "short.yaml"
    assert main(["collect", "--config", str(cfg), "--out", str(got), *COLLECT, "--trajectories", "4"]) == 2
    assert "was collected with different settings" in one_error_line(capsys)


def test_collect_bad_engine_settings_are_one_line(tmp_path, capsys):
    out = tmp_path / "x.h5"
    with pytest.raises(SystemExit):
        main(["collect", "--out", str(out), *COLLECT, "--sim-dtype", "float16"])
    assert "argument --sim-dtype: invalid choice: 'float16'" in capsys.readouterr().err
    assert main(["collect", "--out", str(out), *COLLECT, "--sim", "batched", "--workers", "2"]) == 2
    assert "field workers is 2 with sim batched" in one_error_line(capsys)
    assert not out.exists()


@pytest.mark.parametrize("arch", ["convnet", "lstmnet"])
def test_a_learned_policy_has_a_tensor_path_with_the_numpy_commands(arch):
    from vitfly.eval.learned_policy import BatchedLearnedPolicy, LearnedPolicy
    from vitfly.sim.batched.policies import BatchedObservation, as_batched_policy
    from vitfly.sim.rollout import Observation
    from vitfly.zoo import create_model

    torch.manual_seed(1)
    net = create_model(arch)
    host, twin = LearnedPolicy(net), as_batched_policy(LearnedPolicy(net))
    assert isinstance(twin, BatchedLearnedPolicy)
    n, rng = 4, np.random.default_rng(0)
    host.reset(n), twin.reset(n)
    for tick, active in enumerate(([True] * 4, [True, False, True, True], [False, False, True, False])):
        depth = rng.random((n, 60, 90))
        quat = rng.normal(size=(n, 4))
        quat /= np.linalg.norm(quat, axis=1, keepdims=True)
        pos, speed, act = rng.uniform(0.0, 4.0, (n, 3)), np.array([3.0, 5.0, 7.0, 4.0]), np.array(active)
        want = host(Observation(depth.astype(np.float32), speed, quat, pos, np.zeros((n, 3)), [], act,
                                np.zeros(n), tick))
        t = torch.tensor
        got = twin(BatchedObservation(t(depth), t(speed), t(quat), t(pos), t(np.zeros((n, 3))), t(act), 0.0, tick,
                                      None))
        assert got.dtype == torch.float64
        assert np.allclose(got.numpy()[act], want[act], rtol=0, atol=1e-12)  # the recurrent state carried alike


def test_workflows_pass_the_engine_through(tmp_path):
    from pathlib import Path

    from vitfly.errors import VitflyError
    from vitfly.workflows.dagger_config import SIM_FIELDS, base_collect, evaluate_key, load_dagger_config
    from vitfly.workflows.pipeline import EvalStage, sweep_config
    from vitfly.workflows.reproduce_config import ReproduceConfig, ReproduceEvaluate, eval_stage

    sweep = sweep_config(EvalStage(sim="batched", sim_dtype="float32"), tmp_path, "expert").validate()
    assert sweep.engine == SimEngine("batched", "cpu", "float32")
    stage = eval_stage(ReproduceConfig(evaluate=ReproduceEvaluate(sim="batched")), ["trees"], [3.0], 1)
    assert (stage.sim, stage.sim_device, stage.sim_dtype) == ("batched", "cpu", "float64")
    repo = Path(__file__).resolve().parents[1]
    data = {"collect_config": str(repo / "configs/collect/spheres.yaml"), "collect": {"sim": "batched"}}
    dagger = repo / "configs/dagger.yaml"
    cfg = load_dagger_config(dagger, "tiny", {"out": str(tmp_path), "data": data})
    assert (base_collect(cfg).engine, base_collect(cfg).num_envs) == (SimEngine("batched"), cfg.data.num_envs)
    # the stages' keys name the sweeps' engine only where it is batched: runs keyed before it existed resume
    numpy_key = evaluate_key(cfg)
    assert not set(SIM_FIELDS) & set(numpy_key) and "device" in numpy_key
    batched = dataclasses.replace(cfg, evaluate=dataclasses.replace(cfg.evaluate, sim="batched"))
    assert evaluate_key(batched)["sim"] == "batched" and "sim" not in evaluate_key(batched, paths=True)
    with pytest.raises(VitflyError, match="data.workers is 2 with data.collect.sim batched"):
        load_dagger_config(dagger, "tiny", {"out": str(tmp_path), "data": {**data, "workers": 2}})
    with pytest.raises(VitflyError, match="data.collect.num_envs is set by the workflow; use data.num_envs"):
        load_dagger_config(dagger, "tiny", {"out": str(tmp_path), "data": {"collect": {"num_envs": 4}}})
