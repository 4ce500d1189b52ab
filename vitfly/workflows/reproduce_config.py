"""Configuration of ``vitfly reproduce``: typed sections, presets, and each model's training recipe.

``load_reproduce_config(path, preset)`` reads ``configs/reproduce.yaml``: the top level, with the
``presets.<preset>`` section deep-merged over it; unknown keys anywhere are one clear error. A model's
training settings are its recipe ``<train.recipes>/<model>.yaml`` (a ``vitfly fit`` config: the
``model.init_args``, ``data`` and ``trainer`` sections), then ``train.overrides``, then
``train.per_model[model]`` (mappings merge key by key), as the pipeline's ``TrainStage``.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from vitfly.errors import VitflyError
from vitfly.eval.config import dataclass_from_dict
from vitfly.eval.findings import draw_label
from vitfly.packaged import config_path, read_yaml
from vitfly.workflows.ablation import run_label
from vitfly.workflows.pipeline import EvalStage, TrainStage

PAPER_MODELS = ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm"]
STAGES = ("data", "train", "evaluate", "paths", "modular", "latency", "report")
SWEEPS = ("spheres", "trees", "window", "ablation", "paths", "modular")  # OUT/eval/<sweep>


@dataclass
class ReproduceTrain:
    """Which networks to train, and how: each model's recipe, then ``overrides``, then ``per_model[model]``."""

    source: str = "train"  # train: train every run here; pretrained: fly the shipped weights (pretrained:<model>)
    recipes: str = "configs/fit"  # <recipes>/<model>.yaml: a `vitfly fit` config (LightningCLI layout); a shipped
    # config's name where no such file exists
    models: list[str] = field(default_factory=lambda: [*PAPER_MODELS, "resnet18"])  # with the state input
    nostate_models: list[str] = field(default_factory=lambda: list(PAPER_MODELS))  # also trained without it
    overrides: dict = field(default_factory=dict)  # TrainStage fields for every model (dicts merge)
    per_model: dict = field(default_factory=dict)  # model -> TrainStage fields (dicts merge)
    closed_loop_check: dict | None = None  # ClosedLoopCheck arguments (None: no check during training)
    publish_weights: bool = False  # publish each finished state model as pretrained:<model>
    publish_models: list[str] = field(default_factory=lambda: list(PAPER_MODELS))
    weights_dir: str | None = None  # None: $VITFLY_WEIGHTS_DIR, else <repository>/weights (a clone; installed: none)
    draws: dict = field(default_factory=dict)  # run label (convnet, vit_lstm-nostate) -> seeds of more trainings of
    # that run, each trained into train/<model>-state-s<seed> and flown as <run>-s<seed> beside it; the paired
    # findings compare such a run by its draws' mean (vitfly.eval.paired)
    slot_order: list[str] = field(default_factory=list)  # GPU slots (scripts/gpu.py status): models in the order
    # they start there, runs with the state first, then without, then draws; [] = the order of `models`
    cpu_models: list[str] = field(default_factory=list)  # models whose runs (draws included) train on a CPU
    # (vitfly reproduce --models): left out of GPU slots


@dataclass
class ReproduceEvaluate:
    """The paper's simulation protocol (trial counts per speed)."""

    preset: str = "medium"
    seed: int = 1000  # scenes the collection (seed 0) never used
    speeds: list[float] = field(default_factory=lambda: [3.0, 4.0, 5.0, 6.0, 7.0])
    spheres_trials: int = 18  # paper: 90 trials per model over 3-7 m/s
    trees_trials: int = 10  # paper: 50 per model, 10 per speed
    window_speeds: list[float] = field(default_factory=lambda: [3.0])
    window_trials: int = 10
    ablation_speeds: list[float] = field(default_factory=lambda: [3.0, 5.0, 7.0])
    ablation_trials: int = 11  # the paper's rates are multiples of 1/11
    baselines: list[str] = field(default_factory=lambda: ["expert", "straight"])
    num_envs: int = 18
    workers: int = 1
    threads: int = 1
    backend: str = "eager"
    device: str = "cpu"
    timeout_s: float | None = None
    sim: str = "numpy"  # simulator engine of the sweeps: numpy or batched (vitfly.sim.engine)
    sim_device: str = "cpu"  # the batched engine's device
    sim_dtype: str = "float64"  # the batched engine's precision
    sim_compile: bool = False  # the batched engine's kernels through torch.compile


