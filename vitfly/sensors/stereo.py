"""Stereo depth sensor models applied to the camera's exact render: ``d435`` (Intel RealSense D435).

The camera (:mod:`vitfly.sim.camera`) casts exact planar depth at the 60 x 90 pixel centres that the
deployment's resize samples. A sensor model turns that clean metric depth into what the robot's
depth stream would have held at those pixels, then runs the original's deployment pipeline to the
network's input. It works at the output resolution (60 x 90): each output pixel stands for the stream
pixel the resize samples there. Noise is computed in the stream's own disparity units (its focal
length ``focal_px``), geometric effects in the output grid (occlusion shadows: the output focal length).

Effects, in order (every parameter and its source in :class:`StereoDepthConfig`):

1. occlusion shadow: a left-right pair has depth only where both imagers see the surface; the depth
   image is aligned to the LEFT imager and the right imager sits ``baseline_m`` to the right (body -y,
   towards higher columns). Background pixels just left of a near surface are hidden from the right
   imager: a band of f * b * (1 / z_near - 1 / z_far) output pixels on the near surface's left side
   reads "no depth";
2. disparity noise: d = f b / z (stream pixels), plus temporal subpixel noise (``subpixel_rms_px``, drawn
   per tick) and a fixed speckle pattern (``pattern_rms_px``: the projector's dot pattern is rigid with
   the camera, so its per-pixel error is fixed in image coordinates; drawn once per scene seed), then
   quantised to ``disparity_step_px``; z' = f b / d'. The depth error grows as z^2: sigma_z = z^2 sigma_d / (f b);
3. invalid pixels: true depth below ``min_range_m`` (disparity beyond the search range), measured depth
   beyond ``max_range_m`` or nothing hit, the occlusion shadow, and the propeller blades in the image's
   corners (``propellers``; read "no depth" or a near value);
4. deployment (``depthfly/scripts/run.py`` of the original project, the node that flew the D435):
   normalised = clip(z / 10 m, 0, 1 / scale) * scale with ``scale`` 0.8, invalid pixels set to 0.8
   (``invalid_value``), then the bilinear resize to 60 x 90 (here: the samples themselves);
5. frame delay: the policy sees the frame of ``delay_ticks`` control ticks ago (:class:`FrameDelay`).

Randomness is seeded: the same (scene seed, tick) gives the same frame.

Example::

    sensor = StereoDepthSensor(StereoDepthConfig(), CameraConfig())
    image = sensor.image(camera.metric_depth(scene, position, rotation), seed=scene.seed, tick=0)
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

SENSOR_MODELS = ("d435",)
PROPELLER_CORNERS = ("none", "top", "bottom")
PROPELLER_READS = ("invalid", "near")
_PATTERN_SALT, _TICK_SALT = 0x9A77, 0x5E45


@dataclass(frozen=True)
class ImageGeometry:
    """The rendered grid the model works on: what it needs of a camera (``vitfly.sim.camera.CameraConfig`` has
    the same attributes and is accepted in its place). Defaults: vitfly's default camera (60 x 90 pixels,
    100 degrees vertical field of view rendered at 640 x 480, so tan(h / 2) = tan(50 deg) x 640 / 480; 10 m range).
    """

    height: int = 60  # pixels
    width: int = 90
    tan_half_horizontal: float = math.tan(math.radians(100.0) / 2) * 640 / 480
    max_range_m: float = 10.0  # normalisation range: normalised depth = metric depth / max_range_m

    @classmethod
    def from_camera_values(cls, values: Mapping[str, Any] | None, max_range_m: float | None = None) -> ImageGeometry:
        """The geometry of a camera recorded as plain values (a dataset's ``camera`` attribute: the fields of
        ``CameraConfig``; missing ones take its defaults). ``max_range_m`` (e.g. the dataset's ``depth_max_m``)
        wins over the recorded one."""
        values = dict(values or {})
        vertical = float(values.get("vertical_fov_deg", 100.0))
        horizontal = values.get("horizontal_fov_deg")
        if horizontal is not None:  # as CameraConfig.tan_half_horizontal
            tan_h = math.tan(math.radians(float(horizontal)) / 2)
        else:
            source_width, source_height = values.get("source_width", 640), values.get("source_height", 480)
            tan_h = math.tan(math.radians(vertical) / 2) * source_width / source_height
        range_m = max_range_m if max_range_m is not None else values.get("max_range_m", 10.0)
        return cls(int(values.get("height", 60)), int(values.get("width", 90)), tan_h, float(range_m))


@dataclass(frozen=True)
class StereoDepthConfig:
    """A stereo depth sensor (m, pixels, ticks). Defaults: the D435 at 848 x 480 as the original flew it.

    Sources: [DS] Intel RealSense D400 Series datasheet (337029); [TG] Grunnet-Jepsen et al., "Tuning
    depth cameras for best performance" (Intel white paper); [LRS] librealsense
    ``src/proc/disparity-transform.cpp``; [RUN] the original's ``depthfly/scripts/run.py``.
    """

    model: str = "d435"
    baseline_m: float = 0.050  # [DS] D435 stereo baseline 50 mm
    stream_width_px: int = 848  # [DS]/[TG] depth stream 848 x 480, the resolution [TG] recommends for the D435
    stream_height_px: int = 480
    stream_hfov_deg: float = 87.0  # [DS] D435 depth field of view 87 x 58 degrees
    subpixel_rms_px: float = 0.08  # [TG] typical subpixel RMS for a well-textured target (temporal, per tick)
    pattern_rms_px: float = 0.05  # ASSUMPTION: fixed speckle (projector pattern) disparity error, per pixel
    disparity_step_px: float = 1.0 / 32.0  # [LRS] disparity in 1/32 pixel (5 fractional bits)
    min_range_m: float = 0.28  # [DS] D435 min-Z ~280 mm (at 1280 x 720; [TG]'s f b / 126 gives 0.17 m at 848 x 480)
    max_range_m: float = 10.0  # [DS] "up to 10 m" (varies with calibration, scene and lighting)
    occlusion: bool = True  # the left-right occlusion shadow beside depth edges
    propellers: str = "none"  # blades in the image corners: "none", "top" (top corners) or "bottom"
    propeller_radius_frac: float = 0.25  # ASSUMPTION: blade disc radius as a fraction of the image height
    propeller_reads: str = "invalid"  # blade pixels: "invalid" (inside min-Z) or "near" (read min_range_m)
    deploy_scale: float = 0.8  # [RUN] normalised = clip(z / 10 m, 0, 1 / 0.8) * 0.8
    invalid_value: float = 0.8  # [RUN] invalid (0) pixels set to 0.8 before the resize
    delay_ticks: int = 0  # frames the policy lags behind (control ticks)

    @property
    def focal_px(self) -> float:
        """The stream's focal length in its own pixels, [TG]: f = (width / 2) / tan(HFOV / 2)."""
        return 0.5 * self.stream_width_px / math.tan(math.radians(self.stream_hfov_deg) / 2)

    def depth_rms_m(self, depth_m):
        """[TG] depth RMS error from the temporal and pattern disparity noise: z^2 sigma_d / (f b)."""
        sigma_d = math.hypot(self.subpixel_rms_px, self.pattern_rms_px)
        return np.asarray(depth_m, dtype=np.float64) ** 2 * sigma_d / (self.focal_px * self.baseline_m)

    def validate(self, prefix: str = "sensor.") -> StereoDepthConfig:
        """Raise ValueError naming the first field out of range (``prefix`` goes before its name)."""
        choices = {"model": SENSOR_MODELS, "propellers": PROPELLER_CORNERS, "propeller_reads": PROPELLER_READS}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                value = getattr(self, name)
                raise ValueError(f"field {prefix}{name} is {value!r}; expected one of {', '.join(allowed)}")
        positive = ("baseline_m", "stream_width_px", "stream_height_px", "disparity_step_px", "max_range_m",
                    "deploy_scale")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"field {prefix}{name} is {getattr(self, name)}; expected > 0")
        for name in ("subpixel_rms_px", "pattern_rms_px", "min_range_m", "propeller_radius_frac", "delay_ticks"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"field {prefix}{name} is {getattr(self, name)}; expected >= 0")
        if not 0 < self.stream_hfov_deg < 180:
            raise ValueError(f"field {prefix}stream_hfov_deg is {self.stream_hfov_deg}; expected 0 < fov < 180")
        if not self.min_range_m < self.max_range_m:
            raise ValueError(f"field {prefix}min_range_m ({self.min_range_m}) must be below max_range_m "
                             f"({self.max_range_m})")
        if not 0.0 <= self.invalid_value <= 1.0:
            raise ValueError(f"field {prefix}invalid_value is {self.invalid_value}; expected 0..1 (normalised)")
        if int(self.delay_ticks) != self.delay_ticks:
            raise ValueError(f"field {prefix}delay_ticks is {self.delay_ticks}; expected a whole number of ticks")
        return self


