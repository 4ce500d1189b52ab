"""Procedural obstacle scenes: ``spheres``, ``trees``, ``window`` and ``course`` (the hardware arena).

A scene is plain data: three arrays of primitive shapes in the world frame (x forward, y left,
z up; metres). The same (env, preset, seed) gives the same arrays bit for bit, and a scene
round-trips through JSON exactly (floats are written with ``repr`` precision), so any trial can
be replayed from its saved layout.

Example::

    scene = make_scene("spheres", "medium", seed=3)
    scene.spheres.shape          # (K, 4) rows [x, y, z, radius]
    save_scene(scene, "scene.json"); load_scene("scene.json").equals(scene)   # True
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from vitfly.atomic import write_text
from vitfly.errors import VitflyError

ENVS = ("spheres", "trees", "window", "course")
PRESETS = ("easy", "medium", "hard")
COURSE_LAYOUTS = ("single", "gap", "multi")
SCENE_FORMAT = "vitfly.scene"
SCENE_FORMAT_VERSION = 1


@dataclass(frozen=True)
class Region:
    """Axis-aligned box where obstacles are placed (world frame, m). Clear zones at start and goal."""

    x: tuple[float, float] = (5.0, 60.0)
    y: tuple[float, float] = (-10.0, 10.0)
    z: tuple[float, float] = (0.0, 10.0)


@dataclass(frozen=True)
class SpheresConfig:
    """Floating spheres (the training distribution): ``count`` spheres, radii uniform in ``radius``."""

    count: int = 250
    radius: tuple[float, float] = (0.5, 1.5)
    region: Region = field(default_factory=Region)


@dataclass(frozen=True)
class TreesConfig:
    """Trees: a vertical trunk cylinder from the ground with a spherical canopy at its top."""

    count: int = 45
    trunk_radius: tuple[float, float] = (0.15, 0.35)
    height: tuple[float, float] = (4.0, 9.0)
    canopy_radius: tuple[float, float] = (0.8, 1.5)
    region: Region = field(default_factory=Region)


@dataclass(frozen=True)
class WindowConfig:
    """A wall across the flight path (normal along x) with one rectangular opening beside the start line.

    The wall's x position, the opening's size, its side (left or right, at random), its lateral offset and its
    height are drawn from the seed. The opening's nearer edge lies ``opening_offset_y`` beside the line y = 0 that
    the drone starts on, so flying straight always meets the wall: as in the paper, only a tight bundle of paths,
    which turn towards the opening, gets through.
    """

    wall_x: tuple[float, float] = (20.0, 40.0)
    thickness: float = 0.3
    opening_width: tuple[float, float] = (1.5, 3.0)
    opening_height: tuple[float, float] = (1.5, 3.0)
    opening_offset_y: tuple[float, float] = (0.5, 2.0)  # m from y = 0 to the opening's nearer side edge
    opening_center_z: tuple[float, float] = (2.0, 5.0)
    region: Region = field(default_factory=Region)


@dataclass(frozen=True)
class CourseConfig:
    """The hardware course: free-standing cylinders and boxes on the floor of a motion-capture-sized arena.

    The arena: 20 m along x from the task's start line, ``arena_y`` wide (8 m); obstacles stand on the floor in
    ``obstacle_x``. They are ``height`` tall (8 m): floor-to-ceiling columns that are passed beside, never over.
    The task is the shared one (start at 3.5 m altitude, goal x = 60 m, bounds z 0..10 m), so a real 4 m ceiling
    is not modelled: 4 m columns would be overflown, 0.5 m above the start altitude (see docs/simulator.md).
    ``layout``:
    ``single`` (one obstacle on the start line, within ``single_offset_y`` of y = 0), ``gap`` (two obstacles
    side by side with a passable gap of ``gap_width`` between their surfaces, beside the start line: the line
    runs ``gap_line_overlap`` inside one of the two, on a random side, so flying straight meets it),
    ``multi`` (``count`` obstacles spread over the arena, the first on the start line, at least ``spacing`` apart
    surface to surface), or ``mixed`` (one of the three per seed). Each obstacle is a cylinder or a box (half each);
    ``radius`` is a cylinder's radius and a box's half-width.
    """

    layout: str = "mixed"
    arena_y: tuple[float, float] = (-4.0, 4.0)  # m; the arena is x 0..20 m (the task starts at x = 0)
    obstacle_x: tuple[float, float] = (6.0, 16.0)  # where obstacles stand (a clear run-up after the start)
    radius: tuple[float, float] = (0.25, 0.5)
    height: tuple[float, float] = (8.0, 8.0)  # m, floor to "ceiling" (taller than the expert would climb over)
    single_offset_y: float = 0.2
    gap_width: tuple[float, float] = (1.6, 2.4)
    gap_line_overlap: tuple[float, float] = (0.05, 0.45)  # m, < 2 * radius[0]: the line meets the obstacle
    count: tuple[int, int] = (3, 6)
    spacing: float = 1.5


# Density presets. Spheres `medium` is calibrated (docs/simulator.md, "Calibration") so that at 3 m/s the
# expert succeeds in roughly 80-90 % of trials and straight flight in at most ~30 %.
PRESET_CONFIGS: dict[str, dict[str, SpheresConfig | TreesConfig | WindowConfig]] = {
    "spheres": {
        "easy": SpheresConfig(count=120),
        "medium": SpheresConfig(count=250),
        "hard": SpheresConfig(count=400),
    },
    "trees": {
        "easy": TreesConfig(count=25),
        "medium": TreesConfig(count=45),
        "hard": TreesConfig(count=80),
    },
    "window": {
        "easy": WindowConfig(opening_width=(2.5, 4.0), opening_height=(2.5, 4.0)),
        "medium": WindowConfig(),
        "hard": WindowConfig(opening_width=(1.0, 1.8), opening_height=(1.0, 1.8)),
    },
    # the course's presets are its layouts; easy/medium/hard name single/mixed/multi
    "course": {
        "easy": CourseConfig(layout="single"),
        "medium": CourseConfig(layout="mixed"),
        "hard": CourseConfig(layout="multi"),
        "single": CourseConfig(layout="single"),
        "gap": CourseConfig(layout="gap"),
        "multi": CourseConfig(layout="multi"),
    },
}


@dataclass(frozen=True, eq=False)
class Scene:
    """Obstacle primitives in the world frame (m).

    spheres:   (K, 4) float64 rows [x, y, z, radius]
    cylinders: (K, 5) float64 vertical cylinders [x, y, z_bottom, z_top, radius]
    boxes:     (K, 6) float64 axis-aligned boxes [x_min, y_min, z_min, x_max, y_max, z_max]
    """

    env: str
    preset: str
    seed: int
    spheres: np.ndarray
    cylinders: np.ndarray
    boxes: np.ndarray

    def __post_init__(self) -> None:
        for name, width in (("spheres", 4), ("cylinders", 5), ("boxes", 6)):
            arr = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1, width)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def num_obstacles(self) -> int:
        return len(self.spheres) + len(self.cylinders) + len(self.boxes)

    def equals(self, other: Scene) -> bool:
        """Bit-for-bit equality of the metadata and all obstacle arrays."""
        return (self.env, self.preset, self.seed) == (other.env, other.preset, other.seed) and all(
            np.array_equal(getattr(self, n), getattr(other, n)) for n in ("spheres", "cylinders", "boxes")
        )

    def expert_obstacles(self, spacing_m: float = 0.5) -> np.ndarray:
        """All obstacles as (K, 4) spheres [x, y, z, radius] for the privileged expert.

        Spheres are exact. Cylinders and boxes are covered by spheres on a grid of ``spacing_m``
        whose radii are just large enough that no point of the shape lies outside the cover.
        """
        return self.expert_objects(spacing_m)[0]

    def expert_objects(self, spacing_m: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The expert cover grouped by object: ``(spheres, object_index, anchor_lo, anchor_hi)``.

        spheres (K, 4) as :meth:`expert_obstacles`; object_index (K,) int, the object of each
        sphere; anchor_lo, anchor_hi (M, 3), the axis-aligned box whose nearest point gives object
        m's distance (see :mod:`vitfly.sim.expert`). Objects: each sphere not centred on a trunk's
        top (anchor: its centre), each trunk with the canopies centred on its top (a tree; anchor:
        the trunk's axis), each box (anchor: the box).
        """
        n_sph, n_cyl = len(self.spheres), len(self.cylinders)
        # a canopy is a sphere centred exactly on a trunk's top centre (the generator writes the same floats)
        owner = np.full(n_sph, -1)
        if n_sph and n_cyl:
            top = self.cylinders[:, [0, 1, 3]]
            match = np.all(self.spheres[None, :, :3] == top[:, None, :], axis=2)  # (cylinders, spheres)
            has = match.any(axis=0)
            owner[has] = np.argmax(match[:, has], axis=0)
        free = np.flatnonzero(owner < 0)
        sphere_object = np.empty(n_sph, dtype=np.int64)
        sphere_object[free] = np.arange(len(free))
        sphere_object[owner >= 0] = len(free) + owner[owner >= 0]
        parts, objects = [self.spheres], [sphere_object]
        lo = [self.spheres[free, :3], self.cylinders[:, [0, 1, 2]], self.boxes[:, :3]]
        hi = [self.spheres[free, :3], self.cylinders[:, [0, 1, 3]], self.boxes[:, 3:]]
        if n_cyl:
            cover, counts = _cover_cylinders(self.cylinders, spacing_m)
            parts.append(cover)
            objects.append(len(free) + np.repeat(np.arange(n_cyl), counts))
        if len(self.boxes):
            cover, counts = _cover_boxes(self.boxes, spacing_m)
            parts.append(cover)
            objects.append(len(free) + n_cyl + np.repeat(np.arange(len(self.boxes)), counts))
        spheres = np.concatenate(parts, axis=0) if len(parts) > 1 else self.spheres.copy()
        return spheres, np.concatenate(objects), np.concatenate(lo), np.concatenate(hi)

    def to_dict(self) -> dict:
        return {
            "format": SCENE_FORMAT,
            "version": SCENE_FORMAT_VERSION,
            "env": self.env,
            "preset": self.preset,
            "seed": int(self.seed),
            "spheres": self.spheres.tolist(),
            "cylinders": self.cylinders.tolist(),
            "boxes": self.boxes.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict, source: str = "scene") -> Scene:
        if not isinstance(data, dict) or data.get("format") != SCENE_FORMAT:
            raise VitflyError(f"{source}: not a vitfly scene (expected field format={SCENE_FORMAT!r})")
        if data.get("version") != SCENE_FORMAT_VERSION:
            raise VitflyError(f"{source}: field version is {data.get('version')!r}, expected {SCENE_FORMAT_VERSION}")
        arrays = {}
        for name, width in (("spheres", 4), ("cylinders", 5), ("boxes", 6)):
            try:
                arr = np.asarray(data.get(name, []), dtype=np.float64).reshape(-1, width)
            except (TypeError, ValueError):
                raise VitflyError(f"{source}: field {name} must be a list of {width}-number rows") from None
            if not np.all(np.isfinite(arr)):
                raise VitflyError(f"{source}: field {name} holds NaN or infinite values")
            arrays[name] = arr
        try:
            return cls(env=str(data["env"]), preset=str(data["preset"]), seed=int(data["seed"]), **arrays)
        except KeyError as err:
            raise VitflyError(f"{source}: missing field {err.args[0]}") from None


