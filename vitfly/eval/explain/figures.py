"""Depth frames with a map overlaid: PNG strips of chosen ticks and GIFs of whole trials.

A map is shown relative to its own maximum at each tick (what it highlights, not how strongly), as a
colour overlay whose opacity grows with the value, on the grey depth frame (near = dark); the red arrow
is the command of whoever is shown: the pilot on the reference row, the model itself on a model's row
(its output deployed as in flight: x clipped, normalised, times the desired speed). The reference
row/panel shows the obstacle edges the edge metrics use, in cyan. Built on ``vitfly.sim.visualize``
(``draw_depth``, ``depth_frame_image``, ``arrow_tip``, ``body_command``); files are written atomically.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure
from PIL import Image, ImageDraw

from vitfly.atomic import atomic_path
from vitfly.sim.visualize import arrow_tip, depth_frame_image, draw_depth

CMAP = colormaps["turbo"]
MAX_ALPHA = 0.65
EDGE_RGB = (0.0, 1.0, 1.0)


@dataclass
class MapRow:
    """One row of a strip / one panel of a GIF: a map over the trial and whose command goes with it.

    maps: (T, 60, 90) >= 0, or None for the reference row (depth and edges only); command_body: (T, 3)
    body-frame commands (m/s) drawn as the arrow, or None.
    """

    label: str
    maps: np.ndarray | None
    command_body: np.ndarray | None


def relative(m: np.ndarray) -> np.ndarray:
    """A map divided by its maximum (zeros stay zeros)."""
    peak = float(np.max(m))
    return m / peak if peak > 0 else np.zeros_like(m)


def overlay_rgba(m: np.ndarray) -> np.ndarray:
    """(H, W, 4) colour overlay of one map: colour and opacity from the map relative to its maximum."""
    rel = relative(np.asarray(m, dtype=np.float64))
    rgba = CMAP(rel)
    rgba[..., 3] = MAX_ALPHA * rel
    return rgba


def edges_rgba(edges: np.ndarray) -> np.ndarray:
    rgba = np.zeros((*edges.shape, 4))
    rgba[..., :3] = EDGE_RGB
    rgba[..., 3] = 0.8 * edges
    return rgba


def strip_figure(
    depth: np.ndarray,
    rows: Sequence[MapRow],
    ticks: Sequence[int],
    time: np.ndarray,
    desired_speed: np.ndarray,
    edges: np.ndarray | None,
    reference: MapRow,
    title: str = "",
) -> Figure:
    """Reference row (depth, edges, pilot's arrow) then one row per map, one column per chosen tick."""
    all_rows = [reference, *rows]
    n_cols = len(ticks)
    fig = Figure(figsize=(1.55 * n_cols + 1.4, 1.12 * len(all_rows) + 0.5), layout="constrained")
    axes = fig.subplots(len(all_rows), n_cols, squeeze=False)
    for i, row in enumerate(all_rows):
        for j, k in enumerate(ticks):
            ax = axes[i][j]
            cmd = None if row.command_body is None else row.command_body[k]
            draw_depth(ax, depth[k], cmd, float(desired_speed[k]))
            if row.maps is not None:
                ax.imshow(overlay_rgba(row.maps[k]), interpolation="nearest")
            elif edges is not None:
                ax.imshow(edges_rgba(edges[k]), interpolation="nearest")
            if i == 0:
                ax.set_title(f"t={time[k]:.1f}s", fontsize=7)
            if j == 0:
                ax.set_ylabel(row.label, fontsize=6.5, rotation=0, ha="right", va="center", wrap=True)
    if title:
        fig.suptitle(title, fontsize=8)
    return fig


def panel_image(
    depth: np.ndarray,
    m: np.ndarray | None,
    edges: np.ndarray | None,
    command_body: np.ndarray | None,
    desired_speed: float,
    scale: int,
    text: str,
) -> Image.Image:
    """One GIF panel: the depth frame ``scale`` x larger, the map (or the edges) blended in, arrow, caption."""
    base = np.asarray(depth_frame_image(depth, None, desired_speed, scale), dtype=np.float64) / 255.0
    rgba = overlay_rgba(m) if m is not None else (edges_rgba(edges) if edges is not None else None)
    if rgba is not None:
        big = np.repeat(np.repeat(rgba, scale, axis=0), scale, axis=1)
        alpha = big[..., 3:]
        base = base * (1.0 - alpha) + big[..., :3] * alpha
    img = Image.fromarray(np.clip(base * 255.0 + 0.5, 0, 255).astype(np.uint8), mode="RGB")
    draw = ImageDraw.Draw(img)
    if command_body is not None:
        h, w = depth.shape
        tip_c, tip_r = arrow_tip(command_body, desired_speed, h, w)
        c0, r0, c1, r1 = w / 2 * scale, h / 2 * scale, tip_c * scale, tip_r * scale
        draw.line([(c0, r0), (c1, r1)], fill=(255, 0, 0), width=2)
        draw.ellipse([c1 - 3, r1 - 3, c1 + 3, r1 + 3], fill=(255, 0, 0))
    if text:
        draw.text((3, 2), text, fill=(255, 255, 255))
    return img


def write_gif(
    path: str | Path,
    depth: np.ndarray,
    panels: Sequence[MapRow],
    time: np.ndarray,
    desired_speed: np.ndarray,
    edges: np.ndarray | None,
    stride: int = 1,
    scale: int = 3,
) -> Path:
    """A GIF of the whole trial, panels side by side (every ``stride``-th tick), at real-time pace."""
    picks = np.arange(0, len(depth), max(1, int(stride)))
    frames = []
    for k in picks:
        images = [
            panel_image(depth[k], None if p.maps is None else p.maps[k], edges[k] if edges is not None else None,
                        None if p.command_body is None else p.command_body[k], float(desired_speed[k]), scale,
                        f"{p.label}  t={time[k]:.1f}s")
            for p in panels
        ]  # fmt: skip
        strip = Image.new("RGB", (sum(im.width + 2 for im in images) - 2, images[0].height), (255, 255, 255))
        x = 0
        for im in images:
            strip.paste(im, (x, 0))
            x += im.width + 2
        frames.append(strip)
    dt_ms = 1000.0 * float(np.median(np.diff(time))) * max(1, int(stride)) if len(time) > 1 else 33.0
    path = Path(path)
    with atomic_path(path) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], duration=int(round(dt_ms)), loop=0)
    return path
