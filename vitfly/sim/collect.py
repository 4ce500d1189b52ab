"""Expert data collection: fly the privileged expert and append trajectories to an HDF5 dataset.

Trajectory k's scene seed and desired speed derive only from (config.seed, k), trajectories are
written in index order, and each one is flown in isolation, so the file is the same whatever the
number of worker processes. Each append is atomic (``vitfly.datamodules.schema.TrajectoryWriter``):
after a kill -9, running the same collection again skips the committed trajectories and goes on.

Which ticks are written: as the original (``run_competition.py``, ``data_collection_xrange``), only
those with 2 < x < 60 m (``log_x_range_m``), so the take-off ramp's overridden labels stay out of
the training data; ``log_every_tick`` keeps every tick. The flight itself is the same either way:
a trajectory's ``n_collisions`` and ``success`` describe the whole flight, start to end, while the
per-row ``collision`` flags cover the logged ticks only. A flight that never enters the window
keeps its last tick, so that trajectory k is still entry k of the file. The file's root attributes
``camera`` and ``control_hz`` record the sensor geometry and rate.

Example::

    cfg = load_collect_config("configs/collect/spheres.yaml", overrides={"trajectories": 10})
    summary = collect(cfg, "data/spheres.h5")
    summary.trajectories, summary.frames, summary.success_by_speed
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import json
import os
import signal
import sys
import time
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from multiprocessing import get_all_start_methods, get_context
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vitfly.datamodules.schema import TrajectoryRecord, TrajectoryWriter, check_depth_compression, encode_depth
from vitfly.errors import VitflyError
from vitfly.packaged import config_path
from vitfly.sim.camera import CameraConfig, expand_camera_preset
from vitfly.sim.engine import SimEngine, fly
from vitfly.sim.policies import ExpertPolicy
from vitfly.sim.rollout import EpisodeResult, RolloutConfig, TaskConfig
from vitfly.sim.scenes import ENVS, make_scene, scene_config
from vitfly.sim.sensor_models import StereoDepthConfig, sensor_from_dict


@dataclass(frozen=True)
class CollectConfig:
    """How a dataset is made. Every field can be set in the YAML; some also by flags."""

    env: str = "spheres"
    preset: str = "medium"
    trajectories: int = 100
    speeds: tuple[float, float] = (3.0, 7.0)  # m/s, each trajectory's speed uniform in [min, max]
    seed: int = 0
    workers: int = 1
    physics_hz: float = 240.0
    control_hz: float = 30.0
    timeout_s: float = 40.0
    body_radius_m: float = 0.0
    depth_compression: str = "none"  # "none" streams fastest in training; "gzip" is ~2.8x smaller
    camera: CameraConfig = field(default_factory=CameraConfig)
    # ticks written: only while log_x_range_m[0] < x < log_x_range_m[1] (m, the original's window),
    # or every tick of the flight with log_every_tick
    log_x_range_m: tuple[float, float] = (2.0, 60.0)
    log_every_tick: bool = False
    physics: str = "auto"  # "pybullet", "native" or "auto"; stored concrete (resolve_physics) with the data
    # a stereo sensor model on the camera's render (YAML ``sensor: {model: d435, ...}``, flag --sensor); None: ideal
    sensor: StereoDepthConfig | None = None
    # the simulator engine (vitfly.sim.engine): "numpy", or "batched" flying num_envs trajectories in lockstep
    # on sim_device in sim_dtype; stored with the data when batched
    sim: str = "numpy"
    sim_device: str = "cpu"
    sim_dtype: str = "float64"
    sim_compile: bool = False  # the batched engine's kernels through torch.compile
    num_envs: int = 8  # the batched engine's lockstep batch (the data does not depend on it)

    @property
    def engine(self) -> SimEngine:
        return SimEngine(self.sim, self.sim_device, self.sim_dtype, self.sim_compile)

    def validate(self, source: str = "config") -> CollectConfig:
        if self.env not in ENVS:
            raise VitflyError(f"{source}: field env is {self.env!r}; expected one of {', '.join(ENVS)}")
        scene_config(self.env, self.preset)  # raises on an unknown preset
        lo, hi = self.speeds
        if not (0 < lo <= hi):
            raise VitflyError(f"{source}: field speeds is [{lo}, {hi}]; expected 0 < min <= max (m/s)")
        if self.trajectories < 1:
            raise VitflyError(f"{source}: field trajectories is {self.trajectories}; expected >= 1")
        for name in ("workers", "num_envs"):
            if getattr(self, name) < 1:
                raise VitflyError(f"{source}: field {name} is {getattr(self, name)}; expected >= 1")
        self.engine.validate(source)
        if self.engine.batched and self.workers > 1:  # one process batches the trajectories on one device
            raise VitflyError(f"{source}: field workers is {self.workers} with sim batched, which flies num_envs "
                              "trajectories at once in one process; use workers 1")
        if self.engine.batched and self.sensor is not None:  # the batched camera has no sensor model yet
            raise VitflyError(f"{source}: field sensor: sensor models run on the numpy engine only (sim: numpy)")
        check_depth_compression(self.depth_compression, f"{source}: field depth_compression")
        x0, x1 = self.log_x_range_m
        if not x0 < x1:
            raise VitflyError(f"{source}: field log_x_range_m is [{x0}, {x1}]; expected min < max (m)")
        self.engine.physics(self.physics, f"{source}: field physics")
        try:
            self.rollout_config().physics_steps_per_tick  # noqa: B018 - validates the rates
            self.camera.validate("camera.")
        except ValueError as err:
            raise VitflyError(f"{source}: {err}") from None
        return self

    def logged_ticks(self, x: np.ndarray) -> np.ndarray:
        """Indices of the ticks to write, given each tick's x position (m)."""
        if self.log_every_tick:
            return np.arange(len(x))
        lo, hi = self.log_x_range_m
        keep = np.flatnonzero((x > lo) & (x < hi))
        return keep if len(keep) else np.arange(len(x))[-1:]

    def rollout_config(self) -> RolloutConfig:
        return RolloutConfig(
            physics_hz=self.physics_hz,
            control_hz=self.control_hz,
            task=TaskConfig(timeout_s=self.timeout_s, body_radius_m=self.body_radius_m),
            camera=self.camera,
            record_depth=True,
            physics=self.physics,
            sensor=self.sensor,
        )

    def content_key(self) -> dict:
        """The fields that decide the data (not how many trajectories, workers, nor the storage)."""
        d = dataclasses.asdict(self)
        for key in ("trajectories", "workers", "depth_compression", "num_envs", "sim", "sim_device", "sim_dtype",
                    "sim_compile"):
            d.pop(key)
        if self.engine.batched:  # absent for the numpy engine: its datasets keep the bytes of before the choice
            d["sim"] = self.engine.key()
        d["speeds"] = list(d["speeds"])
        d["log_x_range_m"] = list(d["log_x_range_m"])
        d["camera"]["mount_offset_m"] = list(d["camera"]["mount_offset_m"])
        if d["sensor"] is None:  # the ideal camera: the key of files from before sensor models
            d.pop("sensor")
        return d


