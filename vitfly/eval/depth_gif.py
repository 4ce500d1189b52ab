"""A GIF of one trial as the policy saw it: depth frames with the velocity command drawn as an arrow.

The arrow shows the command's sideways and vertical parts in the camera's view (paper Fig. 1):
the world-frame command is rotated into the body frame (quaternion (w, x, y, z), body-to-world);
body +y (left) points to the image's left, body +z (up) to the image's top, and a command at the
full desired speed sideways reaches the image border.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import colormaps
from PIL import Image, ImageDraw

from vitfly.eval.atomic import atomic_path


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) (w, x, y, z)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def arrow_offsets_px(command_world, quat, desired_speed: float, half_width_px: float) -> np.ndarray:
    """(T, 2) image offsets (right, down) in pixels of the command arrow from the image centre."""
    body = np.einsum("tji,tj->ti", quat_to_matrix(quat), np.asarray(command_world, dtype=np.float64))  # R^T v
    scale = half_width_px / max(float(desired_speed), 1e-6)
    return np.stack([-body[:, 1], -body[:, 2]], axis=1) * scale


def depth_frames_rgb(depth: np.ndarray, upscale: int = 4) -> np.ndarray:
    """(T, H, W) depth in [0, 1] -> (T, H*upscale, W*upscale, 3) uint8 (near = dark; 0 'no reading' = black)."""
    rgb = (colormaps["magma"](np.clip(depth, 0, 1))[..., :3] * 255).astype(np.uint8)
    rgb[depth <= 0] = 0
    return rgb.repeat(upscale, axis=1).repeat(upscale, axis=2)


def write_depth_gif(path: str | Path, depth, command_world, quat, desired_speed: float, time_s=None,
                    contact=None, upscale: int = 4, max_frames: int = 300, title: str = "") -> Path:
    """Write the GIF atomically; long trials are subsampled to ``max_frames`` frames."""
    depth = np.asarray(depth, dtype=np.float32)
    n = len(depth)
    stride = max(1, int(np.ceil(n / max_frames)))
    keep = np.arange(0, n, stride)
    images = depth_frames_rgb(depth[keep], upscale)
    h, w = images.shape[1:3]
    offsets = arrow_offsets_px(np.asarray(command_world)[keep], np.asarray(quat)[keep], desired_speed, w / 2)
    tick_s = float(np.median(np.diff(time_s))) if time_s is not None and n > 1 else 1 / 30.0
    times = np.asarray(time_s)[keep] if time_s is not None else keep * tick_s
    hits = np.asarray(contact, dtype=bool)[keep] if contact is not None else np.zeros(len(keep), bool)
    frames = []
    cx, cy = w / 2, h / 2
    for img, (dx, dy), t, hit in zip(images, offsets, times, hits, strict=True):
        frame = Image.fromarray(img)
        draw = ImageDraw.Draw(frame)
        tip = (cx + dx, cy + dy)
        draw.line([(cx, cy), tip], fill=(255, 40, 40), width=3)
        length = float(np.hypot(dx, dy))
        if length > 4:
            ux, uy = dx / length, dy / length
            head = [tip, (tip[0] - 10 * ux + 5 * uy, tip[1] - 10 * uy - 5 * ux),
                    (tip[0] - 10 * ux - 5 * uy, tip[1] - 10 * uy + 5 * ux)]
            draw.polygon(head, fill=(255, 40, 40))
        draw.ellipse([cx - 3, cy - 3, cx + 3, cy + 3], outline=(255, 255, 255))
        draw.rectangle([0, 0, w, 14], fill=(0, 0, 0))
        draw.text((4, 2), f"{title}  t={t:5.2f}s", fill=(255, 255, 255))
        if hit:
            draw.rectangle([0, h - 16, 80, h], fill=(0, 0, 0))
            draw.text((4, h - 14), "COLLISION", fill=(255, 60, 60))
        frames.append(frame.convert("P", palette=Image.Palette.ADAPTIVE, colors=128))
    path = Path(path)
    with atomic_path(path) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:],
                       duration=int(round(1000 * stride * tick_s)), loop=0)
    return path
