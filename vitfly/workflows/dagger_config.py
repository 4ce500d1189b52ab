"""Configuration of ``vitfly dagger``: typed sections, presets, the mixing schedule and the seed ranges.

``load_dagger_config(path, preset, overrides)`` reads ``configs/dagger.yaml``: the top level, with the
``presets.<preset>`` section deep-merged over it, then the command line's overrides; unknown keys anywhere
are one clear error.

Mixing schedule: round i flies with beta_i = ``schedule.beta0 * schedule.decay ** i``, the probability that
the expert's command (rather than the student's) is flown at a tick. Round 0 with beta_0 = 1 is the
expert's own flights: plain behaviour-cloning data.

Seeds: the scene seeds and speeds of a round's flights derive from a collection seed, as ``vitfly collect
--seed`` does (``vitfly.sim.collect.trajectory_spec``). DAgger round i flies collection seed
``data.seed + i``; the behaviour-cloning baseline's extra expert flights for round i fly
``data.seed + BC_SEED_OFFSET + i``. Every such seed lies in ``TRAIN_SEEDS`` = [0, 1000), and evaluation
sweeps use seeds from ``EVAL_SEED_MIN`` = 1000 up (the evaluation's own derivation from ``(seed, env,
trial)``). Both ranges are checked here, and every flown training scene is checked against the evaluated
scenes before it is flown.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path

from vitfly.errors import VitflyError
from vitfly.eval.config import dataclass_from_dict
from vitfly.packaged import config_path, read_yaml

TRAIN_SEEDS = range(0, 1000)  # collection seeds of every DAgger and baseline flight
EVAL_SEED_MIN = 1000  # evaluation sweep seeds (vitfly evaluate / reproduce / pipeline use 1000)
BC_SEED_OFFSET = 500  # the baseline's extra expert flights for round i: collection seed data.seed + 500 + i


@dataclass
class DaggerData:
    """The flights: what every round flies and how many."""

    collect_config: str | None = "configs/collect/spheres.yaml"  # base collect YAML (env, preset, speeds, sensor)
    # its overrides (not trajectories, seed, workers or num_envs: set here); sim: batched flies every round on
    # the batched engine (sim_device, sim_dtype, sim_compile), num_envs flights at a time
    collect: dict = field(default_factory=dict)
    seed: int = 0  # round i flies collection seed seed + i; the baseline's extras seed + 500 + i
    expert_trajectories: int = 60  # round 0
    trajectories_per_round: int = 30  # rounds >= 1
    num_envs: int = 10  # flights stepped in lockstep (one batched network call per tick); every flight on sim batched
    workers: int = 1  # processes for the expert-only flights (round 0 at beta 1, the baseline's extras); numpy engine


@dataclass
class DaggerSchedule:
    """beta_i = beta0 * decay ** i: probability that the expert's command is flown at a tick of round i."""

    rounds: int = 3  # rounds after round 0
    beta0: float = 1.0
    decay: float = 0.5

    def beta(self, round_index: int) -> float:
        return float(self.beta0 * self.decay**round_index)


@dataclass
class DaggerTrain:
    """Round 0 trains from scratch (or from ``init_checkpoint``); round i >= 1 fine-tunes round i-1's final weights."""

    model: str = "convnet"
    use_state: bool = True
    epochs: int = 20  # round 0
    finetune_epochs: int = 6  # each round >= 1 (the baseline gets as many optimiser steps)
    batch_size: int = 8
    val_fraction: float = 0.2  # round 0's validation trajectories; every later round validates on them
    seed: int = 0
    policy_kwargs: dict = field(default_factory=dict)  # PolicyModule: lr, warmup_epochs, tbptt_steps, ...
    finetune_policy_kwargs: dict = field(default_factory=dict)  # merged over policy_kwargs for rounds >= 1
    data_kwargs: dict = field(default_factory=dict)  # TrajectoryDataModule
    trainer_kwargs: dict = field(default_factory=dict)  # lightning.Trainer
    init_checkpoint: str | None = None  # a behaviour-cloned checkpoint (or pretrained:NAME) to start round 0 from


