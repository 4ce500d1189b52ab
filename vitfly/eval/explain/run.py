"""``explain_trial``: maps of several models on the same frames, their numbers, and the figures.

Writes into ``out_dir``:

- ``explain.json``: the trial, the method of every map kind, and per model and map kind the temporal
  consistency and edge numbers (``vitfly.eval.explain.map_metrics``); ``explain.csv``: the same numbers,
  one row per (model, map);
- ``strip_<model>.png``: the chosen ticks, one row per map kind of that model;
- ``<model>.gif``: the whole trial, the model's main maps side by side;
- ``side_by_side.png`` / ``side_by_side.gif``: every model's command Grad-CAM (and the attention of those
  that have it) on the same frames.

Everything is computed before the first file is written; each file is written atomically.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.eval.explain.figures import MapRow, strip_figure, write_gif
from vitfly.eval.explain.frames import TrialFrames
from vitfly.eval.explain.map_metrics import map_metrics
from vitfly.eval.explain.maps import METHODS, SequenceMaps, explain_sequence
from vitfly.eval.explain.policies import ExplainedPolicy, file_stem
from vitfly.eval.learned_policy import deploy_command
from vitfly.sim.visualize import body_command, save_figure

CSV_COLUMNS = ("model", "map", "random_weights", "ticks", "consistency", "consistency_pairs", "edge_mass_share",
               "edge_area_share", "edge_lift", "edge_ticks")
GIF_MAPS = ("command", "attention")  # per-model GIF panels, where the model has them


@dataclass
class ModelExplanation:
    policy: ExplainedPolicy
    maps: SequenceMaps
    metrics: dict[str, dict]  # map kind -> numbers
    command_body: np.ndarray  # (T, 3) the model's own command in the body frame, m/s


@dataclass
class ExplainResult:
    frames: TrialFrames
    models: list[ModelExplanation]
    ticks: list[int]
    files: dict[str, Path] = field(default_factory=dict)

    def rows(self) -> list[dict]:
        """One dict per (model, map kind) with the CSV columns."""
        out = []
        for m in self.models:
            for kind, numbers in m.metrics.items():
                out.append({"model": m.policy.label, "map": kind, "random_weights": m.policy.random_weights,
                            "ticks": len(self.frames), **numbers})
        return out


def choose_ticks(n_ticks: int, count: int, ticks: Sequence[int] | None = None) -> list[int]:
    """Explicit ``ticks`` (checked), else ``count`` ticks evenly spread over the trial."""
    if ticks:
        bad = [t for t in ticks if not 0 <= t < n_ticks]
        if bad:
            raise VitflyError(f"--ticks {bad[0]}: the trial has ticks 0..{n_ticks - 1}")
        return list(ticks)
    if count < 1:
        raise VitflyError(f"--frames must be >= 1, got {count}")
    return sorted(set(np.linspace(0, n_ticks - 1, min(count, n_ticks)).round().astype(int).tolist()))


def explain_models(
    policies: Sequence[ExplainedPolicy],
    frames: TrialFrames,
    device: str = "cpu",
    progress: Callable[[str], None] | None = None,
) -> list[ModelExplanation]:
    """Maps and numbers of every policy on the trial's frames."""
    out = []
    for p in policies:
        if progress:
            progress(f"{p.label}: maps over {len(frames)} ticks")
        seq = explain_sequence(p.net, frames.depth, frames.desired_speed, frames.quat, device)
        metrics = {kind: map_metrics(maps, frames.edges) for kind, maps in seq.maps.items()}
        command = deploy_command(seq.output, frames.desired_speed)
        out.append(ModelExplanation(p, seq, metrics, body_command(command, frames.quat)))
    return out


def _json_value(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _json_value(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_value(x) for x in v]
    if isinstance(v, np.generic):
        return _json_value(v.item())
    return v


def _csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()})
    return buf.getvalue()


def _method_of(kind: str) -> str:
    return METHODS["attention_stage"] if kind.startswith("attention_stage") else METHODS[kind]


def explain_trial(
    policies: Sequence[ExplainedPolicy],
    frames: TrialFrames,
    out_dir: str | Path,
    ticks: Sequence[int] | None = None,
    n_frames: int = 8,
    gif: bool = True,
    gif_stride: int = 1,
    device: str = "cpu",
    progress: Callable[[str], None] | None = None,
) -> ExplainResult:
    """Explain every policy on ``frames`` and write the files listed in the module docstring."""
    chosen = choose_ticks(len(frames), n_frames, ticks)
    models = explain_models(policies, frames, device, progress)
    result = ExplainResult(frames, models, chosen)
    out = Path(out_dir)
    f = frames
    pilot_body = None if f.command is None else body_command(f.command, f.quat)
    pilot = f.info.get("pilot", "recorded")
    reference = MapRow(f"depth, edges ({f.edge_source})\narrow: {pilot}", None, pilot_body)
    stems: set[str] = set()
    if progress:
        progress("writing figures")
    side_rows: list[MapRow] = []
    side_panels: list[MapRow] = [MapRow("edges", None, pilot_body)]
    for m in models:
        stem = file_stem(m.policy.label)
        while stem in stems:
            stem += "_"
        stems.add(stem)
        rows = [MapRow(f"{m.policy.label}\n{kind}", maps, m.command_body) for kind, maps in m.maps.maps.items()]
        fig = strip_figure(f.depth, rows, chosen, f.time, f.desired_speed, f.edges, reference,
                           title=f"{m.policy.label} ({m.policy.arch}) — {f.title}")
        result.files[f"strip_{stem}"] = save_figure(fig, out / f"strip_{stem}.png")
        panels = [MapRow(f"{m.policy.label} {kind}", m.maps.maps[kind], m.command_body)
                  for kind in GIF_MAPS if kind in m.maps.maps]
        if gif:
            result.files[f"gif_{stem}"] = write_gif(out / f"{stem}.gif", f.depth, panels, f.time, f.desired_speed,
                                                    f.edges, gif_stride, scale=4)
        side_rows += [MapRow(f"{m.policy.label}\n{kind}", m.maps.maps[kind], m.command_body)
                      for kind in GIF_MAPS if kind in m.maps.maps]
        side_panels += [MapRow(f"{m.policy.label}", m.maps.maps["command"], m.command_body)] \
            if "command" in m.maps.maps else panels[:1]  # fmt: skip
    fig = strip_figure(f.depth, side_rows, chosen, f.time, f.desired_speed, f.edges, reference, title=f.title)
    result.files["side_by_side"] = save_figure(fig, out / "side_by_side.png")
    if gif and len(models) > 1:
        result.files["side_by_side_gif"] = write_gif(out / "side_by_side.gif", f.depth, side_panels, f.time,
                                                     f.desired_speed, f.edges, gif_stride, scale=3)
    summary = {
        "trial": {"title": f.title, "ticks": len(f), "edge_source": f.edge_source, **f.info},
        "strip_ticks": chosen,
        "methods": {kind: _method_of(kind) for m in models for kind in m.maps.maps},
        "models": [
            {"label": m.policy.label, "spec": m.policy.spec, "arch": m.policy.arch,
             "random_weights": m.policy.random_weights, "gradcam_layers": list(m.maps.layers),
             "metrics": m.metrics}
            for m in models
        ],
    }  # fmt: skip
    write_text(out / "explain.json", json.dumps(_json_value(summary), indent=1))
    write_text(out / "explain.csv", _csv_text(result.rows()))
    result.files["json"], result.files["csv"] = out / "explain.json", out / "explain.csv"
    return result