@dataclass
class ReproducePaths:
    """Repeated trials of one spheres scene (scene ``scene_trial`` of the evaluation's seed)."""

    speed: float = 5.0
    repeats: int = 10
    jitter_m: float = 0.1  # start offsets in y and z, uniform in [-jitter, jitter] m
    scene_trial: int = 0
    baselines: list[str] = field(default_factory=lambda: ["expert"])


@dataclass
class ReproduceModular:
    """The paper's comparison with modular baselines: the planners (``modular:NAME``, ``vitfly.planners``) beside
    learned models and baselines, every policy on the same spheres scenes (one sweep seed), at ``speeds`` m/s."""

    planners: list[str] = field(default_factory=lambda: ["fastplanner", "fastplanner_scaled", "convex",
                                                         "convex_scaled"])
    planner_config: str | None = None  # planners YAML (None: the shipped configs/planners.yaml)
    models: list[str] = field(default_factory=lambda: ["vit_lstm"])  # learned models flown beside (those in
    # train.models: the others are left out)
    baselines: list[str] = field(default_factory=lambda: ["expert"])
    speeds: list[float] = field(default_factory=lambda: [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0])
    planner_speeds: dict = field(default_factory=dict)  # planner -> its own (fewer) speeds, where the budget asks
    trials: int = 30  # per speed and policy
    seed: int | None = None  # sweep seed of the scenes; None: evaluate.seed
    num_envs: int | None = None  # lockstep scenes per policy call; None: evaluate.num_envs
    workers: int | None = None  # worker processes; None: evaluate.workers

    def speeds_of(self, planner: str) -> list[float]:
        return [float(v) for v in self.planner_speeds.get(planner, self.speeds)]


@dataclass
class ReproduceLatency:
    iters: int = 1000
    warmup: int = 100
    threads: int = 1
    backend: str = "eager"
    device: str = "auto"  # auto: CPU, plus the GPU when CUDA is present


@dataclass
class ReproduceReport:
    """What the report reads besides the run directory's own flights."""

    published: dict[str, str] = field(default_factory=dict)  # sweep (spheres, trees, ..., modular) -> a published
    # folder of this study (its outcomes.jsonl.gz, as `vitfly evaluate --merge` writes one into docs/), whose
    # trials join OUT/eval/<sweep>'s: a new checkout reports the committed flights without flying them again


@dataclass
class ReproduceConfig:
    preset: str = "custom"  # the name recorded in the outputs (set from --preset)
    out: str = "runs/reproduce"
    data: str = "data/reproduce_spheres.h5"
    collect_config: str | None = "configs/collect/spheres.yaml"
    collect: dict = field(default_factory=dict)  # overrides of the collect YAML
    threads: int = 0  # torch threads for training; 0 = all cores
    train: ReproduceTrain = field(default_factory=ReproduceTrain)
    evaluate: ReproduceEvaluate = field(default_factory=ReproduceEvaluate)
    paths: ReproducePaths = field(default_factory=ReproducePaths)
    modular: ReproduceModular = field(default_factory=ReproduceModular)
    latency: ReproduceLatency = field(default_factory=ReproduceLatency)
    report: ReproduceReport = field(default_factory=ReproduceReport)

    @property
    def out_dir(self) -> Path:
        return Path(self.out)

    def train_dir(self, model: str, use_state: bool, seed: int | None = None) -> Path:
        """``train/<model>-state`` (or ``-nostate``); another training draw's with ``-s<seed>``."""
        return self.out_dir / "train" / Run(model, use_state, seed).dir_name

    def eval_dir(self, name: str) -> Path:
        return self.out_dir / "eval" / name