def load_collect_config(path: str | os.PathLike | None, overrides: dict[str, Any] | None = None) -> CollectConfig:
    """Read a collect YAML (safe loader; a path, or a shipped config's name such as ``collect/spheres``), apply
    ``overrides`` (flags; None values ignored), validate."""
    data: dict[str, Any] = {}
    path = config_path(path) if path is not None else None
    source = str(path) if path is not None else "collect config"
    if path is not None:
        try:
            with open(path) as f:
                data = yaml.safe_load(f) or {}
        except FileNotFoundError:
            raise VitflyError(f"{path}: config file not found") from None
        except yaml.YAMLError as err:
            raise VitflyError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from None
        if not isinstance(data, dict):
            raise VitflyError(f"{path}: expected a mapping of collect settings at the top level")
    for key, value in (overrides or {}).items():
        if value is not None:
            data[key] = value
    config = _from_mapping(CollectConfig, data, source, "").validate(source)
    return dataclasses.replace(config, physics=config.engine.physics(config.physics, f"{source}: field physics"))


def _from_mapping(cls, data: dict, source: str, prefix: str):
    """Build dataclass ``cls`` from a mapping, naming any unknown or mistyped key."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in fields:
            raise VitflyError(f"{source}: unknown key '{prefix}{key}'; expected one of {', '.join(sorted(fields))}")
        default = getattr(cls(), key)
        name = f"{prefix}{key}"
        if cls is CollectConfig and key == "sensor":
            try:
                kwargs[key] = sensor_from_dict(value, "sensor.")
            except ValueError as err:
                raise VitflyError(f"{source}: {err}") from None
        elif default is None:  # optional number (e.g. camera.horizontal_fov_deg): null keeps None
            kwargs[key] = None if value is None else _number(value, float, source, name)
        elif dataclasses.is_dataclass(default):
            if not isinstance(value, dict):
                raise VitflyError(f"{source}: field {name} must be a mapping")
            if isinstance(default, CameraConfig):  # camera: {preset: NAME, ...} -> the preset's fields
                try:
                    value = expand_camera_preset(value, f"{name}.")
                except ValueError as err:
                    raise VitflyError(f"{source}: {err}") from None
            kwargs[key] = _from_mapping(type(default), value, source, f"{name}.")
        elif isinstance(default, tuple):
            if not isinstance(value, list | tuple) or len(value) != len(default):
                raise VitflyError(f"{source}: field {name} must be a list of {len(default)} numbers")
            kwargs[key] = tuple(_number(v, type(default[0]), source, name) for v in value)
        else:
            kwargs[key] = _number(value, type(default), source, name)
    return cls(**kwargs)


def _number(value, kind: type, source: str, name: str):
    if kind is bool:
        if not isinstance(value, bool):
            raise VitflyError(f"{source}: field {name} must be true or false, got {value!r}")
        return value
    if kind is str:
        if not isinstance(value, str):
            raise VitflyError(f"{source}: field {name} must be a string, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise VitflyError(f"{source}: field {name} must be a number, got {value!r}")
    if kind is int:
        if float(value) != int(value):
            raise VitflyError(f"{source}: field {name} must be a whole number, got {value!r}")
        return int(value)
    return float(value)


def stored_collect_key(stored: dict | None) -> dict | None:
    """A dataset's ``config.collect`` as :meth:`CollectConfig.content_key` writes it today (files from
    before the physics field were all flown by pybullet)."""
    return {**stored, "physics": stored.get("physics", "pybullet")} if isinstance(stored, dict) else stored


def trajectory_spec(seed: int, index: int, speeds: tuple[float, float]) -> tuple[int, float]:
    """(scene seed, desired speed m/s) of trajectory ``index``; depends only on (seed, index)."""
    rng = np.random.default_rng([int(seed), int(index)])
    scene_seed = int(rng.integers(0, 2**31 - 1))
    speed = round(float(rng.uniform(speeds[0], speeds[1])), 2)
    return scene_seed, speed


def fly_trajectory(config: CollectConfig, index: int) -> TrajectoryRecord:
    """Fly the expert on trajectory ``index`` of ``config`` and return its dataset record."""
    return fly_trajectories(config, [index])[0]


def fly_trajectories(config: CollectConfig, indices: list[int]) -> list[TrajectoryRecord]:
    """Fly the expert on trajectories ``indices`` of ``config`` in lockstep on its engine; their records in order.

    Each trajectory's flight depends on its own scene and speed only (and its camera draws on its scene
    seed), so flying them together gives what flying each alone gives.
    """
    specs = [trajectory_spec(config.seed, k, config.speeds) for k in indices]
    scenes = [make_scene(config.env, config.preset, scene_seed) for scene_seed, _ in specs]
    results = fly(scenes, [speed for _, speed in specs], ExpertPolicy(), config.rollout_config(),
                  engine=config.engine)
    return [_record(config, speed, result) for (_, speed), result in zip(specs, results, strict=True)]


def _record(config: CollectConfig, speed: float, result: EpisodeResult) -> TrajectoryRecord:
    """A flown trajectory's dataset record: the logged ticks, and the whole flight's outcome."""
    log, summary = result.log, result.summary
    rows = config.logged_ticks(log.position[:, 0])
    return TrajectoryRecord(
        depth=encode_depth(log.depth[rows]),
        desired_speed=speed,
        quat=log.quat[rows],
        position=log.position[rows],
        velocity=log.velocity[rows],
        velocity_cmd=log.command[rows],
        time=log.time[rows],
        collision=log.contact[rows],
        env=config.env,
        seed=result.scene.seed,
        n_collisions=summary.n_collisions,  # the whole flight, not only the logged ticks
        success=summary.success,
    )


@dataclass
class CollectSummary:
    """What a collection run left in the file (all trajectories, including resumed ones)."""

    path: str
    trajectories: int
    frames: int
    new_trajectories: int
    wall_s: float
    success_by_speed: dict[float, tuple[int, int]]  # speed bin (m/s, nearest 1) -> (successes, trials)


def _ready(_: int) -> bool:
    return True


def _die_with_parent() -> None:
    """Worker initializer: on Linux, ask the kernel to kill this worker when the parent dies, so a
    kill -9 of `vitfly collect` leaves no orphans flying trajectories nobody will write."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def start_pool(workers: int) -> ProcessPoolExecutor | None:
    """Worker processes for ``workers`` > 1, all started now.

    Called before any HDF5 file is opened and before the progress bar's thread starts, so on Linux
    the workers can be forked (copies of this process: no re-imports, nothing open to corrupt).
    """
    if workers <= 1:
        return None
    method = "fork" if "fork" in get_all_start_methods() else "spawn"
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=get_context(method), initializer=_die_with_parent)
    list(pool.map(_ready, range(workers)))
    return pool


