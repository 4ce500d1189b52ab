"""The depth camera of :mod:`vitfly.sim.camera` for E scenes at once: analytic ray casting in torch.

The same rays (one per output pixel, every :data:`vitfly.sim.camera.CAMERA_PRESETS` geometry and any
:class:`~vitfly.sim.camera.CameraConfig`), the same planar depth, normalisation, maximum range, ground
plane, noise and dropout. Each visible shape of every scene is cast only against the pixels of its
projected window (the numpy camera's exact bounds), all (shape, pixel) pairs of all scenes in one pass
per shape kind, and the nearest hit per pixel is kept by one scatter-min.

Differentiable: the depth of a pixel is a smooth function of the camera pose (position, rotation) and
of the parameters of the obstacle it sees (``torch.autograd`` through the intersection formulas and the
scatter-min); the windows and the choice of the nearest surface are discrete and carry no gradient.

Example::

    camera = BatchedCamera(CameraConfig(), device="cpu", dtype=torch.float64)
    depth = camera.render(batch, position, rotation)     # (E, 60, 90) in [0, 1]
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from vitfly.sim.batched.scenes import SceneBatch
from vitfly.sim.camera import CameraConfig, DepthCamera

_BIG = 1e6  # tangent-space bound of a shape that may cover the whole image


def _where_safe(cond: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``x`` where ``cond`` else 1: a denominator or square-root argument whose unused entries stay harmless."""
    return torch.where(cond, x, torch.ones_like(x))


def pixel_windows(u_lo, u_hi, v_lo, v_hi, tan_h: float, tan_v: float, height: int, width: int):
    """Row and column ranges [r0, r1) x [c0, c1) whose pixel centres may fall in tangent-space boxes.

    Tangent-space bounds (K,) each (u = y / x left, v = z / x up, body frame); the arithmetic of the
    numpy camera's ``_pixel_windows`` (col = (1 - u / tan_h) W / 2 - 0.5, floor / ceil + 1, clipped).
    """
    c0 = torch.floor((1.0 - u_hi / tan_h) * width / 2 - 0.5).clamp(0, width)
    c1 = (torch.ceil((1.0 - u_lo / tan_h) * width / 2 - 0.5) + 1).clamp(0, width)
    r0 = torch.floor((1.0 - v_hi / tan_v) * height / 2 - 0.5).clamp(0, height)
    r1 = (torch.ceil((1.0 - v_lo / tan_v) * height / 2 - 0.5) + 1).clamp(0, height)
    return r0.long(), r1.long(), c0.long(), c1.long()


def sphere_windows(cam, radius, mask, max_range_m: float, frustum, tan_h: float, tan_v: float, height: int,
                   width: int):
    """Which spheres to cast and their pixel windows: ``(keep, r0, r1, c0, c1)``, each (E, K).

    cam (E, K, 3) centres in the camera frame, radius (E, K) m, mask (E, K) the spheres to consider.
    Kept: planar depth possibly within the range (at least cx - r) and not wholly outside a frustum side
    plane. Windows: exact image bounds from the tangent planes through the camera for spheres wholly in
    front; a sphere reaching behind the image plane may cover the whole image (the numpy camera's bounds).
    """
    cx, cy, cz = cam.unbind(-1)
    keep = mask & (cx - radius < max_range_m)
    # plane by plane, not a (K, 4) product: elementwise, it compiles to one vectorised loop
    for i in range(frustum.shape[0]):
        keep = keep & (cx * frustum[i, 0] + cy * frustum[i, 1] + cz * frustum[i, 2] > -radius)
    r2 = radius * radius
    front = cx > radius
    k = torch.where(front, cx * cx - r2, torch.ones_like(cx))
    hu = radius * torch.sqrt((cx * cx + cy * cy - r2).clamp(min=0.0))
    hv = radius * torch.sqrt((cx * cx + cz * cz - r2).clamp(min=0.0))
    big = torch.full_like(cx, _BIG)
    windows = pixel_windows(torch.where(front, (cx * cy - hu) / k, -big), torch.where(front, (cx * cy + hu) / k, big),
                            torch.where(front, (cx * cz - hv) / k, -big), torch.where(front, (cx * cz + hv) / k, big),
                            tan_h, tan_v, height, width)
    return (keep, *windows)


