"""The paper's results figures, from summary rows and trial records (``vitfly reproduce`` draws them all).

- ``collision_metrics_figure``: per environment, collisions per trial, time in collision per obstacle (the
  paper's definition) and success rate (no collision) vs speed (the paper's Spheres/Trees figures);
- ``command_figure``: commanded acceleration and energy cost vs speed, one column per environment
  (the paper's acceleration/energy figure);
- ``mean_paths_figure``: top-down and side views of each policy's mean path over repeated trials of one
  scene with a band of +-0.1 standard deviations (the paper's path-distribution figure);
- ``mean_paths_3d_figure``: the same mean paths in 3D;
- ``modular_baselines_figure``: collision rate and actual vs desired forward speed of the modular planners beside
  the networks, and the planners' replan compute time (the paper's modular-baselines figure);
- ``paired_findings_figure``: the verdicts as a picture, every claim's paired difference A - B with its 95 %
  interval, coloured by what it decides (``draw_paired_differences`` draws any list of paired differences).

Figures are ``matplotlib.figure.Figure`` objects saved atomically (no pyplot state).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from vitfly.eval.findings import label
from vitfly.eval.paired import OUTCOMES, PairedDifference
from vitfly.eval.paired_findings import METRIC_WORDS, PairedFinding
from vitfly.eval.plots import _save, plot_vs_speed, policy_colours
from vitfly.eval.records import TrialRecord
from vitfly.eval.repeats import mean_path
from vitfly.sim.visualize import draw_scene, format_views

BAND_SIGMA = 0.1  # the paper's band: mean +- 0.1 sigma
DECIDED_COLOURS = {"for": "tab:green", "against": "tab:red", "undecided": "0.55"}  # PairedDifference.side
X_STEP_M = 0.25  # resampling grid of the mean paths


def collision_metrics_figure(rows: Sequence[dict], env: str, path: str | Path) -> Path:
    sel = [r for r in rows if r["env"] == env]
    return plot_vs_speed(sel, [("collisions", "collisions per trial", False),
                               ("time_in_collision", "time in collision\nper obstacle (s)", False),
                               ("success_paper_rate", "success (%)\n(no collision)", True)],
                         path, f"{env}: collision metrics vs speed")


def command_figure(rows: Sequence[dict], path: str | Path) -> Path:
    return plot_vs_speed(rows, [("cmd_acc", "commanded acceleration (1/s²)", False),
                                ("energy_cost", "energy cost (1/s²)", False)],
                         path, "command characteristics vs speed (lower is better)")


def _by_policy(recs: Sequence[TrialRecord]) -> dict[str, list[TrialRecord]]:
    out: dict[str, list[TrialRecord]] = {}
    for r in recs:
        out.setdefault(r.policy, []).append(r)
    return dict(sorted(out.items()))


def mean_paths(recs: Sequence[TrialRecord], goal_x_m: float = 60.0) -> dict[str, dict[str, np.ndarray]]:
    """Per policy: ``x`` grid (G,), ``mean`` (G, 2) of (y, z), ``std`` (G, 2), ``count`` (G,), and ``max_lateral``
    (largest |mean y - y at the start| in m, the paper's 'maximum mean lateral deviation')."""
    x_grid = np.arange(0.0, goal_x_m + 1e-9, X_STEP_M)
    out = {}
    for policy, group in _by_policy(recs).items():
        mean, std, count = mean_path(group, x_grid)
        y0 = float(np.nanmean([g.path_arrays()["position"][0, 1] for g in group]))
        lateral = np.abs(mean[:, 0] - y0)
        out[policy] = {"x": x_grid, "mean": mean, "std": std, "count": count,
                       "max_lateral": float(np.nanmax(lateral)) if np.isfinite(lateral).any() else float("nan")}
    return out


def mean_paths_figure(recs: Sequence[TrialRecord], path: str | Path, scene=None, title: str = "") -> Path:
    paths = mean_paths(recs)
    colours = policy_colours(list(paths))
    fig = Figure(figsize=(11, 5.8), layout="constrained")
    ax_top, ax_side = fig.subplots(2, 1, height_ratios=(2, 1))
    if scene is not None:
        draw_scene(ax_top, ax_side, scene)
    for policy, p in paths.items():
        n = int(p["count"].max()) if len(p["count"]) else 0
        for ax, k in ((ax_top, 0), (ax_side, 1)):
            mean, band = p["mean"][:, k], BAND_SIGMA * p["std"][:, k]
            ax.fill_between(p["x"], mean - band, mean + band, color=colours[policy], alpha=0.3, lw=0, zorder=3)
            ax.plot(p["x"], mean, color=colours[policy], lw=1.4, zorder=4,
                    label=f"{policy} ({n} trials)" if k == 0 else None)
    format_views(ax_top, ax_side)
    ax_top.set_title(title or f"mean path over repeated trials of one scene, band ±{BAND_SIGMA:g} σ "
                     "(top-down, then side)")
    ax_top.legend(loc="upper left", fontsize=8)
    return _save(fig, Path(path))


def mean_paths_3d_figure(recs: Sequence[TrialRecord], path: str | Path, scene=None, title: str = "") -> Path:
    paths = mean_paths(recs)
    colours = policy_colours(list(paths))
    fig = Figure(figsize=(9, 6), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    if scene is not None and len(scene.spheres):
        u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 12), np.linspace(0, np.pi, 7))
        for x, y, z, r in scene.spheres:
            if abs(y) < 6:  # the obstacles near the flight corridor only
                ax.plot_surface(x + r * np.cos(u) * np.sin(v), y + r * np.sin(u) * np.sin(v), z + r * np.cos(v),
                                color="0.7", alpha=0.25, lw=0)
    for policy, p in paths.items():
        ax.plot(p["x"], p["mean"][:, 0], p["mean"][:, 1], color=colours[policy], lw=1.8, label=policy)
    ax.set_xlabel("x (m), forward")
    ax.set_ylabel("y (m), left +")
    ax.set_zlabel("z (m), up +")
    ax.set_xlim(0, 60)
    ax.set_ylim(-6, 6)
    ax.set_zlim(0, 10)
    ax.set_title(title or "mean paths (3D)")
    ax.legend(loc="upper left", fontsize=8)
    return _save(fig, Path(path))


