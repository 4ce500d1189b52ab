"""The report of ``vitfly dagger``: success and collisions per round and speed for DAgger and the baseline.

Written into the run directory:

- ``dagger.md``: per round (beta, labelled frames) and method, the success rate at each speed (the paper's
  definition: no collision) with its 95 % Wilson interval and the mean collisions per trial; the expert on
  the same scenes; and whether the target holds (at ``report.target_speed`` the last round's DAgger student
  beats the baseline by ``report.target_margin_points`` points or more, and beats the expert);
- ``dagger.csv``: the same numbers, one row per (round, method, env, speed);
- ``success_vs_frames.png``: success vs expert-labelled frames, DAgger and the baseline, one panel per speed;
- ``paths_<env>.png``: top-down and side paths of the last round's students (and the expert) over repeats
  of one evaluation scene (``vitfly.eval.plots.plot_paths``);
- ``dagger.json``: all of it plus the stage results (frames, optimiser steps, wall times).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from vitfly.atomic import write_text
from vitfly.eval import records
from vitfly.eval.findings import wilson
from vitfly.workflows.dagger_config import DaggerConfig, paths_plan, student_label

METHODS = {"dagger": "DAgger", "bc": "BC (equal frames)"}
CSV_COLUMNS = ("round", "beta", "labelled_frames", "method", "policy", "env", "speed", "trials", "successes",
               "success_rate", "ci_low", "ci_high", "collisions_mean", "success_strict_rate")


def cell(recs: list) -> dict:
    """Success (the paper's: no collision) with its Wilson interval, and mean collisions, over ``recs``."""
    n = len(recs)
    k = sum(bool(r.success_paper) for r in recs)
    lo, hi = wilson(k, n)
    collisions = [r.metrics.get("collisions") for r in recs]
    collisions = [c for c in collisions if c is not None]
    return {"trials": n, "successes": k, "success_rate": k / n if n else math.nan, "ci_low": lo, "ci_high": hi,
            "collisions_mean": float(np.mean(collisions)) if collisions else math.nan,
            "success_strict_rate": float(np.mean([r.success_strict for r in recs])) if n else math.nan}


def table_rows(cfg: DaggerConfig, recs: list, results: dict) -> list[dict]:
    """One row per (round, method, env, speed), then the baselines (round None)."""
    by_key: dict[tuple, list] = {}
    for rec in recs:
        by_key.setdefault((rec.policy, rec.env, float(rec.speed)), []).append(rec)
    rows = []
    for r in cfg.rounds:
        frames = results.get(f"r{r}.collect", {}).get("frames")
        for method in ("dagger", "bc"):
            if method == "bc" and r and not cfg.baseline:
                continue
            label = student_label(r, method == "bc")
            for env in cfg.evaluate.env:
                for speed in cfg.evaluate.speeds:
                    rows.append({"round": r, "beta": cfg.schedule.beta(r) if method == "dagger" else 1.0,
                                 "labelled_frames": frames, "method": method, "policy": label, "env": env,
                                 "speed": float(speed), **cell(by_key.get((label, env, float(speed)), []))})
    for b in cfg.evaluate.baselines:
        for env in cfg.evaluate.env:
            for speed in cfg.evaluate.speeds:
                rows.append({"round": None, "beta": None, "labelled_frames": None, "method": b, "policy": b,
                             "env": env, "speed": float(speed), **cell(by_key.get((b, env, float(speed)), []))})
    return rows


def _find(rows: list[dict], **match) -> dict | None:
    for row in rows:
        if all(row[k] == v for k, v in match.items()):
            return row
    return None


def target_check(cfg: DaggerConfig, rows: list[dict]) -> dict:
    """The issue's target at the last round: DAgger - baseline >= margin points, and DAgger > expert."""
    rep, env, last = cfg.report, cfg.evaluate.env[0], cfg.rounds[-1]
    speed = float(rep.target_speed)
    dagger = _find(rows, round=last, method="dagger", env=env, speed=speed)
    bc = _find(rows, round=last, method="bc", env=env, speed=speed)
    expert = _find(rows, method="expert", env=env, speed=speed)
    out = {"env": env, "speed": speed, "round": last, "margin_points": rep.target_margin_points,
           "dagger": dagger and dagger["success_rate"], "bc": bc and bc["success_rate"],
           "expert": expert and expert["success_rate"]}
    if last == 0 or not cfg.baseline or dagger is None or bc is None or not dagger["trials"] or not bc["trials"]:
        return {**out, "met": None, "why": "no DAgger round against a baseline to compare"}
    gain = 100.0 * (dagger["success_rate"] - bc["success_rate"])
    beats_expert = None if expert is None or not expert["trials"] else dagger["success_rate"] > expert["success_rate"]
    met = gain >= rep.target_margin_points and beats_expert is not False
    why = f"DAgger {_pct(dagger)} vs BC {_pct(bc)}: {gain:+.0f} points (target >= +{rep.target_margin_points:.0f})"
    if beats_expert is not None:
        why += f"; expert {_pct(expert)}: DAgger {'beats' if beats_expert else 'does not beat'} it"
    return {**out, "gain_points": gain, "beats_expert": beats_expert, "met": bool(met), "why": why}


def _pct(row: dict | None) -> str:
    if row is None or not row["trials"]:
        return "-"
    return f"{100 * row['success_rate']:.0f} % ({row['successes']}/{row['trials']})"


def _cell_text(row: dict | None) -> str:
    if row is None or not row["trials"]:
        return "-"
    return (f"{100 * row['success_rate']:.0f} % [{100 * row['ci_low']:.0f}, {100 * row['ci_high']:.0f}] · "
            f"{row['collisions_mean']:.2f}")


def markdown(cfg: DaggerConfig, rows: list[dict], target: dict, results: dict) -> str:
    speeds = [float(s) for s in cfg.evaluate.speeds]
    t, e = cfg.train, cfg.evaluate
    start = f", starting from {t.init_checkpoint}" if t.init_checkpoint else ""
    lines = [f"# DAgger vs behaviour cloning at equal labelled frames ({t.model}, preset {cfg.preset})", "",
             f"Each cell: success (no collision) over {e.trials} trials with its 95 % Wilson interval · mean "
             f"collisions per trial; {e.preset} scenes from evaluation seed {e.seed}, never flown in training. "
             f"Round 0 is behaviour cloning on {cfg.data.expert_trajectories} expert flights{start} (shared by "
             f"both methods); each later round adds {cfg.data.trajectories_per_round} flights of the previous "
             f"student mixed with the expert (beta_i = {cfg.schedule.beta0:g} x {cfg.schedule.decay:g}^i) for DAgger, "
             "or expert flights up to the same number of labelled frames for BC, and fine-tunes for the same "
             "number of optimiser steps.", ""]
    for env in e.env:
        lines += [f"## {env}", "", "| round | beta | labelled frames | method | "
                  + " | ".join(f"{s:g} m/s" for s in speeds) + " |",
                  "| ---: | ---: | ---: | --- | " + " | ".join("---" for _ in speeds) + " |"]
        for r in cfg.rounds:
            for method in ("dagger", "bc"):
                if r == 0 and method == "bc":
                    continue  # the same student
                cells = [_find(rows, round=r, method=method, env=env, speed=s) for s in speeds]
                if all(c is None for c in cells):
                    continue
                first = next(c for c in cells if c is not None)
                name = "BC (shared round 0)" if r == 0 else METHODS[method]
                beta = f"{first['beta']:.3f}" if method == "dagger" else "1 (expert)"
                frames = "-" if first["labelled_frames"] is None else f"{first['labelled_frames']:,}"
                lines.append(f"| {r} | {beta} | {frames} | {name} | "
                             + " | ".join(_cell_text(c) for c in cells) + " |")
        for b in e.baselines:
            cells = [_find(rows, method=b, env=env, speed=s) for s in speeds]
            lines.append(f"| - | - | - | {b} | " + " | ".join(_cell_text(c) for c in cells) + " |")
        lines.append("")
    lines += ["## Target", ""]
    if target.get("met") is None:
        lines.append(f"Not checked: {target['why']}.")
    else:
        verdict = "met" if target["met"] else "NOT met"
        lines.append(f"At {target['speed']:g} m/s in {target['env']}, round {target['round']}: {target['why']}. "
                     f"Target {verdict} (for {t.model}).")
    steps = [(r, results.get(f"r{r}.train", {}).get("steps"), results.get(f"r{r}.bc-train", {}).get("steps"))
             for r in cfg.rounds]
    lines += ["", "Optimiser steps per round (DAgger / BC): "
              + ", ".join(f"r{r} {a}" + ("" if b is None else f" / {b}") for r, a, b in steps) + ".", ""]
    return "\n".join(lines)


def rows_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in CSV_COLUMNS})
    return buf.getvalue()