@dataclass
class DaggerEvaluate:
    """Every round's students on held-out scenes (``vitfly.eval.sweep``; see SweepConfig for the fields)."""

    env: list[str] = field(default_factory=lambda: ["spheres"])
    preset: str = "medium"
    speeds: list[float] = field(default_factory=lambda: [3.0, 5.0, 7.0])
    trials: int = 30  # per (env, speed)
    seed: int = 1000  # >= EVAL_SEED_MIN: scenes no round flies
    num_envs: int = 30
    workers: int = 1
    threads: int = 1
    backend: str = "eager"
    timeout_s: float | None = None
    device: str = "cpu"  # learned policies' network, also for the students' training flights
    baselines: list[str] = field(default_factory=lambda: ["expert"])
    sim: str = "numpy"  # simulator engine of the sweeps: numpy or batched (vitfly.sim.engine); paths fly numpy
    sim_device: str = "cpu"  # the batched engine's device (with device, the same card: observations stay on it)
    sim_dtype: str = "float64"  # the batched engine's precision
    sim_compile: bool = False  # the batched engine's kernels through torch.compile


@dataclass
class DaggerPaths:
    """Repeats of one evaluation scene by the last round's students (and the expert)."""

    speed: float = 7.0
    repeats: int = 5
    jitter_m: float = 0.1
    scene_trial: int = 0


@dataclass
class DaggerReport:
    """The target the report checks: at ``target_speed``, the last round's DAgger student beats the baseline
    by at least ``target_margin_points`` percentage points of success, and the expert."""

    target_speed: float = 7.0
    target_margin_points: float = 15.0


@dataclass
class DaggerConfig:
    preset: str = "custom"
    out: str = "runs/dagger"
    threads: int = 0  # torch threads for training and the students' flights; 0 = all cores
    baseline: bool = True  # behaviour cloning at an equal number of expert-labelled frames
    data: DaggerData = field(default_factory=DaggerData)
    schedule: DaggerSchedule = field(default_factory=DaggerSchedule)
    train: DaggerTrain = field(default_factory=DaggerTrain)
    evaluate: DaggerEvaluate = field(default_factory=DaggerEvaluate)
    paths: DaggerPaths = field(default_factory=DaggerPaths)
    report: DaggerReport = field(default_factory=DaggerReport)

    @property
    def out_dir(self) -> Path:
        return Path(self.out)

    @property
    def rounds(self) -> list[int]:
        return list(range(self.schedule.rounds + 1))

    def collect_seed(self, round_index: int, baseline: bool = False) -> int:
        return self.data.seed + (BC_SEED_OFFSET if baseline else 0) + round_index

    def trajectories(self, round_index: int) -> int:
        return self.data.expert_trajectories if round_index == 0 else self.data.trajectories_per_round


SECTIONS = (("data", DaggerData), ("schedule", DaggerSchedule), ("train", DaggerTrain),
            ("evaluate", DaggerEvaluate), ("paths", DaggerPaths), ("report", DaggerReport))
RESERVED_COLLECT_KEYS = {"trajectories": "data.expert_trajectories / data.trajectories_per_round",
                         "seed": "data.seed", "workers": "data.workers", "num_envs": "data.num_envs"}
SIM_FIELDS = ("sim", "sim_device", "sim_dtype", "sim_compile")


def deep_merge(base: dict, extra: dict) -> dict:
    """``extra`` over ``base``; mappings merge key by key, anything else is replaced."""
    out = copy.deepcopy(base)
    for k, v in (extra or {}).items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def load_dagger_config(path: str | os.PathLike | None, preset: str | None = None,
                       overrides: dict | None = None) -> DaggerConfig:
    """Defaults < YAML top level < ``presets.<preset>`` (deep-merged) < ``overrides`` (nested mappings merge;
    None values are ignored). ``path``: a YAML file or a shipped config's name."""
    path = config_path(path) if path else None
    data = dict(read_yaml(path)) if path else {}
    source = str(path) if path else "dagger config"
    presets = data.pop("presets", None) or {}
    if not isinstance(presets, dict):
        raise VitflyError(f"{source}: field 'presets' must be a mapping of preset names to settings")
    if preset is not None:
        if preset not in presets:
            raise VitflyError(f"{source}: no preset {preset!r} under 'presets' (known: {', '.join(presets) or 'none'})")
        data = deep_merge(data, presets[preset])
        data.setdefault("preset", preset)
    data = deep_merge(data, _drop_none(overrides or {}))
    sections = {}
    for name, cls in SECTIONS:
        sections[name] = dataclass_from_dict(cls, data.pop(name, None) or {}, f"{source}: {name}")
    cfg = dataclasses.replace(dataclass_from_dict(DaggerConfig, data, source), **sections)
    check_config(cfg, source)
    return cfg