def window_pairs(r0, r1, c0, c1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every (shape, pixel-in-window) pair, shape by shape: ``(shape (P,), start (K,), cols (K,))``.

    Pair p belongs to shape ``shape[p]`` and is pixel ``p - start[shape]`` of its window, counted
    row-major over ``cols`` columns (see :func:`pair_pixels`).
    """
    cols = (c1 - c0).clamp(min=0)
    count = (r1 - r0).clamp(min=0) * cols
    shape = torch.repeat_interleave(count, output_size=int(count.sum()))
    return shape, torch.cumsum(count, 0) - count, cols.clamp(min=1)


def pair_pixels(shape, start, r0, c0, cols) -> tuple[torch.Tensor, torch.Tensor]:
    """Image row and column of each pair of :func:`window_pairs`."""
    offset = torch.arange(shape.shape[0], device=shape.device) - start[shape]
    n = cols[shape]
    # offset // n in float64 (exact for these small integers, and much cheaper than integer division)
    row = torch.floor((offset.double() + 0.5) / n.double()).long()
    return r0[shape] + row, c0[shape] + offset - row * n


def pixel_rays(row, col, tan_h: float, tan_v: float, height: int, width: int, dtype: torch.dtype):
    """Body-frame ray (1, u, v) of pixel (row, col), u left and v up: the numpy camera's formula, op for op
    (so the same values in float64); computed, not gathered, which is cheaper per pair."""
    u = tan_h * (1.0 - 2.0 * (col.to(dtype) + 0.5) / width)
    v = tan_v * (1.0 - 2.0 * (row.to(dtype) + 0.5) / height)
    return u, v


def _world_ray(rot, u, v, i: int) -> torch.Tensor:
    """Component i of the world-frame ray R (1, u, v), rot (P, 3, 3) (as the numpy camera sums it)."""
    return rot[:, i, 0] + rot[:, i, 1] * u + rot[:, i, 2] * v


def sphere_pair_depth(pairs, env, cam, r2, tan_h: float, tan_v: float, height: int, width: int):
    """(flat index into the (E H W) buffer, planar depth in m) of every (sphere, pixel) pair; +inf where the
    ray misses (or hits behind).

    pairs: (shape, start, r0, c0, cols) of :func:`window_pairs` and the windows; env (K,) each sphere's
    scene; cam (K, 3) sphere centres in the camera frame (x forward, y left, z up); r2 (K,) squared
    radii; the camera's tangents and size give the pixel rays (:func:`pixel_rays`). Outside a sphere the
    near intersection, inside it the far side (the exit point), as the numpy camera.
    """
    shape = pairs[0]
    row, col = pair_pixels(*pairs)
    uu, vv = pixel_rays(row, col, tan_h, tan_v, height, width, cam.dtype)
    aa = 1.0 + uu * uu + vv * vv  # squared ray length
    cx, cy, cz = cam[shape].unbind(-1)
    b = cx + cy * uu + cz * vv  # ray . centre
    c_sphere = (cam * cam).sum(-1) - r2  # > 0 when the camera is outside the sphere
    c = c_sphere[shape]
    disc = b * b - aa * c
    hit = disc >= 0
    root = torch.sqrt(_where_safe(disc > 0, disc)) * (disc > 0)
    t = (b - torch.where(c > 0, root, -root)) / aa
    return (env[shape] * height + row) * width + col, torch.where(hit & (t > 0), t, torch.inf)


def cylinder_pair_depth(pairs, env, cyl, origin, rot, tan_h: float, tan_v: float, height: int, width: int):
    """(flat index, planar depth in m) of every (vertical cylinder, pixel) pair (side wall and caps), +inf
    for none. cyl (K, 5) [x, y, z_bottom, z_top, radius]; origin (K, 3) the camera centre and rot (K, 3, 3)
    the body-to-world rotation of each cylinder's scene. Solved in the world frame, as the numpy camera.
    """
    shape = pairs[0]
    row, col = pair_pixels(*pairs)
    u, v = pixel_rays(row, col, tan_h, tan_v, height, width, cyl.dtype)
    r_pair = rot[shape]
    dx, dy, dz = (_world_ray(r_pair, u, v, i) for i in range(3))
    px, py, pz = origin[shape].unbind(-1)
    ox, oy = px - cyl[shape, 0], py - cyl[shape, 1]
    z0, z1, r = cyl[shape, 2], cyl[shape, 3], cyl[shape, 4]
    r2 = r * r
    a = dx * dx + dy * dy
    b = dx * ox + dy * oy
    disc = b * b - a * (ox * ox + oy * oy - r2)
    wall_ok = (disc >= 0) & (a > 0)  # a vertical ray never meets the side wall
    root = torch.sqrt(_where_safe(disc > 0, disc)) * (disc > 0)
    t = (-b - root) / _where_safe(wall_ok, a)
    z = pz + t * dz
    best = torch.where(wall_ok & (t > 0) & (z >= z0) & (z <= z1), t, torch.inf)
    up = dz != 0
    for zc in (z0, z1):  # caps
        tc = (zc - pz) / _where_safe(up, dz)
        qx, qy = ox + tc * dx, oy + tc * dy
        best = torch.where(up & (tc > 0) & (qx * qx + qy * qy <= r2) & (tc < best), tc, best)
    return (env[shape] * height + row) * width + col, best


def box_pair_depth(pairs, env, boxes, origin, rot, tan_h: float, tan_v: float, height: int, width: int):
    """(flat index, planar depth in m) of every (axis-aligned box, pixel) pair (slab method), +inf for none;
    inside a box, its far side. boxes (K, 6) [min xyz, max xyz]; origin, rot as :func:`cylinder_pair_depth`."""
    shape = pairs[0]
    row, col = pair_pixels(*pairs)
    u, v = pixel_rays(row, col, tan_h, tan_v, height, width, boxes.dtype)
    r_pair = rot[shape]
    lo, hi, o = boxes[shape, :3], boxes[shape, 3:], origin[shape]
    t_near = t_far = None
    for i in range(3):
        d = _world_ray(r_pair, u, v, i)
        moving = d != 0
        d_safe = _where_safe(moving, d)
        t0, t1 = (lo[:, i] - o[:, i]) / d_safe, (hi[:, i] - o[:, i]) / d_safe
        # a ray parallel to a slab: the numpy camera's substitution, literally (see docs/simulator.md)
        inside = (lo[:, i] <= o[:, i]) & (o[:, i] <= hi[:, i])
        inf = torch.full_like(t0, torch.inf)
        t0 = torch.where(moving, t0, torch.where(inside, -inf, inf))
        t1 = torch.where(moving, t1, torch.where(inside, inf, -inf))
        near, far = torch.minimum(t0, t1), torch.maximum(t0, t1)
        t_near = near if t_near is None else torch.maximum(t_near, near)
        t_far = far if t_far is None else torch.minimum(t_far, far)
    t = torch.where(t_near > 0, t_near, t_far)
    return (env[shape] * height + row) * width + col, torch.where((t_near > t_far) | (t_far <= 0), torch.inf, t)


def ground_depth(origin, rotation, u, v, envs) -> torch.Tensor:
    """(E, H W) planar depth (m) of the plane z = 0 below each camera above it (+inf elsewhere)."""
    dz = rotation[:, 2, 0:1] + rotation[:, 2, 1:2] * u + rotation[:, 2, 2:3] * v
    down = (dz < 0) & (origin[:, 2:3] > 0) & envs[:, None]
    return torch.where(down, -origin[:, 2:3] / _where_safe(down, dz), torch.inf)


class BatchedCamera:
    """Renders E scenes' depth images in one call (see the module docstring).

    ``compile``: a function that compiles the per-pair kernels (e.g. ``torch.compile``), or None to run
    them eagerly (the default; exactness tests run eager).
    """

    def __init__(self, config: CameraConfig | None = None, device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float64, compile: Callable | None = None):
        self.config = cfg = (config or CameraConfig()).validate()
        ref = DepthCamera(cfg)  # the numpy camera's rays, frustum and reach, value for value
        like = dict(dtype=dtype, device=device)
        self.device, self.dtype = torch.device(device), dtype
        self.tan_h, self.tan_v = ref._tan_h, ref._tan_v
        self.u = torch.as_tensor(ref._u_flat, **like)
        self.v = torch.as_tensor(ref._v_flat, **like)
        self._image = (ref._tan_h, ref._tan_v, cfg.height, cfg.width)  # what the pair kernels need of the rays
        self.mount = torch.as_tensor(np.asarray(cfg.mount_offset_m, dtype=np.float64), **like)
        self.frustum = torch.as_tensor(ref._frustum, **like)  # (4, 3) inward unit normals, body frame
        self.reach = ref._reach
        corners = [[sx, sy, sz] for sx in (0, 1) for sy in (0, 1) for sz in (0, 1)]
        self._box_corners = torch.as_tensor(corners, **like)
        self._cyl_corners = torch.as_tensor(
            [[-1, -1, 0], [-1, -1, 1], [-1, 1, 0], [-1, 1, 1], [1, -1, 0], [1, -1, 1], [1, 1, 0], [1, 1, 1]], **like)
        wrap = compile or (lambda f: f)
        self._spheres_kernel = wrap(sphere_pair_depth)
        self._cylinders_kernel = wrap(cylinder_pair_depth)
        self._boxes_kernel = wrap(box_pair_depth)
        self._ground_kernel = wrap(ground_depth)
        self._sphere_windows = wrap(sphere_windows)

    # -- public ------------------------------------------------------------------------------------

    def camera_centre(self, position: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
        """(E, 3) camera centres (world, m): the body origin plus the mount offset turned into the world."""
        return position + rotation @ self.mount

    def cast(self, batch: SceneBatch, position: torch.Tensor, rotation: torch.Tensor,
             envs: torch.Tensor | None = None) -> torch.Tensor:
        """Nearest hit per pixel (E, H, W), planar depth in m, +inf for none (hits beyond the range kept).

        position (E, 3) body origins, world frame (m); rotation (E, 3, 3) body-to-world; ``envs`` (E,)
        bool: the scenes to render (the others read +inf), all by default.
        """
        cfg = self.config
        e, size = position.shape[0], cfg.height * cfg.width
        origin = self.camera_centre(position, rotation)
        if envs is None:
            envs = torch.ones(e, dtype=torch.bool, device=position.device)
        flats, depths = [], []
        for cast in (self._cast_spheres, self._cast_cylinders, self._cast_boxes):
            out = cast(batch, origin, rotation, envs)
            if out is not None:
                flats.append(out[0])
                depths.append(out[1])
        # the ground (or nothing) first; the shapes' hits replace it where nearer
        if cfg.render_ground:
            buffer = self._ground_kernel(origin, rotation, self.u, self.v, envs).reshape(-1)
        else:
            buffer = torch.full((e * size,), torch.inf, dtype=position.dtype, device=position.device)
        if flats:  # (one kind of shape: no copy)
            flat = flats[0] if len(flats) == 1 else torch.cat(flats)
            depth = depths[0] if len(depths) == 1 else torch.cat(depths)
            buffer = buffer.scatter_reduce(0, flat, depth, "amin", include_self=True)
        depth = buffer.view(e, size)
        return depth.view(e, cfg.height, cfg.width)

    def metric_depth(self, batch, position, rotation, envs=None) -> torch.Tensor:
        """Planar depth (E, H, W) in m, +inf where nothing is hit within range (as ``DepthCamera.metric_depth``)."""
        depth = self.cast(batch, position, rotation, envs)
        return torch.where(depth > self.config.max_range_m, torch.inf, depth)

    def render(self, batch, position, rotation, envs=None, noise: torch.Tensor | None = None,
               dropout: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised depth (E, H, W) in [0, 1] (as ``DepthCamera.render``), in the batch's dtype.

        ``noise`` (E, H, W): Gaussian draws in metres (standard deviation ``noise_std_m``), added to
        finite metric depth; ``dropout`` (E, H, W): uniform [0, 1) draws, a pixel reads 0 where its draw is below
        ``dropout_prob``. Both required when the config asks for them (the rollout draws them seeded).
        """
        cfg = self.config
        if cfg.noise_std_m > 0.0 or cfg.dropout_prob > 0.0:
            metric = self.metric_depth(batch, position, rotation, envs)
            if (cfg.noise_std_m > 0.0 and noise is None) or (cfg.dropout_prob > 0.0 and dropout is None):
                raise ValueError("BatchedCamera.render needs noise / dropout draws when the config asks for them")
            if cfg.noise_std_m > 0.0:
                metric = torch.where(torch.isfinite(metric), metric + noise, metric)
            image = (metric / cfg.max_range_m).clamp(1e-6, 1.0)  # noise must not fake "no reading"
            if cfg.dropout_prob > 0.0:
                image = torch.where(dropout < cfg.dropout_prob, torch.zeros_like(image), image)
            return image
        # beyond the range reads 1, like nothing at all
        return (self.cast(batch, position, rotation, envs) / cfg.max_range_m).clamp(max=1.0)

    # -- casting: each returns (flat pixel index into the (E H W) buffer, depth) of all its pairs ------

    def _windows(self, u_lo, u_hi, v_lo, v_hi):
        cfg = self.config
        return pixel_windows(u_lo, u_hi, v_lo, v_hi, self.tan_h, self.tan_v, cfg.height, cfg.width)

    def _pairs(self, windows):
        """(shape, start, r0, c0, cols) of every pixel in each shape's window (see :func:`window_pairs`)."""
        r0, r1, c0, c1 = windows
        shape, start, cols = window_pairs(r0, r1, c0, c1)
        return shape, start, r0, c0, cols

    def _cast_spheres(self, batch, origin, rotation, envs):
        cfg = self.config
        sph = batch.spheres
        # world -> camera frame: R^T (centre - origin)
        cam = torch.einsum("ekj,eji->eki", sph[..., :3] - origin[:, None, :], rotation)
        with torch.no_grad():
            keep, r0, r1, c0, c1 = self._sphere_windows(
                cam.detach(), sph[..., 3].detach(), batch.sphere_mask & envs[:, None], cfg.max_range_m, self.frustum,
                self.tan_h, self.tan_v, cfg.height, cfg.width)
            env, k = keep.nonzero(as_tuple=True)
            if len(env) == 0:
                return None
            pairs = self._pairs((r0[env, k], r1[env, k], c0[env, k], c1[env, k]))
        r = sph[env, k, 3]
        return self._spheres_kernel(pairs, env, cam[env, k], r * r, *self._image)

    def _corner_windows(self, corners_cam: torch.Tensor):
        """Pixel windows of the convex hulls of (K, 8, 3) camera-frame corners (whole image if one is behind)."""
        front = (corners_cam[..., 0] > 1e-6).all(-1)
        xc = torch.where(front[:, None], corners_cam[..., 0], torch.ones_like(corners_cam[..., 0]))
        u, v = corners_cam[..., 1] / xc, corners_cam[..., 2] / xc
        big = torch.full_like(front, _BIG, dtype=corners_cam.dtype)
        return self._windows(torch.where(front, u.amin(-1), -big), torch.where(front, u.amax(-1), big),
                             torch.where(front, v.amin(-1), -big), torch.where(front, v.amax(-1), big))

    def _cast_cylinders(self, batch, origin, rotation, envs):
        if batch.cylinders.shape[1] == 0:
            return None
        cyl = batch.cylinders
        with torch.no_grad():
            c = cyl.detach()
            sx, sy, sz = self._cyl_corners.unbind(-1)
            x, y, z0, z1, r = (c[..., i : i + 1] for i in range(5))
            corners = torch.stack([x + r * sx, y + r * sy, z0 + (z1 - z0) * sz], -1) - origin[:, None, None, :]
            cam = torch.einsum("eknj,eji->ekni", corners, rotation.detach())  # (E, K, 8, 3)
            # beyond the range, or wholly outside one frustum plane
            outside = ((cam @ self.frustum.T) < 0.0).all(2).any(-1)
            keep = (cam[..., 0].amin(-1) < self.config.max_range_m) & ~outside & batch.cylinder_mask & envs[:, None]
            env, k = keep.nonzero(as_tuple=True)
            if len(env) == 0:
                return None
            pairs = self._pairs(self._corner_windows(cam[env, k]))
        return self._cylinders_kernel(pairs, env, cyl[env, k], origin[env], rotation[env], *self._image)

    def _cast_boxes(self, batch, origin, rotation, envs):
        if batch.boxes.shape[1] == 0:
            return None
        boxes = batch.boxes
        with torch.no_grad():
            b = boxes.detach()
            o = origin.detach()[:, None, :]
            lo, hi = b[..., :3], b[..., 3:]
            nearest = torch.minimum(torch.maximum(o, lo), hi)
            keep = (torch.linalg.vector_norm(nearest - o, dim=-1) < self.reach) & batch.box_mask & envs[:, None]
            env, k = keep.nonzero(as_tuple=True)
            if len(env) == 0:
                return None
            lo, hi = lo[env, k], hi[env, k]
            corners = lo[:, None, :] + self._box_corners * (hi - lo)[:, None, :] - o[env]
            cam = torch.einsum("knj,kji->kni", corners, rotation.detach()[env])
            pairs = self._pairs(self._corner_windows(cam))
        return self._boxes_kernel(pairs, env, boxes[env, k], origin[env], rotation[env], *self._image)