def ordered_records(
    config: CollectConfig, indices: list[int], pool: ProcessPoolExecutor | None
) -> Iterator[TrajectoryRecord]:
    """Records for ``indices`` in index order, flown here or by the pool's workers (the batched engine:
    ``num_envs`` at a time, here)."""
    if config.engine.batched:
        for start in range(0, len(indices), config.num_envs):
            yield from fly_trajectories(config, indices[start : start + config.num_envs])
        return
    if pool is None:
        for k in indices:
            yield fly_trajectory(config, k)
        return
    pending: dict[int, Future] = {}
    queue = iter(indices)
    done_buffer: dict[int, TrajectoryRecord] = {}
    for k in queue:  # prime: a bounded number in flight keeps memory flat
        pending[k] = pool.submit(fly_trajectory, config, k)
        if len(pending) >= 2 * config.workers:
            break
    for want in indices:
        while want not in done_buffer:
            finished, _ = wait(list(pending.values()), return_when=FIRST_COMPLETED)
            for k in [k for k, fut in pending.items() if fut in finished]:
                done_buffer[k] = pending.pop(k).result()
                nxt = next(queue, None)
                if nxt is not None:
                    pending[nxt] = pool.submit(fly_trajectory, config, nxt)
        yield done_buffer.pop(want)