CONTROL_PERIOD_MS = 1000.0 / 30.0  # one control tick at the paper's 30 Hz
REPLAN_PERIOD_MS = 100.0  # the planners' 10 Hz replan period (configs/planners.yaml)


def modular_baselines_figure(rows: Sequence[dict], recs: Sequence[TrialRecord], path: str | Path,
                             title: str = "") -> Path:
    """``draw_modular_baselines`` saved to ``path``."""
    return _save(draw_modular_baselines(rows, recs, title), Path(path))


def draw_modular_baselines(rows: Sequence[dict], recs: Sequence[TrialRecord], title: str = "") -> Figure:
    """The paper's comparison with modular baselines, three panels: collision rate (trials with a collision, %) vs
    desired speed; actual forward speed vs desired speed (m/s): the cruise speed between x = 10 and 50 m
    (``modular_baselines.cruise_speeds``), with the y = x line a policy that flies the speed asked of it follows;
    each planner's replan compute time (mean and 95th percentile, ms) against the
    control tick and the replan period. ``rows``: summary rows of one env; ``recs``: its trial records."""
    from vitfly.eval.modular_baselines import CRUISE_WINDOW_M, cruise_speeds, replan_latency

    cruise = cruise_speeds(recs)
    policies = sorted({r["policy"] for r in rows})
    colours = policy_colours(policies)
    fig = Figure(figsize=(13.5, 4.2), layout="constrained")
    ax_col, ax_speed, ax_lat = fig.subplots(1, 3, width_ratios=(1, 1, 0.8))
    top = 0.0
    for p in policies:
        sel = sorted((r for r in rows if r["policy"] == p), key=lambda r: r["speed"])
        x = np.array([r["speed"] for r in sel], float)
        ax_col.plot(x, [100.0 * (1.0 - r["success_paper_rate"]) for r in sel], marker="o", color=colours[p],
                    label=p, lw=1.5, ms=4)
        fwd = np.array([cruise.get((p, float(r["speed"])), np.nan) for r in sel], float)
        ax_speed.plot(x, fwd, marker="o", color=colours[p], lw=1.5, ms=4)
        top = max(top, float(np.nanmax(x)) if len(x) else 0.0, float(np.nanmax(fwd)) if np.isfinite(fwd).any() else 0)
    ax_speed.plot([0, top + 0.5], [0, top + 0.5], ls="--", color="0.5", lw=1, label="y = x (desired speed)")
    ax_col.set(xlabel="desired speed (m/s)", ylabel="collision rate (%)\n(trials with a collision)", ylim=(-5, 105),
               title="collisions")
    window = f"x {CRUISE_WINDOW_M[0]:g}-{CRUISE_WINDOW_M[1]:g} m"
    ax_speed.set(xlabel="desired speed (m/s)", ylabel=f"actual forward speed (m/s), {window}", xlim=(0, top + 0.5),
                 ylim=(0, top + 0.5), title="actual vs desired forward speed")
    ax_speed.legend(loc="upper left", fontsize=8)
    latency = replan_latency(recs)
    names = list(latency)
    k = np.arange(len(names))
    ax_lat.bar(k - 0.2, [latency[n]["mean_ms"] for n in names], 0.4, color=[colours.get(n, "0.5") for n in names],
               label="mean")
    ax_lat.bar(k + 0.2, [latency[n]["p95_ms"] for n in names], 0.4, color=[colours.get(n, "0.5") for n in names],
               alpha=0.45, hatch="//", label="95th percentile")
    ax_lat.axhline(CONTROL_PERIOD_MS, ls=":", color="0.3", lw=1, label=f"control tick ({CONTROL_PERIOD_MS:.0f} ms)")
    ax_lat.axhline(REPLAN_PERIOD_MS, ls="--", color="0.3", lw=1, label=f"replan period ({REPLAN_PERIOD_MS:.0f} ms)")
    ax_lat.set_xticks(k, names, rotation=25, ha="right", fontsize=8)
    ax_lat.set(ylabel="replan compute time (ms)", title="planning latency")
    ax_lat.legend(fontsize=7, loc="upper left")
    for ax in (ax_col, ax_speed, ax_lat):
        ax.grid(alpha=0.3)
    handles, labels = ax_col.get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 6))
    fig.suptitle(title or "modular baselines vs end-to-end: spheres, the same scenes for every policy")
    return fig