def _deep_merge(base: dict, extra: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in (extra or {}).items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def load_reproduce_config(path: str | os.PathLike | None, preset: str | None = None,
                          overrides: dict | None = None) -> ReproduceConfig:
    """Defaults < YAML top level (a path or a shipped config's name) < its ``presets.<preset>`` (deep-merged) <
    overrides (top-level keys)."""
    path = config_path(path) if path else None
    data = dict(read_yaml(path)) if path else {}
    source = str(path) if path else "reproduce config"
    presets = data.pop("presets", None) or {}
    if not isinstance(presets, dict):
        raise VitflyError(f"{source}: field 'presets' must be a mapping of preset names to settings")
    if preset is not None:
        if preset not in presets:
            raise VitflyError(f"{source}: no preset {preset!r} under 'presets' (known: {', '.join(presets) or 'none'})")
        data = _deep_merge(data, presets[preset])
        data.setdefault("preset", preset)
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    sections = {}
    for name, cls in (("train", ReproduceTrain), ("evaluate", ReproduceEvaluate), ("paths", ReproducePaths),
                      ("modular", ReproduceModular), ("latency", ReproduceLatency), ("report", ReproduceReport)):
        sections[name] = dataclass_from_dict(cls, data.pop(name, None) or {}, f"{source}: {name}")
    cfg = dataclasses.replace(dataclass_from_dict(ReproduceConfig, data, source), **sections)
    check_config(cfg, source)
    return cfg


def check_config(cfg: ReproduceConfig, source: str) -> None:
    from vitfly.zoo import list_models

    t = cfg.train
    check_train_source(cfg, source)
    known = list_models()
    for key in ("models", "nostate_models", "publish_models"):
        for m in getattr(t, key):
            if m not in known:
                raise VitflyError(f"{source}: train.{key} has {m!r}; known: {', '.join(known)}")
    for m in t.per_model:
        if m not in known:
            raise VitflyError(f"{source}: train.per_model has {m!r}; known: {', '.join(known)}")
    for m in t.nostate_models:
        if m not in t.models:
            raise VitflyError(f"{source}: train.nostate_models has {m!r}, which train.models does not train "
                              "with the state (the ablation compares the two)")
    for b in [*cfg.evaluate.baselines, *cfg.paths.baselines]:
        if b not in ("expert", "straight"):
            raise VitflyError(f"{source}: baselines have {b!r}; expected expert and/or straight")
    for name in ("spheres_trials", "trees_trials", "window_trials", "ablation_trials"):
        if getattr(cfg.evaluate, name) < 1:
            raise VitflyError(f"{source}: evaluate.{name} must be >= 1")
    if cfg.paths.repeats < 1 or cfg.paths.jitter_m < 0:
        raise VitflyError(f"{source}: paths.repeats must be >= 1 and paths.jitter_m >= 0")
    check_modular(cfg, source)
    for sweep, folder in cfg.report.published.items():  # the report stage reads them (the GPU machine has no docs/)
        if sweep not in SWEEPS:
            raise VitflyError(f"{source}: report.published has {sweep!r}; expected sweeps: {', '.join(SWEEPS)}")
        if not isinstance(folder, str):
            raise VitflyError(f"{source}: report.published.{sweep} has {folder!r}; expected a folder's path")
    check_draws(cfg, source)
    check_slot_plan(cfg, source)
    for m in cfg.train.models:  # every recipe read (and checked) before anything runs
        train_stage(cfg, m, True, source)
    if t.closed_loop_check is not None:
        _closed_loop_check(t.closed_loop_check, source)
    from vitfly.workflows.pipeline import sweep_config

    sweep_config(eval_stage(cfg, ["spheres"], cfg.evaluate.speeds, 1), cfg.eval_dir("spheres"),
                 "expert").validate(f"{source}: evaluate")


def check_modular(cfg: ReproduceConfig, source: str) -> None:
    """The ``modular`` section: known planners (read from their YAML), learned models that the study has,
    baselines, speeds and trial counts."""
    from vitfly.planners import load_planner_options

    m = cfg.modular
    for name in m.planners:
        try:
            load_planner_options(name, m.planner_config)
        except VitflyError as err:
            raise VitflyError(f"{source}: modular.planners: {err}") from None
    from vitfly.zoo import list_models

    for model in m.models:  # one the study does not train is left out when the stage runs (it says so)
        if model not in list_models():
            raise VitflyError(f"{source}: modular.models has {model!r}; known: {', '.join(list_models())}")
    for b in m.baselines:
        if b not in ("expert", "straight"):
            raise VitflyError(f"{source}: modular.baselines has {b!r}; expected expert and/or straight")
    for name, speeds in m.planner_speeds.items():
        if name not in m.planners:
            raise VitflyError(f"{source}: modular.planner_speeds has {name!r}, which modular.planners does not fly")
        if not isinstance(speeds, list) or not speeds or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in speeds):
            raise VitflyError(f"{source}: modular.planner_speeds.{name} must be a list of speeds > 0 m/s, "
                              f"got {speeds!r}")
    if not m.speeds or any(v <= 0 for v in m.speeds):
        raise VitflyError(f"{source}: modular.speeds must be a list of speeds > 0 m/s, got {m.speeds!r}")
    if m.trials < 1 or any(v is not None and v < 1 for v in (m.num_envs, m.workers)):
        raise VitflyError(f"{source}: modular.trials, modular.num_envs and modular.workers must be >= 1")


