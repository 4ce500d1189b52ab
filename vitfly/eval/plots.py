"""The evaluation plots a reader of the paper expects, drawn from summary rows and trial records.

- ``rates_vs_speed.png``: collisions per trial and success rate vs speed, one line per policy,
  one column per environment (the paper's collision-rate figure and its success-rate supplement);
  success twice, each panel naming its definition: the paper's (no collision), then the strict one
  (goal reached and no collision);
- ``time_in_collision_vs_speed.png``: time in contact per collision vs speed, as the paper plots it
  (0 for trials without a collision, mean over all trials), then over colliding trials only;
- ``energy_vs_speed.png``: energy cost and commanded acceleration vs speed;
- ``paths_<env>.png``: top-down (x-y) and side (x-z) views of the paths flown in one scene,
  all repeats, all policies, over the scene's obstacles.

Figures are built with ``matplotlib.figure.Figure`` (no pyplot state) and saved atomically.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from vitfly.atomic import atomic_path
from vitfly.eval.records import TrialRecord
from vitfly.sim.visualize import draw_path, draw_scene, format_views

FIXED_COLOURS = {"expert": "black", "straight": "0.55"}
PALETTE = ("tab:green", "tab:blue", "tab:red", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive",
           "tab:cyan")


def policy_colours(policies: Sequence[str]) -> dict[str, str]:
    """A stable colour per policy: expert black, straight grey, learned policies from the palette."""
    learned = sorted(p for p in set(policies) if p not in FIXED_COLOURS)
    colours = {p: PALETTE[i % len(PALETTE)] for i, p in enumerate(learned)}
    colours.update({p: c for p, c in FIXED_COLOURS.items() if p in policies})
    return colours


def _save(fig: Figure, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    return path


def _series(rows: Sequence[dict], env: str, policy: str, column: str) -> tuple[np.ndarray, np.ndarray]:
    sel = sorted((r for r in rows if r["env"] == env and r["policy"] == policy), key=lambda r: r["speed"])
    return np.array([r["speed"] for r in sel], float), np.array([r[column] for r in sel], float)


def plot_vs_speed(rows: Sequence[dict], panels: Sequence[tuple[str, str, bool]], path: str | Path,
                  title: str = "") -> Path:
    """One row of axes per panel (column stem or rate column, y label, as percent), one column per env.

    Stems plot ``<stem>_mean`` with ``<stem>_std`` error bars; ``*_rate`` columns plot the rate itself.
    """
    envs = sorted({r["env"] for r in rows})
    policies = sorted({r["policy"] for r in rows})
    colours = policy_colours(policies)
    fig = Figure(figsize=(4.2 * len(envs), 3.0 * len(panels)), layout="constrained")
    axes = fig.subplots(len(panels), len(envs), squeeze=False)
    for j, env in enumerate(envs):
        for i, (column, ylabel, percent) in enumerate(panels):
            ax = axes[i][j]
            for p in policies:
                if column.endswith("_rate"):
                    x, y = _series(rows, env, p, column)
                    err = None
                else:
                    x, y = _series(rows, env, p, f"{column}_mean")
                    std = _series(rows, env, p, f"{column}_std")[1]
                    err = np.stack([np.minimum(std, np.maximum(y, 0)), std])  # the lower bar stops at 0
                if len(x) == 0 or not np.isfinite(y).any():
                    continue
                scale = 100.0 if percent else 1.0
                ax.errorbar(x, y * scale, yerr=None if err is None else err * scale, marker="o", capsize=3,
                            color=colours[p], label=p, lw=1.5, ms=4)
            ax.set_xlabel("desired speed (m/s)")
            ax.set_ylabel(ylabel)
            if percent:
                ax.set_ylim(-5, 105)
            ax.grid(alpha=0.3)
            if i == 0:
                ax.set_title(env)
    handles, labels = axes[0][0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 4))
    if title:
        fig.suptitle(title)
    return _save(fig, Path(path))


def plot_paths(records: Sequence[TrialRecord], path: str | Path, scene=None, title: str = "") -> Path:
    """Top-down and side views of every given record's path (meant: repeats of one scene), by policy.

    ``scene`` (optional) has ``spheres`` (K, 4), ``cylinders`` (K, 5), ``boxes`` (K, 6) arrays as in
    ``vitfly.sim.scenes.Scene``; collisions are marked with red crosses.
    """
    colours = policy_colours([r.policy for r in records])
    # equal metres on both axes; the panel heights follow the y (20 m) and z (10 m) ranges
    fig = Figure(figsize=(11, 5.8), layout="constrained")
    ax_top, ax_side = fig.subplots(2, 1, height_ratios=(2, 1))
    if scene is not None:
        draw_scene(ax_top, ax_side, scene)
    seen: set[str] = set()
    for rec in records:
        arr = rec.path_arrays()
        label = rec.policy if rec.policy not in seen else None
        seen.add(rec.policy)
        draw_path(ax_top, ax_side, arr["position"], arr["contact"], color=colours[rec.policy], lw=1.3,
                  alpha=0.85, zorder=3, label=label)  # above the opaque obstacles
    format_views(ax_top, ax_side)
    ax_top.set_title(title or "paths over repeated trials of one scene (top-down, then side)")
    ax_top.legend(loc="upper left", fontsize=8)
    return _save(fig, Path(path))


def scene_for_paths(records: Sequence[TrialRecord], env: str) -> tuple[int | None, list[TrialRecord]]:
    """The scene of ``env`` flown most often (ties: the lowest trial index) and its records."""
    recs = [r for r in records if r.env == env]
    if not recs:
        return None, []
    counts: dict[int, int] = {}
    first: dict[int, int] = {}
    for r in recs:
        counts[r.scene_seed] = counts.get(r.scene_seed, 0) + 1
        first.setdefault(r.scene_seed, r.trial)
        first[r.scene_seed] = min(first[r.scene_seed], r.trial)
    seed = max(counts, key=lambda s: (counts[s], -first[s]))
    return seed, [r for r in recs if r.scene_seed == seed]


def write_standard_plots(out_dir: str | Path, rows: Sequence[dict], records: Sequence[TrialRecord],
                         scene_loader=None) -> dict[str, Path]:
    """All summary plots into ``out_dir``; ``scene_loader(env, preset, seed)`` draws obstacles under paths.

    ``paths_<env>.png`` only where the records hold their paths (not those of an outcomes file)."""
    out = Path(out_dir)
    written = {
        "rates_vs_speed": plot_vs_speed(
            rows, [("collisions", "collisions per trial", False),
                   ("success_paper_rate", "success (%)\npaper: no collision", True),
                   ("success_strict_rate", "success (%)\nstrict: goal + no collision", True)],
            out / "rates_vs_speed.png", "collision and success rates"),
        "time_in_collision_vs_speed": plot_vs_speed(
            rows, [("time_in_collision", "time in collision (s)\nper collision, 0 w/o one (paper)", False),
                   ("time_in_collision_colliding", "time in collision (s)\ncolliding trials only", False)],
            out / "time_in_collision_vs_speed.png", "time in contact per collision"),
        "energy_vs_speed": plot_vs_speed(
            rows, [("energy_cost", "energy cost (1/s²)", False), ("cmd_acc", "commanded acc. (1/s²)", False)],
            out / "energy_vs_speed.png", "command characteristics"),
    }
    with_paths = [r for r in records if r.has_path]
    for env in sorted({r.env for r in with_paths}):
        seed, recs = scene_for_paths(with_paths, env)
        scene = scene_loader(env, recs[0].preset, seed) if scene_loader is not None else None
        written[f"paths_{env}"] = plot_paths(
            recs, out / f"paths_{env}.png", scene,
            title=f"{env}: scene seed {seed}, {len(recs)} trial(s) (top-down, then side)")
    return written