def sensor_from_dict(values: Mapping[str, Any] | None, prefix: str = "sensor.") -> StereoDepthConfig | None:
    """A validated :class:`StereoDepthConfig` from plain values (``{model: d435, ...}``); None or
    ``{model: none}`` gives None. Raises ValueError with one line naming the field."""
    if values is None:
        return None
    if not isinstance(values, Mapping):
        raise ValueError(f"field {prefix.rstrip('.')} must be a mapping such as {{model: d435}}, got {values!r}")
    values = dict(values)
    if values.get("model") in (None, "none") and set(values) <= {"model"}:
        return None
    known = [f.name for f in dataclasses.fields(StereoDepthConfig)]
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ValueError(f"unknown field {prefix}{unknown[0]}; known: {', '.join(known)}")
    kinds = {f.name: type(getattr(StereoDepthConfig(), f.name)) for f in dataclasses.fields(StereoDepthConfig)}
    for name, value in values.items():
        kind = kinds[name]
        ok = isinstance(value, kind) if kind in (str, bool) else (
            isinstance(value, int | float) and not isinstance(value, bool))
        if not ok:
            raise ValueError(f"field {prefix}{name} has {value!r}; expected {kind.__name__}")
        if kind is int and float(value) != int(value):
            raise ValueError(f"field {prefix}{name} has {value!r}; expected a whole number")
        values[name] = kind(value)
    return StereoDepthConfig(**values).validate(prefix)


