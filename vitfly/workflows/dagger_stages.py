"""``vitfly dagger``'s stages: the plan, each stage's fingerprint, its manifest, and where its outputs go.

``plan_stages(cfg)`` lists every stage in order (``r<I>.collect``, ``r<I>.train``, ``r<I>.bc-collect``,
``r<I>.bc-train``, ``r<I>.evaluate``, ``paths``, ``report``), each keyed by what decides its result: its settings
and the fingerprints of the stages it builds on. ``manifests/<stage>.json`` records the key, whether the stage is
done and what it produced; ``check_existing`` refuses, before anything runs, to build on flights that a dataset
holds under other settings. Running the stages is ``vitfly.workflows.dagger``'s job.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.eval.fingerprint import digest
from vitfly.workflows.dagger_config import DaggerConfig, base_collect, evaluate_key
from vitfly.zoo.pretrained import is_pretrained_spec

DAGGER_DATA = "data/dagger.h5"
BC_DATA = "data/bc.h5"


@dataclass(frozen=True)
class Stage:
    """One step of the run: ``name`` (e.g. ``r1.collect``), ``kind``, round, and ``key``: what decides its result."""

    name: str
    kind: str  # collect | train | bc-collect | bc-train | evaluate | paths | report
    round: int | None
    key: dict

    @property
    def fingerprint(self) -> str:
        return digest(self.key)


def train_dir(cfg: DaggerConfig, round_index: int, baseline: bool = False) -> Path:
    name = "r0" if round_index == 0 else f"{'bc' if baseline else 'dagger'}-r{round_index}"
    return cfg.out_dir / "train" / name


def final_checkpoint(cfg: DaggerConfig, round_index: int, baseline: bool = False) -> Path:
    """The weights a round's training ended with (the next round starts from them, evaluation flies them): its
    ``last.ckpt``, which every training rewrites at the end of each epoch (``vitfly.training.checkpoints``)."""
    return train_dir(cfg, round_index, baseline) / "checkpoints" / "last.ckpt"


def _file_hash(path: str | None) -> str | None:
    """SHA-256 of a file's bytes, 16 hex digits (None for None; ``pretrained:NAME``: its safetensors file)."""
    if path is None:
        return None
    if is_pretrained_spec(path):
        from vitfly.zoo.pretrained import manifest_entry, pretrained_name

        return str(manifest_entry(pretrained_name(path))["sha256"])[:16]
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()[:16]


def train_settings(cfg: DaggerConfig, round_index: int) -> dict:
    """What a round's training is run with (round 0 from scratch, later rounds fine-tuning)."""
    t = cfg.train
    policy_kwargs = dict(t.policy_kwargs)
    if round_index > 0:
        policy_kwargs.update(t.finetune_policy_kwargs)
    return {"model": t.model, "use_state": t.use_state, "batch_size": t.batch_size, "val_fraction": t.val_fraction,
            "seed": t.seed, "epochs": t.epochs if round_index == 0 else t.finetune_epochs,
            "policy_kwargs": policy_kwargs, "data_kwargs": dict(t.data_kwargs),
            "trainer_kwargs": dict(t.trainer_kwargs)}


def plan_stages(cfg: DaggerConfig) -> list[Stage]:
    """Every stage in order, each keyed by its settings and the fingerprints of the stages it builds on."""
    collect_key = base_collect(cfg).content_key()
    collect_key.pop("seed")  # per round below
    init = _file_hash(cfg.train.init_checkpoint)
    stages: list[Stage] = []
    fp: dict[str, str] = {}

    def add(name: str, kind: str, r: int | None, key: dict) -> None:
        stage = Stage(name, kind, r, {"stage": kind, "round": r, **key})
        fp[name] = stage.fingerprint
        stages.append(stage)

    for r in cfg.rounds:
        beta = cfg.schedule.beta(r)
        add(f"r{r}.collect", "collect", r, {
            "collect": collect_key, "collect_seed": cfg.collect_seed(r), "trajectories": cfg.trajectories(r),
            "beta": beta, "mix_seed": [cfg.data.seed, r],
            "student": fp.get(f"r{r - 1}.train") if r else (init if beta < 1.0 else None),
            "previous": fp.get(f"r{r - 1}.collect")})
        add(f"r{r}.train", "train", r, {
            "data": fp[f"r{r}.collect"], "settings": train_settings(cfg, r),
            "init": fp.get(f"r{r - 1}.train") if r else init})
        if r and cfg.baseline:
            add(f"r{r}.bc-collect", "bc-collect", r, {
                "collect": collect_key, "collect_seed": cfg.collect_seed(r, baseline=True),
                "frames_of": fp[f"r{r}.collect"],
                "previous": fp.get(f"r{r - 1}.bc-collect", fp["r0.collect"])})
            add(f"r{r}.bc-train", "bc-train", r, {
                "data": fp[f"r{r}.bc-collect"], "settings": train_settings(cfg, r), "steps_of": fp[f"r{r}.train"],
                "init": fp.get(f"r{r - 1}.bc-train", fp["r0.train"])})
        students = [fp[f"r{r}.train"]] + ([fp[f"r{r}.bc-train"]] if r and cfg.baseline else [])
        add(f"r{r}.evaluate", "evaluate", r, {
            "evaluate": evaluate_key(cfg), "students": students})
    last = cfg.rounds[-1]
    finals = [fp[f"r{last}.train"]] + ([fp[f"r{last}.bc-train"]] if last and cfg.baseline else [])
    add("paths", "paths", None, {"paths": dataclasses.asdict(cfg.paths), "evaluate": evaluate_key(cfg, paths=True),
                                 "students": finals})
    add("report", "report", None, {})
    return stages


