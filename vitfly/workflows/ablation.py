"""``vitfly ablate --no-state``: each architecture trained with and without the state input, flown in
spheres and trees at 3, 5 and 7 m/s, success rates beside the paper's (``tables/table-no-state-info``).

Layout of ``OUT``: ``train/<model>-state`` and ``train/<model>-nostate`` (checkpoints, resumable),
``eval/`` (one trials.jsonl for all policies, labels ``<model>`` and ``<model>-nostate``, reports
and plots), ``ablation.csv`` and ``ablation.md`` (the table; success as the paper defines it, a
trial without a collision). Every stage resumes; a retrained model is flown again (its trials are
keyed by its weights, see ``vitfly.workflows.pipeline.stage_evaluate``).
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.eval.config import dataclass_from_dict
from vitfly.eval.paper_tables import ABLATION_ENVS, ABLATION_SPEEDS, MODEL_LABELS, paper_success
from vitfly.packaged import config_path, read_yaml
from vitfly.workflows.pipeline import EvalStage, TrainStage, stage_collect, stage_evaluate, stage_train


@dataclass
class AblationConfig:
    out: str = "runs/ablate"
    data: str = "data/spheres.h5"
    collect_config: str | None = "configs/collect/spheres.yaml"
    collect: dict = field(default_factory=dict)
    models: list[str] = field(default_factory=lambda: ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm"])
    train: TrainStage = field(default_factory=TrainStage)  # model and use_state are set per run
    evaluate: EvalStage = field(default_factory=lambda: EvalStage(env=list(ABLATION_ENVS),
                                                                  speeds=list(ABLATION_SPEEDS), trials=11))
    threads: int = 0  # torch threads for training; 0 = all cores


def _deep_merge(base: dict, extra: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in extra.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_ablation_config(path: str | os.PathLike | None, preset: str | None = None,
                         overrides: dict | None = None) -> AblationConfig:
    """Defaults < YAML (a path or a shipped config's name) < the YAML's ``presets.<preset>`` section (deep-merged)
    < overrides (top level)."""
    path = config_path(path) if path else None
    data = dict(read_yaml(path)) if path else {}
    source = str(path) if path else "ablate config"
    presets = data.pop("presets", None) or {}
    if preset is not None:
        if preset not in presets:
            known = ", ".join(presets) or "none"
            raise VitflyError(f"{source}: no preset {preset!r} under 'presets' (known: {known})")
        data = _deep_merge(data, presets[preset])
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    train = dataclass_from_dict(TrainStage, data.pop("train", None) or {}, f"{source}: train")
    evaluate = dataclass_from_dict(EvalStage, data.pop("evaluate", None) or {}, f"{source}: evaluate")
    cfg = dataclasses.replace(dataclass_from_dict(AblationConfig, data, source), train=train, evaluate=evaluate)
    from vitfly.zoo import list_models

    for m in cfg.models:
        if m not in list_models():
            raise VitflyError(f"{source}: field 'models' has {m!r}; known: {', '.join(list_models())}")
    return cfg


def run_label(model: str, use_state: bool) -> str:
    return model if use_state else f"{model}-nostate"


def ablation_rows(summary_rows: list[dict], cfg: AblationConfig) -> list[dict]:
    """One row per (env, model, speed): our success rate with and without state, and the paper's.

    Success is the paper's definition (a trial without a collision), as in the paper's table.
    """
    by_key = {(r["policy"], r["env"], float(r["speed"])): r for r in summary_rows}
    rows = []
    for env in cfg.evaluate.env:
        for model in cfg.models:
            for speed in cfg.evaluate.speeds:
                row = {"env": env, "model": model, "speed": float(speed)}
                for use_state, tag in ((False, "nostate"), (True, "state")):
                    r = by_key.get((run_label(model, use_state), env, float(speed)))
                    row[f"success_{tag}"] = None if r is None else r["success_paper_rate"]
                    row[f"trials_{tag}"] = 0 if r is None else r["trials"]
                    row[f"paper_{tag}"] = paper_success(env, model, speed, use_state)
                rows.append(row)
    return rows


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.0f}"


def ablation_markdown(rows: list[dict], speeds: list[float]) -> str:
    """The paper's table layout: success % without (✗) / with (✓) the state, ours and (paper)."""
    head = ["env", "model", *(f"{s:g} m/s {mark}" for s in speeds for mark in ("✗", "✓"))]
    lines = ["| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (2 * len(speeds))]
    cells: dict[tuple[str, str], list[str]] = {}
    for r in rows:
        c = cells.setdefault((r["env"], r["model"]), [])
        for tag in ("nostate", "state"):
            paper = r[f"paper_{tag}"]
            c.append(_pct(r[f"success_{tag}"]) + ("" if paper is None else f" ({paper})"))
    for (env, model), c in cells.items():
        lines.append(f"| {env} | {MODEL_LABELS.get(model, model)} | " + " | ".join(c) + " |")
    return "\n".join([
        "Success rate (%) without (✗) and with (✓) the state input (desired speed + attitude); "
        "ours, the paper's in parentheses (paper: tables/table-no-state-info). Success as the paper "
        "defines it: a trial without a collision.", "", *lines, ""])


def ablation_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    cols = ["env", "model", "speed", "success_nostate", "success_state", "trials_nostate", "trials_state",
            "paper_nostate", "paper_state"]
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r[k] is None else r[k]) for k in cols})
    return buf.getvalue()


def print_ablation(rows: list[dict], speeds: list[float]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="no-state ablation: success % (paper: no collision) without ✗ / with ✓ state -- ours (paper)")
    table.add_column("env")
    table.add_column("model")
    for s in speeds:
        for mark in ("✗", "✓"):
            table.add_column(f"{s:g} m/s {mark}", justify="right")
    grouped: dict[tuple[str, str], list[str]] = {}
    for r in rows:
        for tag in ("nostate", "state"):
            paper = r[f"paper_{tag}"]
            grouped.setdefault((r["env"], r["model"]), []).append(
                _pct(r[f"success_{tag}"]) + ("" if paper is None else f" ({paper})"))
    for (env, model), c in grouped.items():
        table.add_row(env, MODEL_LABELS.get(model, model), *c)
    Console(width=max(Console().width, 120)).print(table)


def run_ablation(cfg: AblationConfig, progress: bool = True) -> list[dict]:
    """Collect (if needed), train every (model, state) pair, evaluate them all, write and print the table."""
    from vitfly.eval.evaluation import write_outputs

    out = Path(cfg.out)
    stage_collect(cfg.collect_config, cfg.collect, cfg.data, progress)
    policies = []
    for model in cfg.models:
        for use_state in (True, False):
            train = dataclasses.replace(cfg.train, model=model, use_state=use_state)
            label = run_label(model, use_state)
            ckpt = stage_train(train, cfg.data, out / "train" / (model + ("-state" if use_state else "-nostate")),
                               cfg.threads, progress)
            policies.append((str(ckpt), label))
    stage_evaluate(cfg.evaluate, out / "eval", policies, progress, gif_for=None)
    summary, _ = write_outputs(out / "eval", with_plots=True, title="no-state ablation")
    rows = ablation_rows(summary, cfg)
    write_text(out / "ablation.csv", ablation_csv(rows))
    write_text(out / "ablation.md", ablation_markdown(rows, cfg.evaluate.speeds))
    print_ablation(rows, cfg.evaluate.speeds)
    print(f"wrote {out / 'ablation.md'}, {out / 'ablation.csv'}, {out / 'eval'}/summary.csv and plots")
    return rows
