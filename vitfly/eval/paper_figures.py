"""The paper's results figures, from summary rows and trial records (``vitfly reproduce`` draws them all).

- ``collision_metrics_figure``: per environment, collisions per trial, time in collision per obstacle (the
  paper's definition) and success rate (no collision) vs speed (the paper's Spheres/Trees figures);
- ``command_figure``: commanded acceleration and energy cost vs speed, one column per environment
  (the paper's acceleration/energy figure);
- ``mean_paths_figure``: top-down and side views of each policy's mean path over repeated trials of one
  scene with a band of +-0.1 standard deviations (the paper's path-distribution figure);
- ``mean_paths_3d_figure``: the same mean paths in 3D.

Figures are ``matplotlib.figure.Figure`` objects saved atomically (no pyplot state).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from vitfly.eval.plots import _save, plot_vs_speed, policy_colours
from vitfly.eval.records import TrialRecord
from vitfly.eval.repeats import mean_path
from vitfly.sim.visualize import draw_scene, format_views

BAND_SIGMA = 0.1  # the paper's band: mean +- 0.1 sigma
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