def scene_config(env: str, preset: str) -> SpheresConfig | TreesConfig | WindowConfig:
    """The generator config for (env, preset); VitflyError naming the known values otherwise."""
    if env not in PRESET_CONFIGS:
        raise VitflyError(f"unknown env {env!r}; expected one of {', '.join(ENVS)}")
    if preset not in PRESET_CONFIGS[env]:
        raise VitflyError(f"unknown preset {preset!r} for env {env}; expected one of {', '.join(PRESET_CONFIGS[env])}")
    return PRESET_CONFIGS[env][preset]


def make_scene(
    env: str,
    preset: str = "medium",
    seed: int = 0,
    config: SpheresConfig | TreesConfig | WindowConfig | CourseConfig | None = None,
) -> Scene:
    """Generate the scene for (env, preset, seed); ``config`` overrides the preset's generator config."""
    cfg = config if config is not None else scene_config(env, preset)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _env_salt(env)]))
    empty = {"spheres": np.zeros((0, 4)), "cylinders": np.zeros((0, 5)), "boxes": np.zeros((0, 6))}
    if env == "spheres":
        return Scene(env, preset, int(seed), **{**empty, "spheres": _spheres(cfg, rng)})
    if env == "trees":
        trunks, canopies = _trees(cfg, rng)
        return Scene(env, preset, int(seed), **{**empty, "spheres": canopies, "cylinders": trunks})
    if env == "window":
        return Scene(env, preset, int(seed), **{**empty, "boxes": _window(cfg, rng)})
    if env == "course":
        cylinders, boxes = _course(cfg, rng)
        return Scene(env, preset, int(seed), **{**empty, "cylinders": cylinders, "boxes": boxes})
    raise VitflyError(f"unknown env {env!r}; expected one of {', '.join(ENVS)}")