def _drop_none(d: dict) -> dict:
    return {k: (_drop_none(v) if isinstance(v, dict) else v) for k, v in d.items() if v is not None}


def check_config(cfg: DaggerConfig, source: str) -> None:
    """Every setting checked before anything runs; one line naming the first bad field."""
    from vitfly.zoo import list_models

    d, s, t, e = cfg.data, cfg.schedule, cfg.train, cfg.evaluate
    if s.rounds < 0:
        raise VitflyError(f"{source}: schedule.rounds must be >= 0, got {s.rounds}")
    for name in ("beta0", "decay"):
        value = getattr(s, name)
        if not 0.0 <= value <= 1.0:
            raise VitflyError(f"{source}: schedule.{name} must be in [0, 1], got {value}")
    if s.beta0 < 1.0 and t.init_checkpoint is None:
        raise VitflyError(f"{source}: schedule.beta0 is {s.beta0}, so round 0 flies a student some of the time; "
                          "set train.init_checkpoint to that student, or beta0: 1.0 (round 0 = the expert's flights)")
    if d.expert_trajectories < 2:
        raise VitflyError(f"{source}: data.expert_trajectories must be >= 2 (training and validation), "
                          f"got {d.expert_trajectories}")
    for name in ("trajectories_per_round", "num_envs", "workers"):
        if getattr(d, name) < 1:
            raise VitflyError(f"{source}: data.{name} must be >= 1, got {getattr(d, name)}")
    last = cfg.collect_seed(s.rounds, baseline=True)
    if d.seed < TRAIN_SEEDS.start or last >= TRAIN_SEEDS.stop:
        raise VitflyError(
            f"{source}: data.seed {d.seed} with {s.rounds} rounds uses collection seeds {d.seed}..{last}; training "
            f"flights must stay in [{TRAIN_SEEDS.start}, {TRAIN_SEEDS.stop}) (evaluation uses {EVAL_SEED_MIN} and up)")
    if e.seed < EVAL_SEED_MIN:
        raise VitflyError(f"{source}: evaluate.seed must be >= {EVAL_SEED_MIN} (seeds below are training flights'), "
                          f"got {e.seed}")
    for key in d.collect:
        if key in RESERVED_COLLECT_KEYS:
            raise VitflyError(f"{source}: data.collect.{key} is set by the workflow; use {RESERVED_COLLECT_KEYS[key]}")
    if d.workers > 1 and d.collect.get("sim") == "batched":
        raise VitflyError(f"{source}: data.workers is {d.workers} with data.collect.sim batched, which flies "
                          "data.num_envs flights at a time in one process; set data.workers 1")
    base_collect(cfg, source)  # the collect YAML and its overrides are valid
    if t.model not in list_models():
        raise VitflyError(f"{source}: train.model {t.model!r} unknown; known: {', '.join(list_models())}")
    if t.epochs < 1 or t.finetune_epochs < 1:
        raise VitflyError(f"{source}: train.epochs and train.finetune_epochs must be >= 1")
    if not 0.0 < t.val_fraction < 1.0:
        raise VitflyError(f"{source}: train.val_fraction must be in (0, 1): later rounds validate on round 0's "
                          f"held-out flights, got {t.val_fraction}")
    reserved = {"max_epochs", "max_steps"} & set(t.trainer_kwargs)
    if reserved:
        raise VitflyError(f"{source}: train.trainer_kwargs.{sorted(reserved)[0]} is set by the workflow; use "
                          "train.epochs / train.finetune_epochs")
    if "split_file" in t.data_kwargs:
        raise VitflyError(f"{source}: train.data_kwargs.split_file is set by the workflow (round 0's split)")
    if t.init_checkpoint is not None and t.init_checkpoint.startswith("pretrained:"):
        from vitfly.zoo.pretrained import weights_identity

        held = weights_identity(t.init_checkpoint)
        if (held["model"], held["use_state"]) != (t.model, t.use_state):
            raise VitflyError(f"{source}: train.init_checkpoint {t.init_checkpoint} holds {held['model']} "
                              f"(use_state={held['use_state']}), not train.model {t.model} "
                              f"(use_state={t.use_state})")
    elif t.init_checkpoint is not None and not Path(t.init_checkpoint).is_file():
        raise VitflyError(f"{source}: train.init_checkpoint {t.init_checkpoint}: no such checkpoint file")
    for b in e.baselines:
        if b not in ("expert", "straight"):
            raise VitflyError(f"{source}: evaluate.baselines has {b!r}; expected expert and/or straight")
    if cfg.paths.repeats < 0 or cfg.paths.jitter_m < 0:
        raise VitflyError(f"{source}: paths.repeats and paths.jitter_m must be >= 0 (repeats 0: no paths)")
    if cfg.report.target_speed not in e.speeds:
        raise VitflyError(f"{source}: report.target_speed {cfg.report.target_speed} is not among evaluate.speeds "
                          f"{e.speeds}")
    from vitfly.workflows.pipeline import sweep_config

    sweep_config(eval_stage(cfg), cfg.out_dir / "eval", "expert").validate(f"{source}: evaluate")


