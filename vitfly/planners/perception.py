"""Depth frame -> world-frame obstacle points, with the simulator camera's own rays (the inverse of rendering)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from vitfly.sim.camera import CameraConfig, DepthCamera


@lru_cache(maxsize=8)
def _body_rays(camera: CameraConfig) -> np.ndarray:
    # (H*W, 3) rays with a unit forward component: planar depth times the ray is the body-frame offset
    return DepthCamera(camera).ray_directions_body.reshape(-1, 3)


def depth_to_world_points(
    depth_norm: np.ndarray, position_m, rotation_body_to_world: np.ndarray, camera: CameraConfig, stride: int = 1
) -> np.ndarray:
    """World-frame points (M, 3) m of the valid pixels of one normalised depth frame.

    depth_norm: (H, W) in [0, 1] = planar depth / ``camera.max_range_m``; 0 ("no reading") and readings at
    or beyond the range (1: nothing hit) are dropped. position_m: (3,) the body origin, world frame;
    rotation_body_to_world: (3, 3). ``stride`` keeps every stride-th row and column (fewer points, coarser map).
    """
    depth_norm = np.asarray(depth_norm, dtype=np.float64)
    if depth_norm.shape != (camera.height, camera.width):
        raise ValueError(f"depth frame of shape {depth_norm.shape}; the camera gives ({camera.height}, {camera.width})")
    rays = _body_rays(camera).reshape(camera.height, camera.width, 3)[::stride, ::stride].reshape(-1, 3)
    flat = depth_norm[::stride, ::stride].reshape(-1)
    # 1 - 1e-6: float32 storage of "at the range" may read a hair below 1
    valid = (flat > 0.0) & (flat < 1.0 - 1e-6)
    mount = np.asarray(camera.mount_offset_m, dtype=np.float64)
    points_body = mount + (flat[valid] * camera.max_range_m)[:, None] * rays[valid]
    rot = np.asarray(rotation_body_to_world, dtype=np.float64).reshape(3, 3)
    return points_body @ rot.T + np.asarray(position_m, dtype=np.float64).reshape(3)