def modular_stage(cfg: ReproduceConfig, speeds: list[float]) -> EvalStage:
    """The evaluation settings of the modular comparison: spheres, its own seed, trial count and speeds."""
    m = cfg.modular
    stage = eval_stage(cfg, ["spheres"], speeds, m.trials)
    return dataclasses.replace(stage, seed=cfg.evaluate.seed if m.seed is None else m.seed,
                               num_envs=stage.num_envs if m.num_envs is None else m.num_envs,
                               workers=stage.workers if m.workers is None else m.workers)


def _closed_loop_check(kwargs: dict, source: str):
    from vitfly.workflows.closed_loop_check import ClosedLoopCheck

    try:
        return ClosedLoopCheck(**kwargs)
    except TypeError as err:
        raise VitflyError(f"{source}: train.closed_loop_check: {err}") from None


RECIPE_SECTIONS = ("seed_everything", "model", "data", "trainer", "ckpt_path")
RECIPE_DATA_FIELDS = {"batch_size", "val_fraction"}  # TrainStage fields; data_path/split_seed: the study's
RECIPE_DATA_IGNORED = {"data_path", "split_seed", "split_file", "use_state", "test_path", "predict_path"}
RECIPE_TRAINER_IGNORED = {"default_root_dir", "logger", "enable_checkpointing"}


def _instantiate(spec: dict, where: str):
    """A ``class_path``/``init_args`` mapping (LightningCLI style) as an object."""
    if not isinstance(spec, dict) or "class_path" not in spec:
        raise VitflyError(f"{where}: expected a mapping with class_path (and init_args)")
    module, _, name = str(spec["class_path"]).rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name)
        return cls(**(spec.get("init_args") or {}))
    except (ImportError, AttributeError, TypeError, ValueError) as err:
        raise VitflyError(f"{where}: cannot build {spec['class_path']} ({err})") from None


def recipe_fields(path: str | Path, model: str) -> dict:
    """A ``vitfly fit`` YAML as TrainStage fields (model, use_state and paths left to the study)."""
    source = str(path)
    data = read_yaml(path)
    unknown = sorted(set(data) - set(RECIPE_SECTIONS))
    if unknown:
        raise VitflyError(f"{source}: unknown section {unknown[0]!r}; a recipe has {', '.join(RECIPE_SECTIONS)}")
    out: dict = {"policy_kwargs": {}, "data_kwargs": {}, "trainer_kwargs": {}}
    if isinstance(data.get("seed_everything"), int):
        out["seed"] = data["seed_everything"]
    model_section = data.get("model") or {}
    class_path = str(model_section.get("class_path", model))
    if class_path.rpartition(".")[2] != model:
        raise VitflyError(f"{source}: model.class_path is {class_path!r}, but the file is the recipe of {model!r}")
    out["policy_kwargs"] = {k: v for k, v in (model_section.get("init_args") or {}).items()
                            if k not in ("use_state", "model")}
    for k, v in (data.get("data") or {}).items():
        if k in RECIPE_DATA_FIELDS:
            out[k] = v
        elif k not in RECIPE_DATA_IGNORED:
            out["data_kwargs"][k] = v
    for k, v in (data.get("trainer") or {}).items():
        if k == "max_epochs":
            out["max_epochs"] = v
        elif k not in RECIPE_TRAINER_IGNORED:
            out["trainer_kwargs"][k] = v
    return out


def train_stage(cfg: ReproduceConfig, model: str, use_state: bool, source: str = "reproduce config", *,
                seed: int | None = None) -> TrainStage:
    """Recipe < ``train.overrides`` < ``train.per_model[model]``, as the pipeline's TrainStage; ``seed``: another
    training draw's (weights' initialisation, data order and train/validation split), else the recipe's. The
    recipe is ``<train.recipes>/<model>.yaml``; where no such file exists, the shipped config of that name
    (``configs/fit`` is ``fit``)."""
    recipe = config_path(Path(cfg.train.recipes) / f"{model}.yaml")
    fields = _deep_merge(recipe_fields(recipe, model), cfg.train.overrides)
    fields = _deep_merge(fields, cfg.train.per_model.get(model) or {})
    fields.update(model=model, use_state=use_state)
    if seed is not None:
        fields["seed"] = int(seed)
    return dataclass_from_dict(TrainStage, fields, f"{source}: train (recipe {recipe} + overrides) of {model}")