def sensor_flag_values(tokens: list[str] | None) -> dict[str, Any] | None:
    """``--sensor MODEL [FIELD=VALUE ...]`` as plain values (values read as YAML); None when not given.

    ``["d435", "delay_ticks=1"]`` -> ``{"model": "d435", "delay_ticks": 1}``; ``["none"]`` -> ``{"model": "none"}``.
    Raises ValueError (one line) for a token that is neither."""
    if not tokens:
        return None
    import yaml

    values: dict[str, Any] = {}
    for i, token in enumerate(tokens):
        name, sep, text = token.partition("=")
        if not sep:
            if i:
                raise ValueError(f"--sensor: expected FIELD=VALUE after the model, got {token!r}")
            values["model"] = token
            continue
        try:
            values[name.strip()] = yaml.safe_load(text)
        except yaml.YAMLError:
            raise ValueError(f"--sensor: cannot read the value of {token!r}") from None
    return values


def sensor_dict(config: StereoDepthConfig | None) -> dict[str, Any] | None:
    """Plain JSON-able values of a sensor model (None for the ideal camera)."""
    return None if config is None else dataclasses.asdict(config)


def occlusion_mask(depth_m: np.ndarray, focal_px: float, baseline_m: float) -> np.ndarray:
    """Pixels of a left-aligned depth image (H, W) that the right imager cannot see (bool, H, W).

    The right imager sits ``baseline_m`` towards higher columns. Pixel p (column c_p, planar depth z_p)
    lands at column r_p = c_p - f b / z_p in the right image; it is hidden when a pixel q further right
    in its row lands at or left of it (r_q <= r_p, then q is nearer). ``inf`` depth: disparity 0.
    """
    with np.errstate(divide="ignore"):
        disparity = np.where(np.isfinite(depth_m) & (depth_m > 0), focal_px * baseline_m / depth_m, 0.0)
    right = np.arange(depth_m.shape[1], dtype=np.float64)[None, :] - disparity
    # smallest right-image column among the pixels to the right of each pixel (suffix minimum, shifted)
    suffix = np.minimum.accumulate(right[:, ::-1], axis=1)[:, ::-1]
    after = np.full_like(right, np.inf)
    after[:, :-1] = suffix[:, 1:]
    return after <= right - 1e-9