def base_collect(cfg: DaggerConfig, source: str = "dagger config"):
    """The CollectConfig every round flies (seed and count set per round)."""
    from vitfly.sim.collect import load_collect_config

    overrides = {**cfg.data.collect, "trajectories": cfg.data.expert_trajectories, "seed": cfg.data.seed,
                 "workers": cfg.data.workers, "num_envs": cfg.data.num_envs}
    try:
        return load_collect_config(cfg.data.collect_config, overrides)
    except VitflyError as err:
        raise VitflyError(f"{source}: data: {err}") from None


def eval_stage(cfg: DaggerConfig):
    from vitfly.workflows.pipeline import EvalStage

    e = cfg.evaluate
    # the students fly their evaluation with the physics back end their training flights used
    return EvalStage(env=list(e.env), preset=e.preset, speeds=list(e.speeds), trials=e.trials, seed=e.seed,
                     num_envs=e.num_envs, workers=e.workers, threads=e.threads, backend=e.backend,
                     timeout_s=e.timeout_s, device=e.device, physics=base_collect(cfg).physics,
                     **{name: getattr(e, name) for name in SIM_FIELDS})


def evaluate_key(cfg: DaggerConfig, paths: bool = False) -> dict:
    """The evaluation settings that decide its trials (``paths``: of the repeats, which fly the numpy engine):
    the engine's fields only where the sweeps fly the batched one, so runs made before it existed resume."""
    key = dataclasses.asdict(cfg.evaluate)
    if paths or cfg.evaluate.sim == "numpy":
        for name in SIM_FIELDS:
            key.pop(name)
    return key


def student_label(round_index: int, baseline: bool) -> str:
    """Evaluation label of a round's student; round 0's is shared by both methods (``bc-r0``)."""
    return f"bc-r{round_index}" if baseline or round_index == 0 else f"dagger-r{round_index}"


def paths_plan(cfg: DaggerConfig):
    from vitfly.eval.repeats import RepeatPlan

    p, e = cfg.paths, cfg.evaluate
    return RepeatPlan(env=e.env[0], preset=e.preset, speed=p.speed, repeats=max(p.repeats, 1), jitter_m=p.jitter_m,
                      seed=e.seed, scene_trial=p.scene_trial, timeout_s=e.timeout_s)
