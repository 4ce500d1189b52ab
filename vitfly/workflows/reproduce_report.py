"""The report of ``vitfly reproduce``: the paper's figures, tables and ``results.md`` from the study's outputs.

Everything is drawn from what is on disk (trial records, checkpoints, latency.json), so the report can be
written at any point of the study; findings without their data are marked n/a.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

from vitfly.atomic import write_text
from vitfly.errors import VitflyError
from vitfly.workflows.reproduce_config import (
    SWEEPS,
    ReproduceConfig,
    Run,
    done_checkpoint,
    draw_groups,
    eval_stage,
    paths_plan,
    runs,
    train_frames,
    train_stage,
)


def latency_markdown(results: list[dict]) -> str:
    """The paper's latency table (Table I) with ours beside it: median (p90) ms per call, batch 1."""
    from vitfly.eval.latency import PAPER_LATENCY_MS, PAPER_PARAMS
    from vitfly.eval.paper_tables import MODEL_LABELS

    def ms(r: dict | None) -> str:
        return "-" if r is None else f"{r['median_ms']:.2f} ({r['p90_ms']:.2f})"

    by_model: dict[str, dict[str, dict]] = {}
    for r in results:
        by_model.setdefault(r["model"], {})[r["device"]] = r
    threads = "/".join(str(t) for t in sorted({r["threads"] for r in results}))
    lines = [f"Inference latency per call, batch 1, {threads} CPU thread(s), {results[0]['backend'] if results else ''}"
             ", median (p90) ms; the paper's from its Table I.", "",
             "| model | parameters | paper parameters | CPU ms | GPU ms | paper CPU ms | paper GPU ms |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for model, d in by_model.items():
        any_r = d.get("cpu") or d.get("cuda")
        paper = PAPER_LATENCY_MS.get(model)
        cells = [MODEL_LABELS.get(model, model), f"{any_r['params']:,}",
                 f"{PAPER_PARAMS[model]:,}" if model in PAPER_PARAMS else "-", ms(d.get("cpu")), ms(d.get("cuda")),
                 f"{paper[0]:.1f}" if paper else "-", f"{paper[1]:.1f}" if paper else "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def study_label(policy: str) -> str:
    """The study's label of a policy: a run folder's name flown by hand (``vitfly evaluate --name convnet-state``,
    ``convnet-state-s1``) reads as the run's label (``convnet``, ``convnet-s1``); every other label is kept."""
    try:
        return Run.parse(policy).label
    except VitflyError:
        return policy


def _summary(directory: Path, published: str | None = None) -> tuple[list[dict], list] | tuple[None, None]:
    """The rows and records of one sweep: the run directory's flights, then a published folder's (``published``:
    ``report.published.<sweep>``, labels read by ``study_label``) that the run directory does not hold; a label
    flown with two setups is refused."""
    from vitfly.eval import records
    from vitfly.eval.aggregate import summarize

    recs = records.read_sweep(directory) if directory.is_dir() else []
    if published is not None:
        if not records.report_files(published):
            raise VitflyError(f"report.published.{directory.name}: {published} holds no {records.OUTCOMES_FILE} and "
                              "no trials*.jsonl (run from the root of a checkout of the repository, which has them)")
        theirs = [dataclasses.replace(r, policy=study_label(r.policy)) for r in records.read_report_records(published)]
        recs = records.merge_records([recs, theirs])
        records.check_consistent(recs, f"report: {directory} and {published}")
    return (summarize(recs), recs) if recs else (None, None)


def _ablation_tables(cfg: ReproduceConfig, rows: list[dict]) -> tuple[str, str]:
    from vitfly.workflows.ablation import AblationConfig, ablation_csv, ablation_markdown, ablation_rows

    acfg = AblationConfig(models=list(cfg.train.nostate_models),
                          evaluate=eval_stage(cfg, ["spheres", "trees"], cfg.evaluate.ablation_speeds, 1))
    table = ablation_rows(rows, acfg)
    return ablation_markdown(table, cfg.evaluate.ablation_speeds), ablation_csv(table)


def closed_loop_numbers(rows_by_sweep: dict[str, list[dict] | None], model: str, cfg: ReproduceConfig) -> dict:
    """Success (the paper's: no collision) per env and speed of one model, for the weights manifest."""
    from vitfly.eval.closed_loop import STUDY_ENVS, closed_loop_cells

    rows = [r for sweep in STUDY_ENVS for r in rows_by_sweep.get(sweep) or []]
    return {"eval_seed": cfg.evaluate.seed, "scene_preset": cfg.evaluate.preset, "success": "no collision",
            **closed_loop_cells(rows, model)}


def _training_table(cfg: ReproduceConfig) -> str:
    import torch

    if cfg.train.source == "pretrained":
        return _shipped_table(cfg)
    lines = ["| run | epochs | optimiser steps | training frames | wall time (min) | checkpoint |",
             "|---|---:|---:|---:|---:|---|"]
    for run in runs(cfg):
        d = cfg.train_dir(*run)
        ckpt = done_checkpoint(d)
        if ckpt is None:
            lines.append(f"| {run.label} | - | - | - | - | not trained |")
            continue
        cost = json.loads((d / "cost.json").read_text()) if (d / "cost.json").exists() else {}
        frames = train_frames(d, cfg.data)
        wall = f"{cost['wall_s'] / 60:.1f}" if "wall_s" in cost else "-"
        # a run trained elsewhere (scripts/gpu_reproduce.py) comes back without last.ckpt; done.json says
        elsewhere = json.loads((d / "done.json").read_text()).get("trained_on")
        if elsewhere:
            epochs, steps = elsewhere["epochs"], elsewhere["steps"]
            wall += f" ({elsewhere['device']})"
        else:
            last = d / "checkpoints" / "last.ckpt"  # a run restored from carry/ keeps only the weights it flies
            saved = torch.load(last if last.exists() else ckpt, map_location="cpu", weights_only=True)
            epochs, steps = saved.get("epoch", -1) + 1, saved.get("global_step", "-")
        lines.append(f"| {run.label} | {epochs} | {steps} | {frames if frames is not None else '-'} "
                     f"| {wall} | {ckpt} |")
    return "\n".join(lines) + "\n"


def _shipped_table(cfg: ReproduceConfig) -> str:
    """The training record of the shipped weights, from ``weights/manifest.json``."""
    from vitfly.zoo.pretrained import manifest_entry

    lines = ["| model | preset | optimiser steps | training frames | wall time (min) | dataset hash |",
             "|---|---|---:|---:|---:|---|"]
    for model in cfg.train.models:
        e = manifest_entry(model)
        wall = f"{e['train_wall_s'] / 60:.1f}" if isinstance(e.get("train_wall_s"), (int, float)) else "-"
        lines.append(f"| pretrained:{model} | {e.get('preset', '-')} | {e.get('steps', '-')} | "
                     f"{e.get('train_frames', '-')} | {wall} | {e.get('dataset_hash', '-')} |")
    return "\n".join(lines) + "\n"


def stage_report(cfg: ReproduceConfig) -> dict:
    """Figures, tables, results.md and results.json from whatever the study has flown so far."""
    from vitfly.eval import paper_figures
    from vitfly.eval.evaluation import scene_of
    from vitfly.eval.findings import findings_markdown, paper_findings
    from vitfly.eval.paired_findings import paired_findings
    from vitfly.eval.plots import plot_paths, scene_for_paths
    from vitfly.workflows.training_curves import training_curves_figure

    out, figures = cfg.out_dir, cfg.out_dir / "figures"
    rows: dict[str, list[dict] | None] = {}
    recs: dict[str, list] = {}
    for name in SWEEPS:
        rows[name], recs[name] = _summary(cfg.eval_dir(name), cfg.report.published.get(name))
    draws = draw_groups(cfg)
    other_draws = {label for run, labels in draws.items() for label in labels if label != run}
    files: dict[str, Path] = {}
    for env in ("spheres", "trees"):  # the figures show each run's own draw (the others: "Training draws")
        if rows[env]:
            files[f"{env}_collision_metrics"] = paper_figures.collision_metrics_figure(
                [r for r in rows[env] if r["policy"] not in other_draws], env, figures / f"{env}_collision_metrics.png")
    command_rows = [r for r in (rows["spheres"] or []) + (rows["trees"] or []) if r["policy"] not in other_draws]
    if command_rows:
        files["command_characteristics"] = paper_figures.command_figure(
            command_rows, figures / "command_characteristics.png")
    lateral = {}
    # the path figures need flown paths, which a published folder's records do not keep
    paths = [r for r in recs["paths"] or [] if r.has_path]
    if paths:
        plan = paths_plan(cfg)
        scene = scene_of(paths, "spheres", plan.preset, plan.scene_seed)
        title = (f"spheres scene seed {plan.scene_seed}, {plan.speed:g} m/s, {plan.repeats} repeats from starts "
                 f"within ±{plan.jitter_m:g} m: mean path, band ±0.1 σ (top-down, then side)")
        files["paths_fixed_scene"] = paper_figures.mean_paths_figure(paths, figures / "paths_fixed_scene.png",
                                                                     scene, title)
        files["paths_fixed_scene_3d"] = paper_figures.mean_paths_3d_figure(
            paths, figures / "paths_fixed_scene_3d.png", scene)
        lateral = {p: v["max_lateral"] for p, v in paper_figures.mean_paths(paths).items()}
    window = [r for r in recs["window"] or [] if r.has_path and r.policy not in other_draws]  # each run's own draw
    if window:
        seed, window_recs = scene_for_paths(window, "window")
        files["window_paths"] = plot_paths(window_recs, figures / "window_paths.png",
                                           scene_of(window_recs, "window", window_recs[0].preset, seed),
                                           title=f"window at {window_recs[0].speed:g} m/s, scene seed {seed}")
    modular_md = ""
    if recs["modular"]:
        from vitfly.eval.modular_baselines import modular_markdown

        files["modular_baselines"] = paper_figures.modular_baselines_figure(
            rows["modular"], recs["modular"], figures / "modular_baselines.png")
        modular_md = modular_markdown(rows["modular"], recs["modular"])
        write_text(out / "modular.md", modular_md)
    ablation_md = ""
    if rows["ablation"]:
        ablation_md, ablation_csv = _ablation_tables(cfg, rows["ablation"])
        write_text(out / "ablation.md", ablation_md)
        write_text(out / "ablation.csv", ablation_csv)
    latency_md = ""
    if (out / "latency.json").exists():
        latency_md = latency_markdown(json.loads((out / "latency.json").read_text())["results"])
        write_text(out / "latency.md", latency_md)
    findings = paper_findings(rows["spheres"], rows["trees"], rows["window"], rows["ablation"], lateral)
    paired = paired_findings(recs["spheres"], recs["trees"], recs["window"], recs["ablation"], recs["modular"],
                             draws=draws)
    paired_md = paired_markdown(paired, recs, draws)
    paired_png = paper_figures.paired_findings_figure(paired, figures / "paired_findings.png")
    if paired_png is not None:
        files["paired_findings"] = paired_png
    curves_png = training_curves_figure(cfg, figures / "training_curves.png")
    if curves_png is not None:
        files["training_curves"] = curves_png
    text = results_markdown(cfg, findings_markdown(findings), files, ablation_md, latency_md, lateral, paired_md,
                            modular_md, draws_markdown(cfg, rows))
    write_text(out / "results.md", text)
    result = {"preset": cfg.preset, "findings": [f.to_dict() for f in findings],
              "paired_findings": [f.to_dict() for f in paired], "modular": _modular_numbers(rows, recs),
              "max_mean_lateral_deviation_m": lateral,
              "files": {k: str(v) for k, v in files.items()}, "config": dataclasses.asdict(cfg)}
    write_text(out / "results.json", json.dumps(result, indent=2, default=str) + "\n")
    if cfg.train.source == "pretrained":
        _record_closed_loop(cfg, rows)
    elif cfg.train.publish_weights:
        _publish_closed_loop(cfg, rows)
    print(f"[report] {out / 'results.md'}: " + ", ".join(f"{f.key} {f.verdict}" for f in findings))
    print("[report] paired: " + ", ".join(f"{f.key} {f.verdict}" for f in paired))
    return result


def _modular_numbers(rows: dict, recs: dict) -> dict:
    """The modular comparison's velocity-matching target and replan times, for results.json ({} if not flown)."""
    if not recs.get("modular"):
        return {}
    from vitfly.eval.modular_baselines import cruise_speeds, planner_policies, replan_latency, velocity_matching

    modular = recs["modular"]
    targets = velocity_matching(rows["modular"], planner_policies(modular), cruise=cruise_speeds(modular))
    return {"velocity_matching": [t.to_dict() for t in targets],
            "replan_latency": replan_latency(modular)}


def draws_markdown(cfg: ReproduceConfig, rows: dict[str, list[dict] | None]) -> str:
    """Each run with other training draws: every draw's seed and its success per sweep, all speeds pooled."""
    from vitfly.eval.findings import label, split_draw
    from vitfly.workflows.pipeline import success_by_policy

    draws = {run: labels for run, labels in draw_groups(cfg).items() if len(labels) > 1}
    if not draws:
        return ""
    sweeps = [name for name in ("spheres", "trees", "window", "ablation") if rows.get(name)]
    rates = {name: {env: success_by_policy([r for r in rows[name] if r["env"] == env])
                    for env in sorted({r["env"] for r in rows[name]})} for name in sweeps}
    columns = [(name, env) for name in sweeps for env in rates[name]]
    lines = ["| run | seed | " + " | ".join(f"{name}" + (f" ({env})" if env != name else "") for name, env in columns)
             + " |", "|---|---:|" + "---:|" * len(columns)]
    by_run = {r.run: r for r in runs(cfg, with_draws=False)}
    for run, labels in draws.items():
        for policy in labels:
            seed = split_draw(policy)[1]
            if seed is None:
                seed = train_stage(cfg, by_run[run].model, by_run[run].use_state).seed
            cells = [f"{100 * rates[n][e][policy]:.0f} %" if policy in rates[n][e] else "-" for n, e in columns]
            lines.append(f"| {label(run)} | {seed} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def paired_markdown(paired: list, recs: dict[str, list | None], draws: dict[str, list[str]] | None = None) -> str:
    """The paired findings table, then ViT+LSTM's success against every other policy in each sweep (a run with
    several training draws by their mean)."""
    from vitfly.eval.paired_findings import lead_table, paired_findings_markdown

    parts = [paired_findings_markdown(paired)]
    for sweep in ("spheres", "trees", "window"):
        if recs.get(sweep) and any(r.policy == "vit_lstm" for r in recs[sweep]):
            parts += [f"ViT+LSTM's success minus each policy's in {sweep} (paired over the same scenes; "
                      "* the 95 % interval excludes 0):", "", lead_table(recs[sweep], sweep, draws=draws)]
    if recs.get("modular") and any(r.policy == "vit_lstm" for r in recs["modular"]):
        for metric, words in (("success", "success"), ("speed_error", "speed error abs(actual / desired - 1)")):
            parts += [f"ViT+LSTM's {words} minus each policy's in the modular comparison (spheres, paired over the "
                      "same scenes; * the 95 % interval excludes 0):", "",
                      lead_table(recs["modular"], "spheres", metric=metric, draws=draws)]
    return "\n".join(parts)


def _publish_closed_loop(cfg: ReproduceConfig, rows: dict) -> None:
    from vitfly.zoo.pretrained import read_manifest, update_manifest

    manifest = read_manifest(cfg.train.weights_dir, missing_ok=True)["models"]
    for model in cfg.train.publish_models:
        ckpt = done_checkpoint(cfg.train_dir(model, True))
        entry = manifest.get(model)
        if ckpt is not None and entry and entry.get("source_checkpoint") == str(ckpt.resolve()):
            update_manifest(model, {"closed_loop": closed_loop_numbers(rows, model, cfg)}, cfg.train.weights_dir)


def _record_closed_loop(cfg: ReproduceConfig, rows: dict) -> None:
    """The shipped weights' closed-loop numbers into their manifest entries (those flown in this study); not
    into an installed vitfly's own manifest (they stay in results.json)."""
    from vitfly.eval.closed_loop import STUDY_ENVS
    from vitfly.zoo.pretrained import WEIGHTS_ENV, can_publish, update_manifest

    if not can_publish():
        print(f"[report] closed-loop numbers kept in results.json only: vitfly is installed, and its shipped weights "
              f"manifest is not written to (set {WEIGHTS_ENV} to fly and record weights of your own)")
        return
    for model in cfg.train.models:
        numbers = closed_loop_numbers(rows, model, cfg)
        if any(env in numbers for env in STUDY_ENVS):
            update_manifest(model, {"closed_loop": numbers})


def results_markdown(cfg: ReproduceConfig, findings_md: str, files: dict[str, Path], ablation_md: str,
                     latency_md: str, lateral: dict[str, float], paired_md: str = "", modular_md: str = "",
                     draws_md: str = "") -> str:
    e = cfg.evaluate
    rel = {k: os.path.relpath(v, cfg.out_dir) for k, v in files.items()}
    figure_lines = [f"- {k.replace('_', ' ')}: ![{k}]({v})" for k, v in rel.items()
                    if k != "training_curves"]  # shown under Training
    lateral_lines = ["| policy | max mean lateral deviation (m) |", "|---|---:|",
                     *(f"| {p} | {v:.2f} |" for p, v in lateral.items())] if lateral else ["(paths not flown)"]
    # the shipped weights were trained elsewhere: their datasets are in the training table, not cfg.data
    source = "Weights from the manifest (training table below)" if cfg.train.source == "pretrained" else \
        f"Dataset `{cfg.data}`"
    return "\n".join([
        f"# vitfly reproduce: the paper's results section (preset `{cfg.preset}`)",
        "",
        f"Made by `vitfly reproduce --config ... --preset {cfg.preset}` into `{cfg.out}`. {source}; "
        f"scenes of evaluation seed {e.seed} (preset {e.preset}), which the collection never used. Trials per "
        f"speed: spheres {e.spheres_trials}, trees {e.trees_trials}, window {e.window_trials} (at "
        f"{', '.join(f'{s:g}' for s in e.window_speeds)} m/s), ablation {e.ablation_trials}. Success is the "
        "paper's (a trial without a collision) unless a row says strict (goal reached and no collision).",
        "",
        "## Findings",
        "",
        findings_md,
        "## Paired comparisons",
        "",
        "Every policy flies the same scenes, so two policies are compared scene by scene: the difference of a "
        "metric with a 95 % paired-bootstrap interval over scenes (BCa, 10,000 resamples; a resample keeps all "
        "speeds of a drawn scene), and for success McNemar's exact test beside it. A claim is decided when its "
        "interval excludes 0 (vitfly.eval.paired)."
        + (" A run trained more than once (training draws, below) is compared by its draws' mean, with a "
           "two-level bootstrap: each resample draws each policy's training draws, then the scenes (percentile "
           "interval); a run trained once borrows the draws' spread pooled over the runs trained more than once (a "
           "normal term with their pooled variance). The findings table above reads each run's own draw."
           if draws_md else ""),
        "",
        *([f"![every claim's paired difference and its interval]({rel['paired_findings']})", ""]
          if "paired_findings" in rel else []),
        paired_md or "(no trials yet)\n",
        *(["## Training draws", "",
           "Runs trained again with other seeds (train.draws: the weights' initialisation, the data order and the "
           "train/validation split), flown on the same scenes as the run itself; success, all speeds pooled:", "",
           draws_md] if draws_md else []),
        "## Training",
        "",
        _training_table(cfg),
        *([f"![training and validation loss per epoch of every run]({rel['training_curves']})", ""]
          if "training_curves" in rel else []),
        "## Figures",
        "",
        *figure_lines,
        "",
        "Per-sweep tables and plots: `eval/<sweep>/summary.md`, `eval/<sweep>/*.png`.",
        "",
        f"## Paths in one scene ({cfg.paths.repeats} repeats at {cfg.paths.speed:g} m/s)",
        "",
        "Paper: ViT+LSTM takes the most direct path, maximum mean lateral deviation 0.75 m.",
        "",
        *lateral_lines,
        "",
        "## Ablation: state input",
        "",
        ablation_md or "(not evaluated)\n",
        "## Modular baselines",
        "",
        *([f"Spheres, scenes of sweep seed {cfg.modular.seed if cfg.modular.seed is not None else e.seed}, "
           f"{cfg.modular.trials} trials per speed and policy (figure: modular baselines; the finding above).", "",
           modular_md] if modular_md else ["(not flown)\n"]),
        "## Latency",
        "",
        latency_md or "(not measured)\n",
    ]) + "\n"