def paired_findings_figure(findings: Sequence[PairedFinding], path: str | Path, title: str = "") -> Path | None:
    """``draw_paired_differences`` of ``vitfly.eval.paired_findings.PairedFinding``s, a panel per finding and metric
    (its claim and verdict above it), saved to ``path``; None when no finding has a comparison."""
    groups = finding_panels(findings)
    if not groups:
        return None
    return paired_differences_figure(groups, path, title or "the paper's findings, decided on pairs")


def paired_differences_figure(groups: Sequence[tuple[str, Sequence[PairedDifference]]], path: str | Path,
                              title: str = "") -> Path:
    """``draw_paired_differences`` saved to ``path``."""
    return _save(draw_paired_differences(groups, title), Path(path))


def finding_panels(findings: Sequence[PairedFinding]) -> list[tuple[str, list[PairedDifference]]]:
    """(claim and verdict, its comparisons on one metric) per finding and metric; findings without any: none."""
    return [(f"{f.claim}: {f.verdict}", [d for d in f.comparisons if d.metric == metric])
            for f in findings for metric in dict.fromkeys(d.metric for d in f.comparisons)]


def draw_paired_differences(groups: Sequence[tuple[str, Sequence[PairedDifference]]], title: str = "") -> Figure:
    """One panel per (name, differences) group, one row per difference: A - B (a dot; success in points) and its
    95 % paired interval (a bar), green where it decides the claim "A better than B" for it, red against (for a
    lower-is-better metric a difference below 0 is for), grey where it cannot tell; a line at 0. The differences of
    one group share a metric (its x axis)."""
    heights = [len(diffs) + 1.5 for _, diffs in groups]
    fig = Figure(figsize=(9.0, 0.3 * sum(heights) + 0.8), layout="constrained")
    axes = fig.subplots(len(groups), 1, height_ratios=heights, squeeze=False)[:, 0]
    for ax, (name, diffs) in zip(axes, groups, strict=True):
        metric = diffs[0].metric
        if any(d.metric != metric for d in diffs):
            raise ValueError(f"{name}: one panel, one metric (got {sorted({d.metric for d in diffs})})")
        scale = 100.0 if metric in OUTCOMES else 1.0
        rows = np.arange(len(diffs))[::-1]  # the first difference on top
        for y, d in zip(rows, diffs, strict=True):
            colour = DECIDED_COLOURS[d.side]
            ax.hlines(y, scale * d.low, scale * d.high, color=colour, lw=2.5)
            ax.plot(scale * d.diff, y, "o", color=colour, ms=5)
        ax.axvline(0.0, color="0.2", lw=0.8)
        ax.set_yticks(rows, [_difference_label(d) for d in diffs], fontsize=8)
        ax.set_ylim(-0.7, len(diffs) - 0.3)
        ax.set_xlabel(f"A - B: {METRIC_WORDS.get(metric, metric)}" + (" (points)" if metric in OUTCOMES else ""),
                      fontsize=8)
        ax.set_title(name, loc="left", fontsize=9)
        ax.grid(axis="x", alpha=0.3)
    words = {"for": "A better (the interval excludes 0)", "against": "B better (the interval excludes 0)",
             "undecided": "cannot tell (the interval holds 0)"}
    handles = [Line2D([], [], color=c, lw=2.5, marker="o", label=words[k]) for k, c in DECIDED_COLOURS.items()]
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=8)
    fig.suptitle(title or "paired differences A - B with their 95 % intervals")
    return fig


def _difference_label(d: PairedDifference) -> str:
    """e.g. "ViT+LSTM - ConvNet (3 draws), spheres, 3-7 m/s pooled (300 pairs)"."""
    a, b = (label(p) + (f" ({n} draws)" if n > 1 else "") for p, n in ((d.a, d.draws_a), (d.b, d.draws_b)))
    speeds = f"{d.speeds[0]:g} m/s" if len(d.speeds) == 1 else f"{min(d.speeds):g}-{max(d.speeds):g} m/s pooled"
    borrowed = ", the draws' spread borrowed" if d.borrowed_sd else ""
    return f"{a} - {b}, {d.env}, {speeds} ({d.pairs} pairs{borrowed})"
