"""The sensor a policy flies with: by default the one it was trained with, as its checkpoint records it.

A checkpoint written by ``vitfly fit`` stores the training dataset's sensor as plain values
(``vitfly.zoo.checkpoint``: ``depth_max_m``, ``camera`` dict, ``control_hz``). Here those values
become the simulator's ``CameraConfig`` and control rate. Explicit settings (``--camera``,
``--control-hz``, ``--depth-max-m`` or the same fields in the YAML) that contradict the checkpoint
are one clear error unless ``override_sensor`` is set; what the checkpoint does not record (older
checkpoints, datasets without the attributes, original-project weights) comes from the explicit
settings or vitfly's defaults, and the one-line note says which.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from vitfly.errors import VitflyError
from vitfly.eval.config import SweepConfig
from vitfly.sim.camera import CameraConfig, expand_camera_preset
from vitfly.zoo.checkpoint import sensor_conflicts

SENSOR_OPTIONS = {"depth_max_m": "--depth-max-m", "control_hz": "--control-hz", "camera": "--camera"}


def _default_control_hz() -> float:
    from vitfly.sim.rollout import RolloutConfig

    return float(RolloutConfig().control_hz)


def expand_preset(values: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The camera fields of ``values``, with ``preset: NAME`` (``vitfly.sim.camera.CAMERA_PRESETS``) replaced by
    that preset's geometry; the fields given beside it win. An unknown name is one VitflyError line."""
    try:
        return expand_camera_preset(values, "camera.")
    except ValueError as err:
        raise VitflyError(f"{source}: {err}") from None


def camera_from_dict(values: Mapping[str, Any], source: str) -> CameraConfig:
    """A ``CameraConfig`` from a plain dict of its fields (JSON lists become tuples; ``preset: NAME`` gives that
    preset's geometry); the fields not given keep their defaults. An unknown field or a value the camera refuses
    is one VitflyError line."""
    values = expand_preset(values, source)
    known = [f.name for f in dataclasses.fields(CameraConfig)]
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise VitflyError(
            f"{source}: camera field {unknown[0]!r} is not a setting of this vitfly's camera; known: {', '.join(known)}"
        )
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    try:
        camera = CameraConfig(**kwargs)
        check = getattr(camera, "validate", None)
        return check(source) if check is not None else camera
    except (TypeError, ValueError) as err:
        raise VitflyError(f"{source}: camera settings do not fit this vitfly's camera ({err})") from None


def camera_dict(camera: CameraConfig) -> dict[str, Any]:
    """Plain JSON-able values of a camera (tuples as lists), the form datasets and checkpoints store."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(camera).items()}


def flight_sensor(cfg: SweepConfig) -> tuple[CameraConfig, float]:
    """(camera, control rate in Hz) a sweep flies with: its resolved settings, else vitfly's defaults."""
    camera = camera_from_dict(cfg.camera or {}, "camera")
    if cfg.depth_max_m is not None:
        camera = dataclasses.replace(camera, max_range_m=float(cfg.depth_max_m))
    return camera, float(cfg.control_hz) if cfg.control_hz is not None else _default_control_hz()


def _explicit(cfg: SweepConfig) -> dict[str, Any]:
    out: dict[str, Any] = {k: getattr(cfg, k) for k in ("depth_max_m", "control_hz") if getattr(cfg, k) is not None}
    if cfg.camera:  # a preset stands for its fields, so that they are compared with the checkpoint's
        camera = expand_preset(cfg.camera, "--camera")
        out["camera"] = {k: list(v) if isinstance(v, tuple) else v for k, v in camera.items()}
    return out


def _summary(camera: CameraConfig, control_hz: float) -> str:
    settings = ", ".join(f"{k}={v}" for k, v in camera_dict(camera).items() if k != "max_range_m")
    return f"depth range {camera.max_range_m:g} m, control {control_hz:g} Hz, camera {settings}"


def resolve_sensor(cfg: SweepConfig, trained: Mapping | None, source: str) -> tuple[SweepConfig, str]:
    """The sweep config with ``camera`` (every field), ``control_hz`` and ``depth_max_m`` filled in, and a one-line
    note of where they came from.

    trained: the checkpoint's sensor ({depth_max_m, camera, control_hz}, None when it records none); source: the
    checkpoint's path, for the messages. Raises VitflyError when an explicit setting contradicts it (unless
    ``cfg.override_sensor``), or when the settings do not make a valid camera and rate.
    """
    from vitfly.sim.rollout import RolloutConfig

    explicit = _explicit(cfg)
    trained = dict(trained) if trained is not None else None
    conflicts: list[str] = []
    values: dict[str, Any] = {"camera": {}}
    if trained is not None:
        if trained.get("camera") is not None:
            camera_from_dict(trained["camera"], f"{source} (sensor.camera)")  # unknown fields: one clear line
            values["camera"] = dict(trained["camera"])
        values["depth_max_m"] = trained["depth_max_m"]
        if trained.get("control_hz") is not None:
            values["control_hz"] = trained["control_hz"]
        given = {**explicit, "camera": {**values["camera"], **explicit.get("camera", {})}}
        conflicts = sensor_conflicts(trained, given)
        if conflicts and not cfg.override_sensor:
            option = SENSOR_OPTIONS[conflicts[0].split(":")[0].split(".")[0]]
            raise VitflyError(
                f"{option} contradicts {source}, which was trained with another sensor ({'; '.join(conflicts)}, "
                "checkpoint vs option): drop the option to fly with the checkpoint's sensor, or add --override-sensor"
            )
    values["camera"].update(explicit.get("camera", {}))
    values.update({k: v for k, v in explicit.items() if k != "camera"})
    if values.get("depth_max_m") is not None:  # the depth range is the camera's normalisation range
        values["camera"]["max_range_m"] = values["depth_max_m"]
    camera, control_hz = flight_sensor(
        dataclasses.replace(cfg, camera=values["camera"], control_hz=values.get("control_hz"), depth_max_m=None)
    )
    try:  # the physics rate must be a multiple of the control rate
        RolloutConfig(control_hz=control_hz).physics_steps_per_tick  # noqa: B018 (raises ValueError if not)
    except ValueError as err:
        raise VitflyError(f"--control-hz: {err}") from None
    resolved = dataclasses.replace(cfg, camera=camera_dict(camera), control_hz=control_hz,
                                   depth_max_m=camera.max_range_m)  # fmt: skip
    return resolved, _note(trained, explicit, conflicts, source, _summary(camera, control_hz))


def _note(trained: dict | None, explicit: dict, conflicts: list[str], source: str, flown: str) -> str:
    options = f"the options ({', '.join(sorted(explicit))}) and the defaults" if explicit else "the defaults"
    if trained is None:
        return f"sensor: {source} does not record the sensor it was trained with; flying with {options}: {flown}"
    if conflicts:
        return f"sensor: --override-sensor: flying {source} with another sensor than it was trained with: {flown}"
    unknown = [k for k in ("camera", "control_hz") if trained.get(k) is None]
    if unknown:
        return (f"sensor: {source} records its depth range but not its {' or '.join(unknown)} (its dataset did not); "
                f"those from {options}: {flown}")  # fmt: skip
    given = f" and the options ({', '.join(sorted(explicit))}), which agree" if explicit else ""
    return f"sensor: flying {source} with the sensor it was trained with{given}: {flown}"


__all__ = ["camera_dict", "camera_from_dict", "flight_sensor", "resolve_sensor"]
