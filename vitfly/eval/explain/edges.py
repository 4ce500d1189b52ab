"""Obstacle edges in the depth image: where a model's map should sit if it "looks at obstacle edges".

An edge pixel is a pixel on an obstacle's visible surface with a 4-neighbour whose depth is more than
``jump_m`` farther (a depth discontinuity whose near side is an obstacle: silhouettes against the
background, the ground or a farther obstacle). Depth beyond the camera range counts as the range
itself, as the network sees it (it reads 1). The mask is then widened by ``width_px`` pixels
(3 x 3 dilation), because every map here comes from a coarser grid than the image.

``scene_edge_masks`` computes them exactly: it re-renders planar metric depth from the scene at the
logged poses, once with and once without the ground plane (ground-only jumps near the horizon are not
obstacle edges), and checks that the re-render reproduces the frames the models saw.
``depth_edge_masks`` is the fallback when no scene is known (a replayed dataset of unknown origin):
jumps in the frames' own depth, without the obstacle/ground distinction.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import binary_dilation

from vitfly.sim.camera import CameraConfig, DepthCamera
from vitfly.sim.quadrotor import quat_wxyz_to_matrix
from vitfly.sim.scenes import Scene

# re-rendered frames agree with the recorded ones when at most this share of pixels differs by more
# than one uint8 step (float32 poses in datasets move a silhouette pixel now and then)
MAX_MISMATCH_SHARE = 0.01


@dataclass(frozen=True)
class EdgeConfig:
    """How obstacle edges are found (metres, pixels)."""

    jump_m: float = 0.5  # depth discontinuity that makes an edge
    width_px: int = 1  # dilation of the one-pixel contour (0: the contour itself)


DEFAULT_EDGES = EdgeConfig()


def _near_side_of_jump(depth_m: np.ndarray, jump_m: float) -> np.ndarray:
    """(H, W) bool: pixels with a 4-neighbour more than ``jump_m`` farther."""
    near = np.zeros(depth_m.shape, dtype=bool)
    dv = depth_m[1:, :] - depth_m[:-1, :]  # row below minus row above
    dh = depth_m[:, 1:] - depth_m[:, :-1]
    near[:-1, :] |= dv > jump_m
    near[1:, :] |= -dv > jump_m
    near[:, :-1] |= dh > jump_m
    near[:, 1:] |= -dh > jump_m
    return near


def _widen(mask: np.ndarray, width_px: int) -> np.ndarray:
    return binary_dilation(mask, np.ones((3, 3), bool), iterations=width_px) if width_px > 0 and mask.any() else mask


def obstacle_edge_mask(
    depth_m: np.ndarray, obstacle_depth_m: np.ndarray, max_range_m: float, config: EdgeConfig = DEFAULT_EDGES
) -> np.ndarray:
    """(H, W) bool edge mask from planar metric depth of the whole view and of the obstacles alone.

    depth_m: everything the camera sees (m, ``inf`` for nothing within range); obstacle_depth_m: the
    same view without the ground (``inf`` off the obstacles).
    """
    seen = np.minimum(depth_m, max_range_m)
    on_obstacle = np.isfinite(obstacle_depth_m) & (obstacle_depth_m <= depth_m) & (obstacle_depth_m <= max_range_m)
    return _widen(_near_side_of_jump(seen, config.jump_m) & on_obstacle, config.width_px)


def depth_edge_masks(depth: np.ndarray, max_range_m: float, config: EdgeConfig = DEFAULT_EDGES) -> np.ndarray:
    """(T, H, W) bool edges from normalised frames (T, H, W) alone: near sides of depth jumps, ground included."""
    out = np.zeros(depth.shape, dtype=bool)
    for t, frame in enumerate(np.asarray(depth, dtype=np.float64)):
        metric = frame * max_range_m
        out[t] = _widen(_near_side_of_jump(metric, config.jump_m) & (frame < 1.0), config.width_px)
    return out


def scene_edge_masks(
    scene: Scene,
    camera: CameraConfig,
    position: np.ndarray,
    quat: np.ndarray,
    recorded_depth: np.ndarray | None = None,
    config: EdgeConfig = DEFAULT_EDGES,
) -> tuple[np.ndarray, float]:
    """Exact edge masks (T, H, W) of a trial, and the share of pixels where the re-render disagrees.

    position: (T, 3) camera positions, world frame (m); quat: (T, 4) body-to-world (w, x, y, z).
    ``recorded_depth`` (T, H, W) normalised: the frames the models saw; the returned share is the
    fraction of pixels whose noise-free re-render differs from them by more than one uint8 step
    (0.0 when nothing is given, NaN when the camera adds noise or dropout and no comparison is fair).
    """
    full = DepthCamera(replace(camera, noise_std_m=0.0, dropout_prob=0.0))
    obstacles_only = DepthCamera(replace(camera, noise_std_m=0.0, dropout_prob=0.0, render_ground=False))
    rotations = quat_wxyz_to_matrix(np.asarray(quat, dtype=np.float64).reshape(-1, 4))
    masks = np.zeros((len(rotations), camera.height, camera.width), dtype=bool)
    mismatched = 0
    for t, (p, rot) in enumerate(zip(np.asarray(position, dtype=np.float64), rotations, strict=True)):
        depth_m = full.metric_depth(scene, p, rot)
        masks[t] = obstacle_edge_mask(depth_m, obstacles_only.metric_depth(scene, p, rot), camera.max_range_m, config)
        if recorded_depth is not None:
            rendered = np.minimum(depth_m / camera.max_range_m, 1.0)
            mismatched += int(np.count_nonzero(np.abs(rendered - recorded_depth[t]) > 1.0 / 255.0 + 1e-6))
    if recorded_depth is None:
        return masks, 0.0
    if camera.noise_std_m > 0.0 or camera.dropout_prob > 0.0:
        return masks, float("nan")
    return masks, mismatched / max(masks.size, 1)
