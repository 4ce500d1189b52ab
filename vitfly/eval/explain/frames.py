"""The frames every explained model is shown: one trial, flown in the simulator or replayed from data.

``fly_trial`` flies one scene through the normal rollout (``record_depth``) with a pilot (the expert,
``straight`` or a learned policy) and keeps what the camera saw at every control tick.
``frames_from_arrays`` wraps a recorded trajectory (e.g. one of a vitfly dataset, read by the caller
with ``vitfly.datamodules.schema.open_trajectories``). Both attach the obstacle edge masks: exact
from the scene when it is known (``scene_from_dataset_config`` rebuilds it for vitfly-collected
data), else from the frames' own depth jumps, and say which in ``edge_source``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace

import numpy as np

from vitfly.errors import VitflyError
from vitfly.eval.explain.edges import (
    DEFAULT_EDGES,
    MAX_MISMATCH_SHARE,
    EdgeConfig,
    depth_edge_masks,
    scene_edge_masks,
)
from vitfly.sim.camera import CameraConfig
from vitfly.sim.rollout import Policy, RolloutConfig, run_episodes
from vitfly.sim.scenes import Scene, make_scene

IMAGE_SHAPE = (60, 90)


@dataclass
class TrialFrames:
    """One trial, tick by tick (T control ticks); world frame, SI units.

    depth (T, 60, 90) float32 in [0, 1] (metric depth / max_range_m); desired_speed (T,) m/s;
    quat (T, 4) body-to-world (w, x, y, z); time (T,) s; position (T, 3) m; command (T, 3) m/s, the
    pilot's command (None when unknown); edges (T, 60, 90) bool obstacle edge masks (None: unknown);
    edge_source "scene" (exact, from the scene's geometry), "depth" (jumps in the frames themselves,
    ground included) or "none"; title, one line for figures; info, JSON-able provenance.
    """

    depth: np.ndarray
    desired_speed: np.ndarray
    quat: np.ndarray
    time: np.ndarray
    position: np.ndarray
    command: np.ndarray | None = None
    edges: np.ndarray | None = None
    edge_source: str = "none"
    title: str = ""
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = len(self.depth)
        if self.depth.ndim != 3 or self.depth.shape[1:] != IMAGE_SHAPE:
            raise VitflyError(f"depth: expected frames of shape (T, {IMAGE_SHAPE[0]}, {IMAGE_SHAPE[1]}), "
                              f"got {self.depth.shape}")
        if t == 0:
            raise VitflyError("the trial has no frames")
        for name, shape in (("desired_speed", (t,)), ("quat", (t, 4)), ("time", (t,)), ("position", (t, 3))):
            if getattr(self, name).shape != shape:
                raise VitflyError(f"{name}: expected shape {shape}, got {getattr(self, name).shape}")

    def __len__(self) -> int:
        return len(self.depth)

    def head(self, n: int) -> TrialFrames:
        """The first ``n`` ticks (all when n >= T)."""
        cut = {f.name: getattr(self, f.name)[:n] for f in fields(self)
               if isinstance(getattr(self, f.name), np.ndarray)}  # fmt: skip
        return replace(self, **cut)


def _attach_edges(frames: TrialFrames, scene: Scene | None, camera: CameraConfig, edge_config: EdgeConfig,
                  source: str, compare: bool = True) -> TrialFrames:
    if scene is not None:
        recorded = frames.depth if compare else None  # not compared: a sensor model made the frames on purpose
        masks, mismatch = scene_edge_masks(scene, camera, frames.position, frames.quat, recorded, edge_config)
        if math.isnan(mismatch) or mismatch <= MAX_MISMATCH_SHARE:
            frames.edges, frames.edge_source = masks, "scene"
            frames.info["edge_rerender_mismatch_share"] = None if math.isnan(mismatch) else mismatch
            return frames
        # the scene does not reproduce the frames (another camera, another scene): do not pretend
        frames.info["edge_rerender_mismatch_share"] = mismatch
        frames.info["edge_note"] = (
            f"{source}: re-rendering the scene differs from the frames on {100 * mismatch:.1f} % of pixels; "
            "edges taken from the frames' own depth jumps"
        )
    frames.edges = depth_edge_masks(frames.depth, camera.max_range_m, edge_config)
    frames.edge_source = "depth"
    return frames


def fly_trial(
    scene: Scene,
    speed_mps: float,
    pilot: Policy,
    pilot_name: str,
    config: RolloutConfig | None = None,
    edge_config: EdgeConfig = DEFAULT_EDGES,
) -> TrialFrames:
    """Fly ``scene`` at ``speed_mps`` with ``pilot`` through the normal rollout and keep every frame.

    With a sensor model in ``config`` (``RolloutConfig.sensor``) the frames are what that sensor gave the
    models, and the edges come from the scene's geometry at the logged poses, exact by construction (the
    modelled frames differ from a clean re-render on purpose, so they are not compared)."""
    cfg = replace(config or RolloutConfig(), record_depth=True)
    result = run_episodes([scene], [float(speed_mps)], pilot, cfg)[0]
    log, s = result.log, result.summary
    frames = TrialFrames(
        depth=log.depth.astype(np.float32),
        desired_speed=np.full(len(log), float(speed_mps)),
        quat=log.quat,
        time=log.time,
        position=log.position,
        command=log.command,
        title=f"{s.env}/{s.preset} seed {s.seed}, {s.desired_speed:g} m/s, flown by {pilot_name}: {s.end_reason}, "
        f"{s.n_collisions} collision(s)" + ("" if cfg.sensor is None else f", {cfg.sensor.model} depth"),
        info={"source": "simulation", "pilot": pilot_name, **s.to_dict(),
              "sensor": None if cfg.sensor is None else cfg.sensor.model},
    )
    return _attach_edges(frames, scene, cfg.camera, edge_config, f"{s.env} seed {s.seed}", cfg.sensor is None)


def frames_from_arrays(
    arrays: Mapping[str, np.ndarray],
    max_range_m: float,
    scene: Scene | None = None,
    camera: CameraConfig | None = None,
    edge_config: EdgeConfig = DEFAULT_EDGES,
    title: str = "",
    info: dict | None = None,
) -> TrialFrames:
    """A recorded trajectory as trial frames.

    ``arrays`` holds the dataset row fields of one trajectory: ``depth`` (T, 60, 90) normalised float
    (or uint8 = round(255 depth)), ``desired_speed`` (T,), ``quat`` (T, 4), ``time`` (T,),
    ``position`` (T, 3) and optionally ``velocity_cmd`` (T, 3). With ``scene`` (and the ``camera`` that
    recorded it) the edges are exact when the re-render reproduces the frames.
    """
    depth = np.asarray(arrays["depth"])
    depth = depth.astype(np.float32) / np.float32(255.0) if depth.dtype == np.uint8 else depth.astype(np.float32)
    command = arrays.get("velocity_cmd")
    frames = TrialFrames(
        depth=depth,
        desired_speed=np.asarray(arrays["desired_speed"], dtype=np.float64).reshape(-1),
        quat=np.asarray(arrays["quat"], dtype=np.float64),
        time=np.asarray(arrays["time"], dtype=np.float64).reshape(-1),
        position=np.asarray(arrays["position"], dtype=np.float64),
        command=None if command is None else np.asarray(command, dtype=np.float64),
        title=title,
        info={"source": "recorded", **(info or {})},
    )
    camera = replace(camera or CameraConfig(), max_range_m=float(max_range_m))
    return _attach_edges(frames, scene, camera, edge_config, title or "recorded trajectory")


def scene_from_dataset_config(config: Mapping, env: str, seed: int) -> tuple[Scene | None, CameraConfig | None]:
    """The scene and camera of a trajectory written by ``vitfly collect`` (its file's ``config`` attribute).

    (None, None) when the file does not say how it was made (e.g. imported from the original dataset).
    """
    collect = config.get("collect") if isinstance(config, Mapping) else None
    if not isinstance(collect, Mapping) or "preset" not in collect:
        return None, None
    camera_fields = {f.name for f in fields(CameraConfig)}
    camera_cfg = collect.get("camera") if isinstance(collect.get("camera"), Mapping) else {}
    try:
        camera = CameraConfig(**{k: v for k, v in camera_cfg.items() if k in camera_fields})
        return make_scene(env, str(collect["preset"]), int(seed)), camera
    except (VitflyError, TypeError, ValueError):
        return None, None