def train_callbacks(stage: TrainStage, cfg: ReproduceConfig, source: str) -> tuple[TrainStage, list]:
    """Callbacks out of ``trainer_kwargs`` (built from class_path), plus the closed-loop check if asked for, and
    a stopwatch (Lightning's ``Timer``) where no ``max_time`` brings one: ``cost.json`` reads it."""
    from lightning.pytorch.callbacks import Timer

    stage, specs = split_callbacks(stage)
    kwargs = stage.trainer_kwargs
    callbacks = [_instantiate(s, f"{source}: trainer.callbacks") for s in specs]
    if cfg.train.closed_loop_check is not None:
        callbacks.append(_closed_loop_check(cfg.train.closed_loop_check, source))
    if kwargs.get("max_time") is None and not any(isinstance(c, Timer) for c in callbacks):
        callbacks.append(Timer(duration=None, verbose=False))  # its state in last.ckpt counts killed sessions
    return stage, callbacks


def split_callbacks(stage: TrainStage) -> tuple[TrainStage, list]:
    """``stage`` without ``trainer_kwargs.callbacks`` (the settings a finished run is compared by), and those
    callbacks' specs (class_path + init_args), unbuilt: building them imports Lightning (seconds)."""
    kwargs = dict(stage.trainer_kwargs)
    specs = kwargs.pop("callbacks", None) or []
    return dataclasses.replace(stage, trainer_kwargs=kwargs), specs if isinstance(specs, list) else [specs]


TRAIN_SOURCES = ("train", "pretrained")


def check_train_source(cfg: ReproduceConfig, source: str) -> None:
    """``train.source`` is known, ``pretrained`` asks only for what is shipped (state models), and
    ``publish_weights`` has a directory to write (an installed vitfly's own weights are read-only)."""
    if cfg.train.source not in TRAIN_SOURCES:
        raise VitflyError(f"{source}: train.source: expected one of {', '.join(TRAIN_SOURCES)}, "
                          f"got {cfg.train.source!r}")
    if cfg.train.source == "pretrained" and cfg.train.weights_dir is not None:
        raise VitflyError(f"{source}: train.source pretrained flies pretrained:<model> from $VITFLY_WEIGHTS_DIR or "
                          "the shipped weights; set that instead of train.weights_dir")
    if cfg.train.publish_weights:
        from vitfly.zoo.pretrained import publish_dir

        try:
            publish_dir(cfg.train.weights_dir)
        except VitflyError as err:
            raise VitflyError(f"{source}: train.publish_weights: {err}") from None
    if cfg.train.source == "pretrained" and cfg.train.nostate_models:
        raise VitflyError(f"{source}: train.source pretrained flies the shipped weights, which are trained with "
                          "the state input only; set train.nostate_models: [] (the ablation needs training)")


class Run(NamedTuple):
    """One training of the study: a model, with the state input or without, and ``seed`` for another training
    draw of that run (None: the study's own run, with the recipe's seed)."""

    model: str
    use_state: bool
    seed: int | None = None

    @property
    def run(self) -> str:
        """The study's run this is (a draw of): ``convnet``, ``convnet-nostate``."""
        return run_label(self.model, self.use_state)

    @property
    def label(self) -> str:
        """The policy label in the sweeps: the run's, and ``-s<seed>`` for another draw."""
        return self.run if self.seed is None else draw_label(self.run, self.seed)

    @property
    def dir_name(self) -> str:
        """The folder under ``train/``: ``convnet-state``, ``convnet-nostate-s2``."""
        base = self.model + ("-state" if self.use_state else "-nostate")
        return base if self.seed is None else f"{base}-s{self.seed}"

    @classmethod
    def parse(cls, name: str) -> Run:
        """A folder name (``dir_name``) back as a Run; one line naming what is expected otherwise."""
        m = re.fullmatch(r"(?P<model>.+)-(?P<kind>state|nostate)(-s(?P<seed>\d+))?", name)
        if not m:
            raise VitflyError(f"{name!r}: expected MODEL-state or MODEL-nostate, with -s<seed> for another draw")
        return cls(m["model"], m["kind"] == "state", None if m["seed"] is None else int(m["seed"]))


