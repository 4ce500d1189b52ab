"""``vitfly evaluate`` as a library call: sweep, then reports, plots, a depth GIF and (optionally) wandb.

Reports always cover every record in the output directory, so several policies evaluated into one
directory (or shards that share it, or merged directories) give one comparison; a directory where
one label holds trials of two setups (e.g. two checkpoints) is refused rather than reported. A directory
that holds only ``outcomes.jsonl.gz`` (a published table) is reported from it, without the path plots.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.eval import plots, records
from vitfly.eval.aggregate import summarize
from vitfly.eval.config import SweepConfig
from vitfly.eval.fingerprint import SweepIdentity
from vitfly.eval.paired import paired_csv, paired_rows
from vitfly.eval.policy_source import PolicySource
from vitfly.eval.report import write_reports
from vitfly.eval.sweep import SweepOutcome, plan_trials, policy_source, rollout_config, run_sweep, sweep_identity

MAX_GIF_FRAMES = 300  # longer trials are subsampled (GIF size)


@dataclass
class EvaluationResult:
    rows: list[dict]
    outcome: SweepOutcome | None
    files: dict[str, Path] = field(default_factory=dict)


def scene_of(records_: Sequence[records.TrialRecord], env: str, preset: str, seed: int):
    """The obstacle layout stored with the trials, else regenerated from (env, preset, seed)."""
    from vitfly.sim.scenes import Scene, make_scene

    for rec in records_:
        if rec.env == env and rec.scene_seed == seed and "scene" in rec.extra:
            return Scene.from_dict(rec.extra["scene"], source=f"trial record {rec.key}")
    return make_scene(env, preset, seed)


REPORTS_STAMP = "reports.json"  # what the reports of a sweep directory were last written from


def _reports_key(out_dir: Path, with_plots: bool, title: str | None) -> dict:
    """The inputs of ``write_outputs``: every trial file's bytes, the title, whether plots, vitfly's version."""
    from vitfly import __version__

    digest = hashlib.sha256()
    for path in records.report_files(out_dir):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return {"records_sha256": digest.hexdigest(), "plots": with_plots, "title": title, "vitfly_version": __version__}


def write_outputs(out_dir: str | Path, with_plots: bool = True, title: str | None = None) -> tuple[list, dict]:
    """summary.csv, summary.md, outcomes.jsonl.gz (the records without paths) and the plots from every record
    in ``out_dir`` (``records.report_files``: its trial files, else its outcomes file).

    Written again only when the records (or the title, or whether plots are wanted) changed since the last
    time: a resumed sweep that flew nothing new costs no redrawing (about a second a figure). The stamp
    ``reports.json`` is written last, so reports cut short by a kill are written again.
    """
    out_dir = Path(out_dir)
    recs = records.read_report_records(out_dir)
    if not recs:
        raise VitflyError(f"{out_dir}: no finished trials (trials*.jsonl or {records.OUTCOMES_FILE}) to report on")
    records.check_consistent(recs, str(out_dir))
    rows = summarize(recs)
    key, stamp = _reports_key(out_dir, with_plots, title), out_dir / REPORTS_STAMP
    if stamp.exists():
        stored = json.loads(stamp.read_text())
        files = {name: out_dir / file for name, file in stored.get("files", {}).items()}
        if stored.get("key") == key and all(path.exists() for path in files.values()):
            return rows, files
    files = dict(write_reports(out_dir, rows, title))
    files["outcomes"] = out_dir / records.OUTCOMES_FILE
    if not records.only_outcomes(out_dir):  # else it is what these reports were read from
        records.write_outcomes(files["outcomes"], recs)
    if len({r.policy for r in recs}) > 1:  # policies flown on the same scenes: their paired differences
        files["paired"] = out_dir / "paired.csv"
        write_text(files["paired"], paired_csv(paired_rows(recs)))
    if with_plots:
        files.update(plots.write_standard_plots(
            out_dir, rows, recs, scene_loader=lambda env, preset, seed: scene_of(recs, env, preset, seed)))
    write_text(stamp, json.dumps({"key": key, "files": {name: str(Path(path).relative_to(out_dir))
                                                        for name, path in files.items()}}, indent=2) + "\n")
    return rows, files


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def depth_gif(cfg: SweepConfig, source: PolicySource | None = None, identity: SweepIdentity | None = None) -> Path:
    """Fly the first trial of the first env at the middle speed with depth frames recorded; write the GIF.

    ``depth_<label>_<env>.json`` beside it names the setup it shows; a GIF of another setup (e.g. the
    checkpoint before a retrain) is flown again.
    """
    from vitfly.sim.engine import fly
    from vitfly.sim.scenes import make_scene
    from vitfly.sim.visualize import write_gif

    spec = next(s for s in plan_trials(cfg) if s.speed == sorted(cfg.speeds)[len(cfg.speeds) // 2])
    path = Path(cfg.out) / f"depth_{_safe(cfg.label)}_{spec.env}.gif"
    source = source or policy_source(cfg)
    setup = (identity or sweep_identity(cfg, source)).setup(spec.env)
    about = {"policy": cfg.label, "setup_id": setup.id, "setup": setup.to_dict(), "env": spec.env,
             "scene_seed": spec.scene_seed, "speed": spec.speed}
    sidecar = path.with_suffix(".json")
    if path.exists() and sidecar.exists() and json.loads(sidecar.read_text()).get("setup_id") == setup.id:
        return path
    result = fly([make_scene(spec.env, spec.preset, spec.scene_seed)], [spec.speed], source.build(),
                 rollout_config(cfg, record_depth=True), engine=cfg.engine)[0]
    stride = max(1, -(-len(result.log) // MAX_GIF_FRAMES))
    write_gif(result, path, stride=stride)
    write_text(sidecar, json.dumps(about, indent=2) + "\n")
    return path


def merge_into(out_dir: str | Path, sources: Sequence[str | Path]) -> int:
    """Copy the records of other directories (e.g. shards run elsewhere) into ``out_dir``; returns how many were
    new (a key ``out_dir`` holds keeps its record). Refused, before anything is written, if a label would then
    hold two setups.

    Into a sweep directory the sources are sweep directories (their records keep their paths). Into a published
    table (``records.only_outcomes``: an ``outcomes.jsonl.gz`` alone) any source joins, without its paths: the
    outcomes file is written again with every record, as a results page commits it."""
    published = records.only_outcomes(out_dir)
    have = records.read_report_records(out_dir)
    keys = {r.key for r in have}
    new = []
    for src in sources:
        if not Path(src).is_dir():
            raise VitflyError(f"--merge {src}: not a directory of trials*.jsonl")
        if records.only_outcomes(src) and not published:
            raise VitflyError(f"--merge {src}: holds only {records.OUTCOMES_FILE} (records without their paths); "
                              "merge sweep directories, or merge into a published folder (its "
                              f"{records.OUTCOMES_FILE} alone)")
        for rec in records.read_report_records(src):
            if rec.key not in keys:
                new.append(rec)
                keys.add(rec.key)
    records.check_consistent([*have, *new], f"--merge into {out_dir}")
    if published:
        if new:
            records.write_outcomes(Path(out_dir) / records.OUTCOMES_FILE, [*have, *new])
        return len(new)
    for rec in new:
        records.append_record(Path(out_dir) / records.TRIALS_FILE, rec)
    return len(new)


def run_evaluation(cfg: SweepConfig, progress: bool = True) -> EvaluationResult:
    """Fly the sweep (resuming), then write every report of ``cfg.out``."""
    if records.only_outcomes(cfg.out):
        # its reports would then cover the new trials alone, and its outcomes file lose the published ones
        raise VitflyError(f"{cfg.out}: holds a published {records.OUTCOMES_FILE} and no trials*.jsonl; fly into "
                          "another --out, or rewrite its reports with --report-only")
    outcome = run_sweep(cfg, progress=progress)
    rows, files = write_outputs(cfg.out, cfg.plots)
    if cfg.gif:
        files[f"depth_{cfg.label}"] = depth_gif(cfg, identity=outcome.identity)
    if cfg.wandb_project:
        from vitfly.eval.wandb_log import log_evaluation

        images = {k: v for k, v in files.items() if Path(v).suffix in (".png", ".gif")}
        log_evaluation(cfg.wandb_project, rows, images, cfg.out, run_name=cfg.label, config=vars(cfg))
    return EvaluationResult(rows, outcome, files)