STAGE_NAMES_HELP = "r<I>.collect, r<I>.train, r<I>.bc-collect, r<I>.bc-train, r<I>.evaluate, paths, report"


# -------------------------------------------------------------------------------------------------
# manifests


def manifest_path(cfg: DaggerConfig, stage: Stage) -> Path:
    return cfg.out_dir / "manifests" / f"{stage.name}.json"


def read_stage_manifest(cfg: DaggerConfig, stage: Stage) -> dict | None:
    path = manifest_path(cfg, stage)
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except ValueError:
        raise VitflyError(f"{path}: not a readable stage manifest (JSON); delete it to rerun the stage") from None


def write_stage_manifest(cfg: DaggerConfig, stage: Stage, done: bool, result: dict | None = None) -> None:
    write_text(manifest_path(cfg, stage), json.dumps(
        {"stage": stage.name, "fingerprint": stage.fingerprint, "done": done, "key": stage.key,
         "result": result or {}}, indent=1, default=str) + "\n")


def _differences(old: dict, new: dict) -> list[str]:
    """Top-level keys whose values differ (what a one-line refusal names)."""
    return sorted(k for k in set(old) | set(new) if json.dumps(old.get(k), sort_keys=True, default=str)
                  != json.dumps(new.get(k), sort_keys=True, default=str))


def data_path(cfg: DaggerConfig, baseline: bool) -> Path:
    return cfg.out_dir / (BC_DATA if baseline else DAGGER_DATA)


def rounds_in(path: Path) -> np.ndarray:
    """The ``dagger_round`` of every committed trajectory of ``path`` (empty when it does not exist yet)."""
    from vitfly.datamodules.schema import open_trajectories

    if not path.exists():
        return np.zeros(0, dtype=np.int64)
    try:
        with open_trajectories(path, check_values=False) as tf:
            if "dagger_round" not in tf.table:
                raise VitflyError(f"{path}: has no /trajectories/dagger_round (not made by vitfly dagger)")
            return np.asarray(tf.table["dagger_round"], dtype=np.int64)
    except VitflyError as err:
        if "holds no trajectory" in str(err):
            return np.zeros(0, dtype=np.int64)
        raise


def check_existing(cfg: DaggerConfig, stages: list[Stage]) -> None:
    """Refuse, before anything runs, to build on flights made with other settings than ``stages`` give them."""
    rounds = {False: rounds_in(data_path(cfg, False)), True: rounds_in(data_path(cfg, True))}
    for stage in stages:
        if stage.kind not in ("collect", "bc-collect"):
            continue
        baseline = stage.kind == "bc-collect"
        present = int(np.sum(rounds[baseline] == stage.round))
        if baseline and stage.round == 1:
            present += int(np.sum(rounds[True] == 0))  # the copy of round 0 is part of the baseline's round 1
        if not present:
            continue
        manifest = read_stage_manifest(cfg, stage)
        where = data_path(cfg, baseline)
        if manifest is None:
            raise VitflyError(f"{where}: holds {present} trajectories of round {stage.round} but "
                              f"{manifest_path(cfg, stage)} is missing, so their settings are unknown; "
                              "use a new --out")
        if manifest.get("fingerprint") != stage.fingerprint:
            diff = ", ".join(_differences(manifest.get("key", {}), stage.key))
            raise VitflyError(
                f"{where}: its round {stage.round} flights ({stage.name}) were made with other settings "
                f"(differs: {diff}); rerun with the settings that made them, or use a new --out")