def plot_success_vs_frames(cfg: DaggerConfig, rows: list[dict], path: Path) -> Path:
    """Success vs expert-labelled frames, DAgger and the baseline (95 % Wilson bars), one panel per speed."""
    from vitfly.sim.visualize import save_figure

    env = cfg.evaluate.env[0]
    speeds = [float(s) for s in cfg.evaluate.speeds]
    fig = Figure(figsize=(4.0 * len(speeds), 3.4), layout="constrained")
    axes = fig.subplots(1, len(speeds), squeeze=False)[0]
    styles = {"dagger": ("tab:red", "o", "DAgger"), "bc": ("tab:blue", "s", "BC, equal frames")}
    for ax, speed in zip(axes, speeds, strict=True):
        for method, (colour, marker, name) in styles.items():
            # round 0's student is both methods' first point
            pts = sorted((r for r in rows if r["method"] == method and r["env"] == env and r["speed"] == speed
                          and r["trials"] and r["labelled_frames"] is not None), key=lambda r: r["round"])
            if not pts:
                continue
            x = np.array([p["labelled_frames"] for p in pts], float)
            y = np.array([p["success_rate"] for p in pts]) * 100
            err = np.array([[p["success_rate"] - p["ci_low"], p["ci_high"] - p["success_rate"]] for p in pts]).T * 100
            ax.errorbar(x, y, yerr=err, color=colour, marker=marker, capsize=3, lw=1.5, ms=4, label=name)
        expert = _find(rows, method="expert", env=env, speed=speed)
        if expert is not None and expert["trials"]:
            ax.axhline(100 * expert["success_rate"], color="black", ls="--", lw=1, label="expert")
        ax.set_title(f"{env}, {speed:g} m/s")
        ax.set_xlabel("expert-labelled frames")
        ax.set_ylabel("success (%), no collision")
        ax.set_ylim(-5, 105)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=len(labels))
    fig.suptitle(f"{cfg.train.model}: success vs labelled frames (bars: 95 % Wilson)")
    return save_figure(fig, path)