def collect(config: CollectConfig, out: str | os.PathLike, progress: bool = True) -> CollectSummary:
    """Fly ``config.trajectories`` expert trajectories into ``out`` (created, or resumed)."""
    out = Path(out)
    config.validate()
    config = dataclasses.replace(config, physics=config.engine.physics(config.physics))  # the dataset names it
    meta = {"made_by": "vitfly collect", "collect": config.content_key()}
    start = time.perf_counter()
    pool = start_pool(config.workers)
    try:
        return _collect_into(config, out, meta, pool, progress, start)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)


def _collect_into(config: CollectConfig, out: Path, meta: dict, pool, progress: bool, start: float) -> CollectSummary:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    frames = _existing_frames(out)
    with TrajectoryWriter(
        out,
        config=meta,
        depth_max_m=config.camera.max_range_m,
        depth_compression=config.depth_compression,
        camera=dataclasses.asdict(config.camera),
        control_hz=config.control_hz,
    ) as writer:
        stored = stored_collect_key(writer.config.get("collect"))
        if stored is not None and stored != json.loads(json.dumps(meta["collect"])):
            raise VitflyError(
                f"{out}: was collected with different settings (attribute config.collect); "
                "rerun with the same config to resume, or choose another --out"
            )
        done = writer.num_trajectories
        expected = [trajectory_spec(config.seed, k, config.speeds)[0] for k in range(done)]
        if writer.seeds() != expected:
            raise VitflyError(f"{out}: its trajectory seeds do not match --seed {config.seed}; choose another --out")
        todo = list(range(done, config.trajectories))
        new = 0
        with Progress(
            TextColumn("[bold]collect[/] {task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("trajectories, {task.fields[frames]} frames"),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            console=Console(stderr=True),
            disable=not progress,
        ) as bar:
            task = bar.add_task(config.env, total=config.trajectories, completed=done, frames=frames)
            for rec in ordered_records(config, todo, pool):
                writer.append(rec)
                new += 1
                frames += rec.length
                bar.update(task, advance=1, frames=frames)
    return summarize(out, new, time.perf_counter() - start)


def _existing_frames(path: Path) -> int:
    """Frames already committed in ``path`` (0 if it does not exist; the writer reports bad files)."""
    if not path.exists():
        return 0
    try:
        return summarize(path).frames
    except (VitflyError, OSError):
        return 0


def summarize(path: str | os.PathLike, new_trajectories: int = 0, wall_s: float = 0.0) -> CollectSummary:
    """Counts and expert success rate per 1 m/s speed bin of a collected dataset."""
    from vitfly.datamodules.schema import open_trajectories

    with open_trajectories(path, check_values=False) as data:
        n = len(data)
        frames = int(np.sum(data.lengths)) if n else 0
        by_speed: dict[float, list[int]] = {}
        for m in range(n):
            meta = data.meta(m)
            key = float(round(float(meta["desired_speed"])))
            s = by_speed.setdefault(key, [0, 0])
            s[0] += int(bool(meta["success"]))
            s[1] += 1
    return CollectSummary(
        path=str(path),
        trajectories=n,
        frames=frames,
        new_trajectories=new_trajectories,
        wall_s=wall_s,
        success_by_speed={k: (v[0], v[1]) for k, v in sorted(by_speed.items())},
    )
