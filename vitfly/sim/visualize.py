"""Pictures of scenes and flights: top and side views with the flown path, depth frames with the
command arrow, and GIFs of whole trials. Reusable by the evaluation code.

Everything draws on matplotlib ``Figure`` objects (no pyplot, no global state) or Pillow images.
The command arrow is drawn in the image: the world-frame command is rotated into the body frame,
divided by the desired speed, and its lateral (+y = left) and vertical (+z = up) parts move the
arrow tip left and up from the image centre, as in the original project's debug view.

Example::

    result = run_episodes([scene], [5.0], ExpertPolicy(), RolloutConfig(record_depth=True))[0]
    save_figure(episode_figure(result), "runs/render/trial.png")
    write_gif(result, "runs/render/trial.gif")
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle
from PIL import Image, ImageDraw

from vitfly.atomic import atomic_path
from vitfly.sim.quadrotor import quat_wxyz_to_matrix
from vitfly.sim.rollout import EpisodeResult
from vitfly.sim.scenes import Scene

OBSTACLE_STYLE = {"facecolor": "0.75", "edgecolor": "0.35", "linewidth": 0.6}


def draw_scene(ax_top, ax_side, scene: Scene) -> None:
    """Obstacles seen from above (x, y) and from the side (x, z), world frame, metres."""
    for x, y, z, r in scene.spheres:
        ax_top.add_patch(Circle((x, y), r, **OBSTACLE_STYLE))
        ax_side.add_patch(Circle((x, z), r, **OBSTACLE_STYLE))
    for x, y, z0, z1, r in scene.cylinders:
        ax_top.add_patch(Circle((x, y), r, **OBSTACLE_STYLE))
        ax_side.add_patch(Rectangle((x - r, z0), 2 * r, z1 - z0, **OBSTACLE_STYLE))
    for x0, y0, z0, x1, y1, z1 in scene.boxes:
        ax_top.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, **OBSTACLE_STYLE))
        ax_side.add_patch(Rectangle((x0, z0), x1 - x0, z1 - z0, **OBSTACLE_STYLE))


def draw_path(ax_top, ax_side, position: np.ndarray, contact: np.ndarray | None = None, **style) -> None:
    """A flown path (T, 3) on both views; ticks in contact marked with red crosses."""
    style = {"color": "tab:blue", "lw": 1.2, **style}
    for ax, k in ((ax_top, 1), (ax_side, 2)):
        ax.plot(position[:, 0], position[:, k], **style)
        if contact is not None and contact.any():
            ax.plot(position[contact, 0], position[contact, k], "x", color="red", ms=4)


def format_views(ax_top, ax_side, x_range=(-2.0, 65.0), y_range=(-10.0, 10.0), z_range=(0.0, 10.0)) -> None:
    ax_top.set_ylabel("y (m), left +")
    ax_side.set_ylabel("z (m), up +")
    ax_side.set_xlabel("x (m), forward")
    ax_top.set_ylim(*y_range)
    ax_side.set_ylim(*z_range)
    for ax in (ax_top, ax_side):
        ax.set_xlim(*x_range)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)


def body_command(command: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """World-frame commands (T, 3) expressed in the body frame given attitudes (T, 4) (w, x, y, z)."""
    rot = quat_wxyz_to_matrix(np.asarray(quat, dtype=np.float64).reshape(-1, 4))
    return np.einsum("nji,nj->ni", rot, np.asarray(command, dtype=np.float64).reshape(-1, 3))


def arrow_tip(command_body: np.ndarray, desired_speed: float, height: int, width: int) -> tuple[float, float]:
    """(column, row) of the arrow tip for a body-frame command: left/up of the centre for +y/+z."""
    v = np.asarray(command_body, dtype=np.float64) / max(float(desired_speed), 1e-6)
    return width / 2 - v[1] * width / 3, height / 2 - v[2] * height / 3


def draw_depth(ax, depth: np.ndarray, command_body: np.ndarray | None = None, desired_speed: float = 1.0) -> None:
    """One depth frame (near = dark, far = light, as stored) with the command arrow."""
    h, w = depth.shape
    ax.imshow(depth, cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
    if command_body is not None:
        tip = arrow_tip(command_body, desired_speed, h, w)
        if np.hypot(tip[0] - w / 2, tip[1] - h / 2) > 0.5:
            ax.annotate("", xy=tip, xytext=(w / 2, h / 2), arrowprops={"arrowstyle": "->", "color": "red", "lw": 1.5})
        ax.plot(*tip, "o", color="red", ms=2.5)  # straight ahead: the arrow is just this dot
    ax.set_xticks([])
    ax.set_yticks([])


def episode_figure(result: EpisodeResult, n_frames: int = 8, title: str | None = None) -> Figure:
    """Top view, side view and (if the log holds depth) a strip of ``n_frames`` depth frames."""
    log, s = result.log, result.summary
    has_depth = log.depth is not None and len(log.depth) > 0
    fig = Figure(figsize=(12, 8.2 if has_depth else 6.2), layout="constrained")
    grid = fig.add_gridspec(3 if has_depth else 2, n_frames, height_ratios=(2, 1, 0.9)[: 3 if has_depth else 2])
    ax_top = fig.add_subplot(grid[0, :])
    ax_side = fig.add_subplot(grid[1, :])
    draw_scene(ax_top, ax_side, result.scene)
    draw_path(ax_top, ax_side, log.position, log.contact)
    format_views(ax_top, ax_side)
    ax_top.set_title(
        title
        or f"{s.env}/{s.preset} seed {s.seed}, {s.desired_speed:g} m/s: {s.end_reason}, "
        f"{s.n_collisions} collision(s), {s.time_in_contact_s:.2f} s in contact"
    )
    if has_depth:
        picks = np.linspace(0, len(log) - 1, n_frames).round().astype(int)
        cmd_body = body_command(log.command[picks], log.quat[picks])
        for j, (k, cb) in enumerate(zip(picks, cmd_body, strict=True)):
            ax = fig.add_subplot(grid[2, j])
            draw_depth(ax, log.depth[k], cb, s.desired_speed)
            ax.set_title(f"t={log.time[k]:.1f}s x={log.position[k, 0]:.0f}m", fontsize=8)
            ax_top.plot(log.position[k, 0], log.position[k, 1], "o", color="tab:orange", ms=3)
            ax_side.plot(log.position[k, 0], log.position[k, 2], "o", color="tab:orange", ms=3)
    return fig


def save_figure(fig: Figure, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Write a figure to PNG atomically (temp file + rename)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return path


def depth_frame_image(
    depth: np.ndarray,
    command_body: np.ndarray | None = None,
    desired_speed: float = 1.0,
    scale: int = 4,
    text: str = "",
) -> Image.Image:
    """A depth frame as an RGB Pillow image, ``scale`` times larger, with the command arrow and a caption."""
    h, w = depth.shape
    grey = np.clip(np.asarray(depth) * 255.0, 0, 255).astype(np.uint8)
    img = Image.fromarray(grey, mode="L").resize((w * scale, h * scale), Image.NEAREST).convert("RGB")
    draw = ImageDraw.Draw(img)
    if command_body is not None:
        tip_c, tip_r = arrow_tip(command_body, desired_speed, h, w)
        c0, r0, c1, r1 = w / 2 * scale, h / 2 * scale, tip_c * scale, tip_r * scale
        draw.line([(c0, r0), (c1, r1)], fill=(255, 0, 0), width=3)
        draw.ellipse([c1 - 4, r1 - 4, c1 + 4, r1 + 4], fill=(255, 0, 0))
    if text:
        draw.text((4, 2), text, fill=(255, 255, 0))
    return img


def write_gif(result: EpisodeResult, path: str | os.PathLike, stride: int = 1, scale: int = 4) -> Path:
    """A GIF of the whole trial: every ``stride``-th depth frame with its command arrow, real time."""
    log, s = result.log, result.summary
    if log.depth is None or len(log.depth) == 0:
        raise ValueError("write_gif needs an episode flown with RolloutConfig(record_depth=True)")
    picks = np.arange(0, len(log), max(1, int(stride)))
    cmd_body = body_command(log.command[picks], log.quat[picks])
    frames = [
        depth_frame_image(
            log.depth[k],
            cb,
            s.desired_speed,
            scale,
            f"t={log.time[k]:4.1f}s x={log.position[k, 0]:4.1f}m" + (" CONTACT" if log.contact[k] else ""),
        )
        for k, cb in zip(picks, cmd_body, strict=True)
    ]
    dt_ms = 1000.0 * float(np.median(np.diff(log.time))) * max(1, int(stride)) if len(log) > 1 else 33.0
    return _save_gif(frames, Path(path), int(round(dt_ms)))


def _save_gif(frames: Sequence[Image.Image], path: Path, duration_ms: int) -> Path:
    with atomic_path(path) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=list(frames[1:]), duration=duration_ms, loop=0)
    return path