def plot_student_paths(cfg: DaggerConfig) -> Path | None:
    """The last round's students (and the expert) over repeats of one evaluation scene."""
    from vitfly.eval.plots import plot_paths
    from vitfly.sim.scenes import make_scene

    recs = records.read_sweep(cfg.out_dir / "paths") if (cfg.out_dir / "paths").exists() else []
    if not recs:
        return None
    plan = paths_plan(cfg)
    scene = make_scene(plan.env, plan.preset, plan.scene_seed)
    title = (f"{plan.env}: evaluation scene {plan.scene_seed} at {plan.speed:g} m/s, {plan.repeats} repeats per "
             f"policy (round {cfg.rounds[-1]}; top-down, then side)")
    return plot_paths(recs, cfg.out_dir / f"paths_{plan.env}.png", scene, title)


def write_report(cfg: DaggerConfig, results: dict) -> dict:
    recs = records.read_sweep(cfg.out_dir / "eval")
    rows = table_rows(cfg, recs, results)
    target = target_check(cfg, rows)
    out = cfg.out_dir
    md = markdown(cfg, rows, target, results)
    write_text(out / "dagger.md", md)
    write_text(out / "dagger.csv", rows_csv(rows))
    files = {"markdown": out / "dagger.md", "csv": out / "dagger.csv",
             "success_vs_frames": plot_success_vs_frames(cfg, rows, out / "success_vs_frames.png")}
    paths = plot_student_paths(cfg)
    if paths is not None:
        files["paths"] = paths
    report = {"target": target, "rows": rows, "files": {k: str(v) for k, v in files.items()},
              "stages": {k: v for k, v in results.items() if k != "report"}, "config": dataclasses.asdict(cfg)}
    write_text(out / "dagger.json", json.dumps(report, indent=1, default=_json_default) + "\n")
    print(md)
    print("wrote " + ", ".join(str(p) for p in [*files.values(), out / "dagger.json"]))
    return {"target": target, "files": report["files"]}


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON-able: {type(value).__name__}")