def save_scene(scene: Scene, path: str | os.PathLike) -> None:
    """Write ``scene`` as JSON atomically (temp file + rename)."""
    write_text(path, json.dumps(scene.to_dict()))


def load_scene(path: str | os.PathLike) -> Scene:
    """Read a scene JSON written by :func:`save_scene`."""
    try:
        with open(path) as f:
            data = json.load(f)
    except FileNotFoundError:
        raise VitflyError(f"{path}: scene file not found") from None
    except json.JSONDecodeError as err:
        raise VitflyError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    return Scene.from_dict(data, source=str(path))


def _env_salt(env: str) -> int:
    # different envs with the same seed should not share random streams
    return sum((i + 1) * ord(c) for i, c in enumerate(env))


def _uniform(rng: np.random.Generator, bounds: tuple[float, float], n: int) -> np.ndarray:
    return rng.uniform(bounds[0], bounds[1], size=n)


def _spheres(cfg: SpheresConfig, rng: np.random.Generator) -> np.ndarray:
    n = int(cfg.count)
    r = cfg.region
    return np.stack(
        [_uniform(rng, r.x, n), _uniform(rng, r.y, n), _uniform(rng, r.z, n), _uniform(rng, cfg.radius, n)], axis=1
    )


def _trees(cfg: TreesConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    n = int(cfg.count)
    r = cfg.region
    x, y = _uniform(rng, r.x, n), _uniform(rng, r.y, n)
    height = _uniform(rng, cfg.height, n)
    trunk_r = _uniform(rng, cfg.trunk_radius, n)
    canopy_r = _uniform(rng, cfg.canopy_radius, n)
    trunks = np.stack([x, y, np.zeros(n), height, trunk_r], axis=1)
    canopies = np.stack([x, y, height, canopy_r], axis=1)
    return trunks, canopies


def _window(cfg: WindowConfig, rng: np.random.Generator) -> np.ndarray:
    r = cfg.region
    wall_x = rng.uniform(*cfg.wall_x)
    w, h = rng.uniform(*cfg.opening_width), rng.uniform(*cfg.opening_height)
    side = 1.0 if rng.uniform() < 0.5 else -1.0  # left (+y) or right (-y) of the start line
    cy = side * (rng.uniform(*cfg.opening_offset_y) + w / 2)
    cz = rng.uniform(*cfg.opening_center_z)
    y0, y1 = max(cy - w / 2, r.y[0]), min(cy + w / 2, r.y[1])
    z0, z1 = max(cz - h / 2, r.z[0]), min(cz + h / 2, r.z[1])
    x0, x1 = wall_x - cfg.thickness / 2, wall_x + cfg.thickness / 2
    boxes = [
        [x0, r.y[0], r.z[0], x1, y0, r.z[1]],  # right of the opening (-y side)
        [x0, y1, r.z[0], x1, r.y[1], r.z[1]],  # left of the opening (+y side)
        [x0, y0, r.z[0], x1, y1, z0],  # below
        [x0, y0, z1, x1, y1, r.z[1]],  # above
    ]
    return np.array([b for b in boxes if b[4] > b[1] and b[5] > b[2]], dtype=np.float64)


def _course(cfg: CourseConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cylinders (K, 5) and boxes (K, 6) of one course layout (see :class:`CourseConfig`)."""
    layout = cfg.layout
    if layout == "mixed":
        layout = COURSE_LAYOUTS[int(rng.integers(len(COURSE_LAYOUTS)))]
    if layout not in COURSE_LAYOUTS:
        raise VitflyError(f"course layout is {cfg.layout!r}; expected one of {', '.join(COURSE_LAYOUTS)}, mixed")
    y_lo, y_hi = cfg.arena_y
    x = rng.uniform(*cfg.obstacle_x)
    if layout == "single":
        sites = [(x, rng.uniform(-cfg.single_offset_y, cfg.single_offset_y), rng.uniform(*cfg.radius))]
    elif layout == "gap":
        gap, side = rng.uniform(*cfg.gap_width), 1.0 if rng.uniform() < 0.5 else -1.0
        centre = side * (gap / 2 + rng.uniform(*cfg.gap_line_overlap))  # the other obstacle is on the line
        r_left, r_right = rng.uniform(*cfg.radius, size=2)
        sites = [(x, centre + gap / 2 + r_left, r_left), (x, centre - gap / 2 - r_right, r_right)]
    else:
        n = int(rng.integers(cfg.count[0], cfg.count[1] + 1))
        sites = [(x, rng.uniform(-cfg.single_offset_y, cfg.single_offset_y), rng.uniform(*cfg.radius))]
        for _ in range(200 * n):  # rejection sampling (seeded, so deterministic)
            if len(sites) == n:
                break
            r = rng.uniform(*cfg.radius)
            cand = (rng.uniform(*cfg.obstacle_x), rng.uniform(y_lo + r, y_hi - r), r)
            if all(math.hypot(cand[0] - s[0], cand[1] - s[1]) - cand[2] - s[2] >= cfg.spacing for s in sites):
                sites.append(cand)
    cylinders, boxes = [], []
    for sx, sy, r in sites:
        h = rng.uniform(*cfg.height)
        if rng.uniform() < 0.5:
            cylinders.append([sx, sy, 0.0, h, r])
        else:
            boxes.append([sx - r, sy - r, 0.0, sx + r, sy + r, h])
    return np.array(cylinders, dtype=np.float64).reshape(-1, 5), np.array(boxes, dtype=np.float64).reshape(-1, 6)


def _grid(lo: float, hi: float, spacing: float) -> tuple[np.ndarray, float]:
    """Cell centres covering [lo, hi] with cells of at most ``spacing``; also the cell size."""
    n = max(1, math.ceil((hi - lo) / spacing - 1e-9))
    step = (hi - lo) / n
    return lo + step * (np.arange(n) + 0.5), step


def _cover_cylinders(cyl: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Covering spheres of each cylinder, one block per cylinder, and the block sizes."""
    out = []
    for x, y, z0, z1, r in cyl:
        zs, step = _grid(z0, z1, spacing)
        radius = math.hypot(r, step / 2)
        out.append(np.stack([np.full_like(zs, x), np.full_like(zs, y), zs, np.full_like(zs, radius)], axis=1))
    return np.concatenate(out, axis=0), np.array([len(o) for o in out])


def _cover_boxes(boxes: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Covering spheres of each box, one block per box, and the block sizes."""
    out = []
    for x0, y0, z0, x1, y1, z1 in boxes:
        (xs, sx), (ys, sy), (zs, sz) = _grid(x0, x1, spacing), _grid(y0, y1, spacing), _grid(z0, z1, spacing)
        radius = 0.5 * math.sqrt(sx * sx + sy * sy + sz * sz)
        gx, gy, gz = np.meshgrid(xs, ys, zs, indexing="ij")
        out.append(np.stack([gx.ravel(), gy.ravel(), gz.ravel(), np.full(gx.size, radius)], axis=1))
    return np.concatenate(out, axis=0), np.array([len(o) for o in out])