def runs(cfg: ReproduceConfig, with_draws: bool = True) -> list[Run]:
    """The study's runs (with the state, then without), then the other draws of ``train.draws``."""
    own = [Run(m, True) for m in cfg.train.models] + [Run(m, False) for m in cfg.train.nostate_models]
    if not with_draws:
        return own
    by_label = {r.run: r for r in own}
    return own + [by_label[run]._replace(seed=int(seed)) for run, seeds in cfg.train.draws.items() for seed in seeds]


def draw_groups(cfg: ReproduceConfig) -> dict[str, list[str]]:
    """Run label -> the policy labels of its draws (its own first), for every run the study trains when any has
    other draws (a run trained once: its label alone, so that its comparisons borrow the others' spread,
    ``vitfly.eval.paired``); {} when none has."""
    groups: dict[str, list[str]] = {}
    for r in runs(cfg):
        groups.setdefault(r.run, [r.run])
        if r.seed is not None:
            groups[r.run].append(r.label)
    return groups if any(len(labels) > 1 for labels in groups.values()) else {}


def check_draws(cfg: ReproduceConfig, source: str) -> None:
    """``train.draws``: runs the study trains, each with distinct seeds other than the run's own."""
    own = {r.run: r for r in runs(cfg, with_draws=False)}
    if not isinstance(cfg.train.draws, dict):
        raise VitflyError(f"{source}: train.draws must map run labels (e.g. convnet, vit_lstm-nostate) to seeds")
    for run, seeds in cfg.train.draws.items():
        if run not in own:
            raise VitflyError(f"{source}: train.draws has {run!r}, which the study does not train; its runs are "
                              f"{', '.join(own)}")
        if cfg.train.source == "pretrained":
            raise VitflyError(f"{source}: train.draws needs training; train.source is pretrained")
        seeds_ok = isinstance(seeds, list) and seeds and len(set(seeds)) == len(seeds)
        if not seeds_ok or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in seeds):
            raise VitflyError(f"{source}: train.draws.{run} must be a list of distinct seeds >= 0, got {seeds!r}")
        own_seed = train_stage(cfg, own[run].model, own[run].use_state, source).seed
        if own_seed in seeds:
            raise VitflyError(f"{source}: train.draws.{run} has the run's own seed {own_seed}: that draw is the run "
                              "itself")


def check_slot_plan(cfg: ReproduceConfig, source: str) -> None:
    """``train.slot_order`` and ``train.cpu_models`` name models the study trains, each once."""
    trained = cfg.train.models  # nostate_models is a part of it
    for name in ("slot_order", "cpu_models"):
        models = getattr(cfg.train, name)
        if not isinstance(models, list) or len(set(map(str, models))) != len(models):
            raise VitflyError(f"{source}: train.{name} must be a list of distinct model names, got {models!r}")
        if unknown := [m for m in models if m not in trained]:
            raise VitflyError(f"{source}: train.{name} has {', '.join(map(repr, unknown))}, which the study does "
                              f"not train; its models are {', '.join(trained)}")


def done_checkpoint(train_dir: Path) -> Path | None:
    marker = train_dir / "done.json"
    if not marker.exists():
        return None
    ckpt = Path(json.loads(marker.read_text())["checkpoint"])
    return ckpt if ckpt.exists() else None


def train_frames(train_dir: Path, data: str) -> int | None:
    from vitfly.datamodules.schema import open_trajectories

    split = train_dir / "split.json"
    if not split.exists():
        return None
    with open_trajectories(data, check_values=False) as tf:
        lengths = tf.lengths
    return int(sum(int(lengths[i]) for i in json.loads(split.read_text())["train"]))


def eval_stage(cfg: ReproduceConfig, env: list[str], speeds: list[float], trials: int) -> EvalStage:
    e = cfg.evaluate
    return EvalStage(env=env, preset=e.preset, speeds=list(speeds), trials=trials, seed=e.seed,
                     num_envs=e.num_envs, workers=e.workers, threads=e.threads, backend=e.backend,
                     timeout_s=e.timeout_s, device=e.device, sim=e.sim, sim_device=e.sim_device, sim_dtype=e.sim_dtype,
                     sim_compile=e.sim_compile)


def paths_plan(cfg: ReproduceConfig):
    from vitfly.eval.repeats import RepeatPlan

    p, e = cfg.paths, cfg.evaluate
    return RepeatPlan(env="spheres", preset=e.preset, speed=p.speed, repeats=p.repeats, jitter_m=p.jitter_m,
                      seed=e.seed, scene_trial=p.scene_trial, timeout_s=e.timeout_s)
