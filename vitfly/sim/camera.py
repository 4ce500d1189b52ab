"""Forward depth camera by exact ray casting of the scene's primitive shapes (numpy).

The default geometry is the camera the paper's training data was actually rendered with: Flightmare
rendered 640 x 480 depth with a 100 degree field of view (Unity's ``fieldOfView`` is vertical;
Flightmare's intrinsics agree: f = (height / 2) / tan(fov / 2)), mounted at t_BC = (0.3, 0, 0) m,
i.e. 0.3 m FORWARD of the body origin (body frame x forward, y left, z up), looking along body +x;
``user_code`` then resized it to 90 x 60 with ``cv2.resize`` (INTER_LINEAR). So the 90 x 60 image
spans 2 atan(4/3 tan 50 deg) = 115.6 degrees across and 100 degrees high, and its pixels are not square.

Why this camera (preset ``vision_config_yaml``) and not the one in the original's
``envsim/parameters/camera_config.yaml`` (320 x 240, 70 degrees, t_BC = (0, 0, 0.3); preset
``camera_config_yaml``): ``envsim/src/visionsim_node.cpp`` builds
``flightlib::VisionEnv($FLIGHTMARE_PATH/flightpy/configs/vision/config.yaml, 0)``, whose constructor
(``init()`` -> ``configCamera(cfg_)``) adds the ``rgb_camera`` of that file (t_BC (0.3, 0, 0),
r_BC (0, 0, -90), 640 x 480, fov 100, depth on). visionsim_node's later
``configCamera(camera_config.yaml)`` returns early ("Camera has been added. Skipping the camera
configuration.") because the quadrotor already has a camera. r_BC (0, 0, -90) is Rz(-90 deg)
(configCamera composes Rz(yaw) Ry(pitch) Rx(roll)); ``transformationRos2Unity`` swaps y and z, so
Unity's camera axes (x right, y up, z forward) become body -y, +z and +x: it looks straight ahead,
image up = body up.

Where each output pixel looks: INTER_LINEAR maps output pixel j's centre to source coordinate
(j + 0.5) * W_src / W_out (edge-based, i.e. pixel centres at +0.5), and interpolates the two source
pixels around it, without anti-aliasing. Taken as a sample of the rendered image at that point,
that is the ray of a pinhole with the same field of view and W_out x H_out pixels, so the source
resolution drops out and only its aspect ratio matters: this camera casts exactly those rays. The
one approximation: across a depth edge, the original blended the two neighbouring source pixels
(1/201 rad apart at the centre of the default camera), where this camera reads the near or the far
surface.

Image row 0 is the top (body +z), column 0 the left (body +y). A pixel holds planar depth
(distance along the optical axis, as a depth camera reports it) divided by ``max_range_m`` and
clipped to 1; nothing within range reads 1, and 0 is reserved for "no reading" (dropout).

Only shapes that can be seen are cast against: spheres and tree canopies within range and inside
the view frustum, trunks and walls within range, and the ground plane z = 0 (optional).

Example::

    camera = DepthCamera(CameraConfig())
    depth = camera.render(scene, position=(0, 0, 3.5), rotation=np.eye(3))   # (60, 90) float32
    # camera_config.yaml's camera, which the original never applied
    CameraConfig.from_preset("camera_config_yaml")
    # in a collect YAML: ``camera: {preset: camera_config_yaml}``; vitfly evaluate: --camera preset=camera_config_yaml
    # vitfly's camera before it followed the original: 90 x 67.4 degrees, square pixels, at the body origin
    CameraConfig(horizontal_fov_deg=90.0, vertical_fov_deg=67.38, mount_offset_m=(0.0, 0.0, 0.0))
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from vitfly.sim.scenes import Scene

# Named camera geometries of the original project (CameraConfig fields). A preset fixes only the
# geometry; range, noise, dropout and ground stay as given (or default).
CAMERA_PRESETS: dict[str, dict] = {
    # flightpy/configs/vision/config.yaml rgb_camera: the camera the original actually rendered with
    "vision_config_yaml": {
        "vertical_fov_deg": 100.0,
        "horizontal_fov_deg": None,
        "source_width": 640,
        "source_height": 480,
        "mount_offset_m": (0.3, 0.0, 0.0),
    },
    # envsim/parameters/camera_config.yaml: configured by visionsim_node but skipped (a camera was already added)
    "camera_config_yaml": {
        "vertical_fov_deg": 70.0,
        "horizontal_fov_deg": None,
        "source_width": 320,
        "source_height": 240,
        "mount_offset_m": (0.0, 0.0, 0.3),
    },
}
DEFAULT_CAMERA_PRESET = "vision_config_yaml"


def expand_camera_preset(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """CameraConfig fields from a mapping that may hold ``preset: NAME``: the preset's geometry, then the
    other fields given (they win). Raises ValueError naming ``{prefix}preset`` for an unknown name."""
    values = dict(values)
    if "preset" not in values:
        return values
    name = values.pop("preset")
    if name not in CAMERA_PRESETS:
        raise ValueError(f"field {prefix}preset is {name!r}; expected one of {', '.join(CAMERA_PRESETS)}")
    return {**CAMERA_PRESETS[name], **values}


@dataclass(frozen=True)
class CameraConfig:
    """Depth camera settings (m, degrees, pixels); defaults are the original's effective Flightmare camera
    (preset ``vision_config_yaml``, see the module docstring).

    ``horizontal_fov_deg`` None: derived from the vertical one and the aspect ratio of the rendered
    (source) image, tan(h / 2) = tan(v / 2) * source_width / source_height (a pinhole resized to the
    output size keeps its fields of view).
    """

    height: int = 60  # output image, after the resize
    width: int = 90
    vertical_fov_deg: float = 100.0  # of the rendering pinhole (Unity's fov is vertical)
    horizontal_fov_deg: float | None = None  # None: from vertical_fov_deg and the source aspect
    source_width: int = 640  # the image Flightmare rendered before the resize (only its aspect matters)
    source_height: int = 480
    mount_offset_m: tuple[float, float, float] = (0.3, 0.0, 0.0)  # camera centre in the body frame (t_BC)
    max_range_m: float = 10.0  # normalisation: stored depth = metric depth / max_range_m, clipped to 1
    render_ground: bool = True  # the plane z = 0
    noise_std_m: float = 0.0  # additive Gaussian noise on metric depth (domain randomisation)
    dropout_prob: float = 0.0  # probability that a pixel reads 0 ("no reading")

    @classmethod
    def from_preset(cls, name: str, **overrides) -> CameraConfig:
        """The camera of preset ``name`` (a key of ``CAMERA_PRESETS``), other fields from ``overrides``."""
        return cls(**expand_camera_preset({"preset": name, **overrides}))

    @property
    def tan_half_vertical(self) -> float:
        return math.tan(math.radians(self.vertical_fov_deg) / 2)

    @property
    def tan_half_horizontal(self) -> float:
        if self.horizontal_fov_deg is not None:
            return math.tan(math.radians(self.horizontal_fov_deg) / 2)
        return self.tan_half_vertical * self.source_width / self.source_height

    def validate(self, prefix: str = "") -> CameraConfig:
        """Raise ValueError naming the first field out of range (``prefix`` goes before its name)."""
        for name in ("vertical_fov_deg", "horizontal_fov_deg"):
            value = getattr(self, name)
            if value is not None and not 0.0 < value < 180.0:
                raise ValueError(f"field {prefix}{name} is {value}; expected 0 < fov < 180 degrees")
        for name in ("height", "width", "source_width", "source_height"):
            if getattr(self, name) < 1:
                raise ValueError(f"field {prefix}{name} is {getattr(self, name)}; expected >= 1 pixel")
        if not self.max_range_m > 0:
            raise ValueError(f"field {prefix}max_range_m is {self.max_range_m}; expected > 0 m")
        return self


class DepthCamera:
    """Renders normalised depth images of a :class:`~vitfly.sim.scenes.Scene`.

    Each visible shape is cast only against the pixels inside its projected bounding rectangle,
    so the cost grows with the image area the shapes cover, not with pixels x shapes.
    """

    def __init__(self, config: CameraConfig | None = None):
        self.config = cfg = (config or CameraConfig()).validate()
        self._tan_h = cfg.tan_half_horizontal
        self._tan_v = cfg.tan_half_vertical
        self._mount = np.asarray(cfg.mount_offset_m, dtype=np.float64).reshape(3)
        u = self._tan_h * (1.0 - 2.0 * (np.arange(cfg.width) + 0.5) / cfg.width)  # +y (left) at column 0
        v = self._tan_v * (1.0 - 2.0 * (np.arange(cfg.height) + 0.5) / cfg.height)  # +z (up) at row 0
        # body-frame ray directions (1, u, v): unit forward component, so the ray parameter is planar depth
        self._v, self._u = np.meshgrid(v, u, indexing="ij")  # (H, W) each
        self._a = 1.0 + self._u**2 + self._v**2  # squared ray length
        # flat views for gathering by flat pixel index
        self._u_flat, self._v_flat, self._a_flat = self._u.ravel(), self._v.ravel(), self._a.ravel()
        # a pixel's ray reaches at most this far (m) before planar depth exceeds the range
        self._reach = cfg.max_range_m * math.sqrt(float(self._a.max()))
        # inward unit normals of the four frustum side planes (body frame), for culling
        planes = np.array(
            [[self._tan_h, -1.0, 0.0], [self._tan_h, 1.0, 0.0], [self._tan_v, 0.0, -1.0], [self._tan_v, 0.0, 1.0]]
        )
        self._frustum = planes / np.linalg.norm(planes, axis=1, keepdims=True)
        # per-bound constants of _pixel_windows: (c0, c1, r0, r1)
        self._win_tan = np.array([[self._tan_h], [self._tan_h], [self._tan_v], [self._tan_v]])
        self._win_size = np.array([[cfg.width], [cfg.width], [cfg.height], [cfg.height]], dtype=np.float64)

    @property
    def ray_directions_body(self) -> np.ndarray:
        """(H, W, 3) body-frame direction of each pixel's ray, scaled to a unit forward (x) component, so that
        ``mount_offset_m + planar_depth_m * ray`` is the hit point in the body frame (inverse of rendering)."""
        return np.stack([np.ones_like(self._u), self._u, self._v], axis=-1)

    @property
    def vertical_fov_deg(self) -> float:
        return math.degrees(2 * math.atan(self._tan_v))

    @property
    def horizontal_fov_deg(self) -> float:
        return math.degrees(2 * math.atan(self._tan_h))

    def metric_depth(self, scene: Scene, position, rotation: np.ndarray) -> np.ndarray:
        """Planar depth in metres (H, W) float64, ``inf`` where nothing is hit within range.

        position: (3,) body origin (the drone's position), world frame (m); the camera sits at
        ``mount_offset_m`` from it in the body frame. rotation: (3, 3) body-to-world matrix.
        """
        depth = self._cast_all(scene, position, rotation)
        depth[depth > self.config.max_range_m] = np.inf
        return depth

    def _cast_all(self, scene: Scene, position, rotation: np.ndarray) -> np.ndarray:
        """Nearest hit per pixel (m), ``inf`` for none; hits beyond the range are left in."""
        cfg = self.config
        rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        pos = np.asarray(position, dtype=np.float64).reshape(3) + rot @ self._mount  # camera centre
        size = cfg.height * cfg.width
        # one slot past the image: where the sphere pass sends the pairs that miss
        buffer = np.full(size + 1, np.inf)
        depth = buffer[:size].reshape(cfg.height, cfg.width)
        if len(scene.spheres):
            self._cast_spheres(buffer, scene.spheres, pos, rot)
        if len(scene.cylinders) or len(scene.boxes):
            # world-frame ray directions, (H, W) per component
            dirs = [rot[i, 0] + rot[i, 1] * self._u + rot[i, 2] * self._v for i in range(3)]
            if len(scene.cylinders):
                self._cast_cylinders(depth, scene.cylinders, pos, rot, dirs)
            if len(scene.boxes):
                self._cast_boxes(depth, scene.boxes, pos, rot, dirs)
            dz = dirs[2]
        else:
            dz = rot[2, 0] + rot[2, 1] * self._u + rot[2, 2] * self._v
        if cfg.render_ground and pos[2] > 0:
            self._cast_ground(depth, pos, dz)
        return depth

    def render(
        self, scene: Scene, position, rotation: np.ndarray, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        """Normalised depth image (H, W) float32 in [0, 1] (see the module docstring).

        position and rotation as :meth:`metric_depth`. ``rng`` drives noise and dropout; it is
        required when either is configured.
        """
        cfg = self.config
        if cfg.noise_std_m > 0.0 or cfg.dropout_prob > 0.0:
            metric = self.metric_depth(scene, position, rotation)
            if rng is None:
                raise ValueError("DepthCamera.render needs an rng when noise or dropout is configured")
            if cfg.noise_std_m > 0.0:
                finite = np.isfinite(metric)
                metric = np.where(finite, metric + rng.normal(0.0, cfg.noise_std_m, metric.shape), metric)
            image = np.clip(metric / cfg.max_range_m, 1e-6, 1.0)  # noise must not fake "no reading"
            if cfg.dropout_prob > 0.0:
                image[rng.random(image.shape) < cfg.dropout_prob] = 0.0
            return image.astype(np.float32)
        # beyond the range reads 1, like nothing at all
        return np.minimum(self._cast_all(scene, position, rotation) / cfg.max_range_m, 1.0).astype(np.float32)

    # -- projection helpers ----------------------------------------------------------------------

    def _pixel_windows(self, u_lo, u_hi, v_lo, v_hi):
        """Row and column ranges [r0, r1) x [c0, c1) whose pixel centres may fall in tangent-space boxes."""
        # u = tan_h (1 - 2 (col + 0.5) / W)  =>  col = (1 - u / tan_h) W / 2 - 0.5; rows likewise
        # (the four bounds in one (4, K) array: c0, c1, r0, r1 before rounding)
        x = np.stack([u_hi, u_lo, v_hi, v_lo])
        x /= self._win_tan
        np.subtract(1.0, x, out=x)
        x *= self._win_size
        x /= 2
        x -= 0.5
        np.floor(x[0::2], out=x[0::2])  # c0, r0
        np.ceil(x[1::2], out=x[1::2])  # c1, r1
        x[1::2] += 1
        np.maximum(x, 0.0, out=x)
        np.minimum(x, self._win_size, out=x)  # as np.clip(x, 0, size)
        c0, c1, r0, r1 = x.astype(np.int64)
        return r0, r1, c0, c1

    def _window_pixels(self, r0, r1, c0, c1) -> tuple[np.ndarray, np.ndarray]:
        """Every flat pixel index of the shapes' pixel windows, shape by shape, and how many each shape has.

        Returns ``(counts, pix)``: ``pix`` lists shape 0's window pixels, then shape 1's, ...; shape k
        has ``counts[k]`` of them (so ``np.repeat(values, counts)`` lines per-shape values up with ``pix``).
        """
        n_rows = np.maximum(r1 - r0, 0) * (c1 > c0)
        # one entry per (shape, row): where the row's run of pixels starts, and how long it is
        row_sid = np.repeat(np.arange(len(n_rows)), n_rows)
        row = r0[row_sid] + np.arange(len(row_sid)) - np.repeat(np.cumsum(n_rows) - n_rows, n_rows)
        run = (c1 - c0)[row_sid]
        start = row * self.config.width + c0[row_sid]
        # expand the runs: pixel = start of its run + position within the run
        offset = np.repeat(start - (np.cumsum(run) - run), run)
        offset += np.arange(len(offset))
        return n_rows * (c1 - c0), offset

    def _points_window(self, points_cam: np.ndarray) -> tuple[slice, slice]:
        """Pixel window of the convex hull of body-frame points (full image if any is behind)."""
        x = points_cam[:, 0]
        if np.any(x <= 1e-6):
            return slice(0, self.config.height), slice(0, self.config.width)
        u, v = points_cam[:, 1] / x, points_cam[:, 2] / x
        r0, r1, c0, c1 = (
            int(w[0]) for w in self._pixel_windows(*(np.array([b]) for b in (u.min(), u.max(), v.min(), v.max())))
        )
        return slice(r0, max(r1, r0)), slice(c0, max(c1, c0))

    # -- casting: each writes min(depth, hit) into the depth buffer ------------------------------

    def _cast_spheres(self, buffer, spheres, pos, rot) -> None:
        # buffer: the flat depth image plus one spare slot at the end, all +inf (spheres are cast first)
        cfg = self.config
        radius = spheres[:, 3]
        cam = (spheres[:, :3] - pos) @ rot  # world -> body frame (R^T rel, row-wise)
        # planar depth on a sphere is at least cx - r: beyond the range it would read 1 anyway
        keep = (cam[:, 0] - radius < cfg.max_range_m) & np.all(cam @ self._frustum.T > -radius[:, None], axis=1)
        if not keep.any():
            return
        cam, r = cam[keep], radius[keep]
        # far to near: a near sphere's hit then usually overwrites a far one's in _scatter_min's first
        # round (the result does not depend on the order, only the number of rounds does)
        order = np.argsort(-cam[:, 0], kind="stable")
        cx, cy, cz = cam[order].T
        r = r[order]
        r2 = r * r
        # exact image bounds from the tangent planes through the camera (spheres wholly in front);
        # a sphere reaching behind the image plane may cover the whole image
        front = cx > r
        k = np.where(front, cx * cx - r2, 1.0)
        hu = r * np.sqrt(np.maximum(cx * cx + cy * cy - r2, 0.0))
        hv = r * np.sqrt(np.maximum(cx * cx + cz * cz - r2, 0.0))
        big = 1e6
        counts, pix = self._window_pixels(
            *self._pixel_windows(
                np.where(front, (cx * cy - hu) / k, -big),
                np.where(front, (cx * cy + hu) / k, big),
                np.where(front, (cx * cz - hv) / k, -big),
                np.where(front, (cx * cz + hv) / k, big),
            )
        )
        if len(pix) == 0:
            return
        # every (sphere, pixel-in-its-window) pair in one vectorised pass
        u, v, a = self._u_flat.take(pix), self._v_flat.take(pix), self._a_flat.take(pix)
        b = np.repeat(cy, counts)
        b *= u
        b += np.repeat(cx, counts)
        v *= np.repeat(cz, counts)
        b += v  # ray . centre: cx + cy u + cz v
        c_sphere = cx * cx + cy * cy + cz * cz - r2  # > 0 when the camera is outside the sphere
        c = np.repeat(c_sphere, counts)
        c *= a
        disc = np.multiply(b, b, out=u)
        disc -= c  # b^2 - a c
        with np.errstate(invalid="ignore"):
            root = np.sqrt(disc, out=disc)  # NaN where the ray misses
            # outside: the near intersection; inside: the far side (exit point)
            if c_sphere.min() > 0:
                b -= root
            else:
                b -= np.where(np.repeat(c_sphere, counts) > 0, root, -root)
            b /= a
            miss = ~(b > 0)  # also where NaN
        # no hit: +inf into the spare slot (so that it cannot displace a hit on its pixel)
        np.copyto(b, np.inf, where=miss)
        np.copyto(pix, len(buffer) - 1, where=miss)
        _scatter_min(buffer, pix, b, empty=True)

    def _cast_cylinders(self, depth, cylinders, pos, rot, dirs) -> None:
        # vertical cylinders (side wall + top and bottom caps), solved in the world frame; culled with
        # the corners of their bounding boxes (body frame): beyond the range, or outside one frustum plane
        sx = np.array([-1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0])
        sy = np.array([-1.0, -1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0])
        sz = np.array([0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0])
        x, y, z0, z1, r = (cylinders[:, i : i + 1] for i in range(5))
        corners = np.stack([x + r * sx, y + r * sy, z0 + (z1 - z0) * sz], axis=-1) - pos  # (K, 8, 3)
        cam = corners @ rot
        outside = np.any(np.all(cam @ self._frustum.T < 0.0, axis=1), axis=1)
        keep = (cam[:, :, 0].min(axis=1) < self.config.max_range_m) & ~outside
        if not keep.any():
            return
        cyl, cam = cylinders[keep], cam[keep]
        # pixel windows from the projected corners; a box reaching behind the camera: whole image
        front = np.all(cam[:, :, 0] > 1e-6, axis=1)
        xc = np.where(front[:, None], cam[:, :, 0], 1.0)
        u, v = cam[:, :, 1] / xc, cam[:, :, 2] / xc
        big = 1e6
        counts, pix = self._window_pixels(
            *self._pixel_windows(
                np.where(front, u.min(axis=1), -big),
                np.where(front, u.max(axis=1), big),
                np.where(front, v.min(axis=1), -big),
                np.where(front, v.max(axis=1), big),
            )
        )
        if len(pix) == 0:
            return
        sid = np.repeat(np.arange(len(counts)), counts)
        dx, dy, dz = (d.ravel()[pix] for d in dirs)
        ox, oy = pos[0] - cyl[sid, 0], pos[1] - cyl[sid, 1]
        z0, z1, r2 = cyl[sid, 2], cyl[sid, 3], cyl[sid, 4] ** 2
        a = dx * dx + dy * dy
        b = dx * ox + dy * oy
        disc = b * b - a * (ox * ox + oy * oy - r2)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(disc)) / a  # side wall, NaN where the ray misses the infinite cylinder
            z = pos[2] + t * dz
            best = np.where((t > 0) & (z >= z0) & (z <= z1), t, np.inf)
            for zc in (z0, z1):  # caps
                tc = (zc - pos[2]) / dz
                px, py = ox + tc * dx, oy + tc * dy
                best = np.where((tc > 0) & (px * px + py * py <= r2) & (tc < best), tc, best)
        hit = best < np.inf
        _scatter_min(depth.reshape(-1), pix[hit], best[hit])

    def _cast_boxes(self, depth, boxes, pos, rot, dirs) -> None:
        # axis-aligned boxes: slab method in the world frame
        nearest = np.clip(pos, boxes[:, :3], boxes[:, 3:])
        keep = np.linalg.norm(nearest - pos, axis=1) < self._reach
        corners = np.array([[sx, sy, sz] for sx in (0, 1) for sy in (0, 1) for sz in (0, 1)], dtype=np.float64)
        for box in boxes[keep]:
            lo, hi = box[:3], box[3:]
            rows, cols = self._points_window((lo + corners * (hi - lo) - pos) @ rot)
            d = [c[rows, cols] for c in dirs]
            if d[0].size == 0:
                continue
            t_near = np.full(d[0].shape, -np.inf)
            t_far = np.full(d[0].shape, np.inf)
            with np.errstate(divide="ignore", invalid="ignore"):
                for i in range(3):
                    t0, t1 = (lo[i] - pos[i]) / d[i], (hi[i] - pos[i]) / d[i]
                    # a ray parallel to a slab misses it unless it starts between the faces
                    parallel = d[i] == 0
                    inside = (lo[i] <= pos[i]) & (pos[i] <= hi[i])
                    t0 = np.where(parallel, -np.inf if inside else np.inf, t0)
                    t1 = np.where(parallel, np.inf if inside else -np.inf, t1)
                    t_near = np.maximum(t_near, np.minimum(t0, t1))
                    t_far = np.minimum(t_far, np.maximum(t0, t1))
            t = np.where(t_near > 0, t_near, t_far)  # inside a box: its far side
            t[(t_near > t_far) | (t_far <= 0)] = np.inf
            np.minimum(depth[rows, cols], t, out=depth[rows, cols])

    def _cast_ground(self, depth, pos, dz) -> None:
        with np.errstate(divide="ignore"):
            t = np.where(dz < 0, -pos[2] / dz, np.inf)
        np.minimum(depth, t, out=depth)


def _scatter_min(flat: np.ndarray, index: np.ndarray, values: np.ndarray, empty: bool = False) -> None:
    """``flat[index] = min(flat[index], values)`` with repeated indices, like ``np.minimum.at``.

    Exact, and much faster when indices repeat a few times: a fancy assignment stores one of the
    candidates of each repeated index (which one does not matter), then only the candidates still
    below what was stored go round again; each round settles at least one candidate per index.
    ``empty``: the caller guarantees ``flat[index]`` is +inf everywhere (saves a read).
    """
    if empty:
        flat[index] = values
    else:
        current = flat.take(index)
        np.minimum(current, values, out=current)
        flat[index] = current
    while True:
        better = values < flat.take(index)
        if not better.any():
            return
        index, values = index[better], values[better]
        flat[index] = values