def propeller_mask(height: int, width: int, corners: str, radius_frac: float) -> np.ndarray:
    """Fixed mask (bool, H, W) of blade discs centred on two image corners ("top" or "bottom"; "none": empty)."""
    mask = np.zeros((height, width), dtype=bool)
    if corners == "none" or radius_frac <= 0:
        return mask
    rows, cols = np.mgrid[0:height, 0:width] + 0.5
    row0 = 0.0 if corners == "top" else float(height)
    radius = radius_frac * height
    for col0 in (0.0, float(width)):
        mask |= (rows - row0) ** 2 + (cols - col0) ** 2 <= radius**2
    return mask


class StereoDepthSensor:
    """Applies a :class:`StereoDepthConfig` to clean metric depth from a camera of ``camera`` geometry."""

    def __init__(self, config: StereoDepthConfig, camera: Any = None):
        """``camera``: a ``CameraConfig`` or an :class:`ImageGeometry` (height, width, tan_half_horizontal,
        max_range_m); None: vitfly's default camera."""
        self.config = config.validate()
        self.camera = camera = camera or ImageGeometry()
        # the rendered grid's focal length (output pixels, horizontal), for the geometry of occlusion
        self.output_focal_px = 0.5 * camera.width / camera.tan_half_horizontal
        self._propellers = propeller_mask(camera.height, camera.width, config.propellers, config.propeller_radius_frac)

    def pattern(self, seed: int) -> np.ndarray:
        """The fixed speckle disparity error (stream pixels, H, W) of scene seed ``seed``."""
        rng = np.random.default_rng([int(seed), _PATTERN_SALT])
        return rng.normal(0.0, self.config.pattern_rms_px, (self.camera.height, self.camera.width))

    def metric(self, depth_m: np.ndarray, seed: int, tick: int) -> np.ndarray:
        """Measured planar depth (m, H, W) float64 from clean depth (``inf`` = nothing hit); NaN = no reading."""
        cfg = self.config
        depth_m = np.asarray(depth_m, dtype=np.float64)
        finite = np.isfinite(depth_m) & (depth_m > 0)
        fb = cfg.focal_px * cfg.baseline_m
        rng = np.random.default_rng([int(seed), int(tick), _TICK_SALT])
        noise = rng.normal(0.0, cfg.subpixel_rms_px, depth_m.shape) if cfg.subpixel_rms_px > 0 else 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            disparity = np.where(finite, fb / depth_m, 0.0) + noise
            if cfg.pattern_rms_px > 0:
                disparity = disparity + self.pattern(seed)
            disparity = np.round(disparity / cfg.disparity_step_px) * cfg.disparity_step_px
            measured = np.where(disparity > 0, fb / disparity, np.inf)
        invalid = ~finite | (depth_m < cfg.min_range_m) | ~(measured <= cfg.max_range_m)
        if cfg.occlusion:
            invalid |= occlusion_mask(depth_m, self.output_focal_px, cfg.baseline_m)
        out = np.where(invalid, np.nan, measured)
        if self._propellers.any():
            out[self._propellers] = np.nan if cfg.propeller_reads == "invalid" else cfg.min_range_m
        return out

    def normalise(self, measured_m: np.ndarray) -> np.ndarray:
        """The deployment pipeline [RUN]: clip(z / range, 0, 1 / scale) * scale, no reading -> ``invalid_value``.

        ``range`` is the camera's normalisation range (10 m by default). float32 (H, W)."""
        cfg = self.config
        image = np.clip(measured_m / self.camera.max_range_m, 0.0, 1.0 / cfg.deploy_scale) * cfg.deploy_scale
        return np.where(np.isnan(measured_m), cfg.invalid_value, image).astype(np.float32)

    def image(self, depth_m: np.ndarray, seed: int, tick: int) -> np.ndarray:
        """What the network sees: :meth:`metric`, then :meth:`normalise`."""
        return self.normalise(self.metric(depth_m, seed, tick))


class FrameDelay:
    """The frame of ``ticks`` calls ago (the first frame stands in until the line has filled)."""

    def __init__(self, ticks: int):
        self.ticks = int(ticks)
        self._frames: deque[np.ndarray] = deque(maxlen=self.ticks + 1)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        if not self._frames:
            self._frames.extend([frame] * (self.ticks + 1))
        else:
            self._frames.append(frame)
        return self._frames[0]


__all__ = ["FrameDelay", "ImageGeometry", "SENSOR_MODELS", "StereoDepthConfig", "StereoDepthSensor", "occlusion_mask",
           "propeller_mask", "sensor_dict", "sensor_flag_values", "sensor_from_dict"]
