"""vitfly checkpoints: save a network so that the rest of vitfly loads it by path alone.

Format (contract 2 in the conventions; the same shape as Lightning checkpoints written by ``vitfly fit``):
a dict saved with ``torch.save`` holding ``state_dict`` (the network's entries prefixed ``net.``),
``hyper_parameters`` = {``model``: registry name, ``use_state``: bool, ``model_kwargs``: dict} and
``pytorch-lightning_version`` (so Lightning's ``load_from_checkpoint`` accepts it), and ``vitfly`` =
{``format``, ``version``, ``vitfly_version``: the vitfly that wrote it, plus provenance}. Everything loads with
``torch.load(..., weights_only=True)``.

``sensor`` (optional, top level): what the network was trained to see, as plain values taken from the
training dataset: ``depth_max_m`` (m that normalised depth 1 stands for), ``camera`` (the dataset's
camera settings, a dict, or None when the dataset did not record them) and ``control_hz`` (the rate
of the recorded control ticks and frames, or None). The zoo stores and checks these; what a camera
dict means is the simulator's business (``vitfly.eval.sensor``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping

import torch
from torch import nn

from vitfly import __version__
from vitfly.atomic import atomic_path
from vitfly.errors import VitflyError
from vitfly.zoo.legacy import check_state_dict, identify_architecture, read_torch_file
from vitfly.zoo.registry import create_model, list_models

NET_PREFIX = "net."
CHECKPOINT_FORMAT = "vitfly.checkpoint"
CHECKPOINT_VERSION = 1
SENSOR_KEY = "sensor"
SENSOR_FIELDS = ("depth_max_m", "camera", "control_hz")


def _positive(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def check_sensor(sensor: object, source: str) -> dict | None:
    """A checkpoint's ``sensor`` entry as a plain dict (None stays None); one-line VitflyError if malformed."""
    if sensor is None:
        return None
    if not isinstance(sensor, Mapping) or set(sensor) - set(SENSOR_FIELDS):
        raise VitflyError(f"{source}: entry 'sensor' must be a dict with keys {', '.join(SENSOR_FIELDS)}")
    depth_max, camera, rate = (sensor.get(k) for k in SENSOR_FIELDS)
    if not _positive(depth_max):
        raise VitflyError(f"{source}: sensor.depth_max_m is {depth_max!r}, expected a positive number of metres")
    if camera is not None and not isinstance(camera, Mapping):
        raise VitflyError(f"{source}: sensor.camera must be a dict of camera settings or null, got {camera!r:.60}")
    if rate is not None and not _positive(rate):
        raise VitflyError(f"{source}: sensor.control_hz is {rate!r}, expected a positive number of Hz or null")
    return {
        "depth_max_m": float(depth_max),
        "camera": None if camera is None else dict(camera),
        "control_hz": None if rate is None else float(rate),
    }


def read_sensor(checkpoint: Mapping, source: str) -> dict | None:
    """The ``sensor`` entry of a checkpoint dict (None when it has none)."""
    return check_sensor(checkpoint.get(SENSOR_KEY), source)


def load_sensor(path: str | os.PathLike) -> dict | None:
    """The sensor a checkpoint file was trained with; None for a checkpoint without one (older vitfly
    checkpoints, original-project state dicts)."""
    obj = read_torch_file(path)
    return read_sensor(obj, os.fspath(path)) if isinstance(obj, Mapping) and "state_dict" in obj else None


def _same_value(a: object, b: object) -> bool:
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in (a, b))
    if numbers:
        return math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-9)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same_value(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def sensor_conflicts(stored: Mapping | None, current: Mapping | None) -> list[str]:
    """What differs between two sensors, as "field: stored vs current" (fields unknown on either side are not
    compared; numbers compare with a relative tolerance of 1e-6)."""
    if not stored or not current:
        return []
    out = []
    for key in ("depth_max_m", "control_hz"):
        a, b = stored.get(key), current.get(key)
        if a is not None and b is not None and not _same_value(a, b):
            out.append(f"{key}: {a} vs {b}")
    cam_a, cam_b = stored.get("camera"), current.get("camera")
    if cam_a is not None and cam_b is not None:
        for key in sorted(set(cam_a) | set(cam_b)):
            if not _same_value(cam_a.get(key), cam_b.get(key)):
                out.append(f"camera.{key}: {cam_a.get(key)} vs {cam_b.get(key)}")
    return out


def vitfly_stamp(metadata: Mapping | None = None) -> dict:
    """The checkpoint's ``vitfly`` entry: format, format version, the vitfly version writing it, ``metadata``."""
    return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "vitfly_version": __version__,
            **dict(metadata or {})}


def _lightning_version() -> str:
    try:
        import lightning

        return lightning.__version__
    except ImportError:  # lightning is a dependency, but the zoo must not need it to save weights
        return "2.0.0"


def save_checkpoint(
    net: nn.Module,
    name: str,
    use_state: bool,
    path: str | os.PathLike,
    model_kwargs: Mapping | None = None,
    metadata: Mapping | None = None,
    sensor: Mapping | None = None,
) -> None:
    """Write ``net`` (registered as ``name``) as a vitfly checkpoint at ``path``, atomically.

    ``model_kwargs`` are the builder's extra keyword arguments (plain values); ``metadata`` (plain values)
    is stored under ``vitfly`` for provenance (e.g. the original file it was converted from); ``sensor``
    ({depth_max_m, camera, control_hz}, see the module docstring) when the training sensor is known.
    """
    if name not in list_models():
        raise VitflyError(f"unknown model {name!r}; known models: {', '.join(list_models())}")
    path = os.fspath(path)
    checkpoint = {
        "state_dict": {NET_PREFIX + k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
        "hyper_parameters": {"model": name, "use_state": bool(use_state), "model_kwargs": dict(model_kwargs or {})},
        "pytorch-lightning_version": _lightning_version(),
        "vitfly": vitfly_stamp(metadata),
    }
    sensor = check_sensor(sensor, "save_checkpoint(sensor=...)")
    if sensor is not None:
        checkpoint[SENSOR_KEY] = sensor
    with atomic_path(path) as tmp:
        torch.save(checkpoint, tmp)


def network_hparams(checkpoint: Mapping, source: str) -> dict:
    """The network a vitfly/Lightning checkpoint dict holds: {model (registry name), use_state, model_kwargs}."""
    hparams = checkpoint.get("hyper_parameters")
    if not isinstance(hparams, Mapping) or "model" not in hparams:
        raise VitflyError(f"{source}: checkpoint has no hyper_parameters.model (the registry name of the network)")
    name = hparams["model"]
    if not isinstance(name, str):
        raise VitflyError(f"{source}: hyper_parameters.model must be a registry name (str), got {type(name).__name__}")
    if name not in list_models():
        known = ", ".join(list_models())
        raise VitflyError(f"{source}: hyper_parameters.model {name!r} is not a known model; known: {known}")
    model_kwargs = hparams.get("model_kwargs") or {}
    if not isinstance(model_kwargs, Mapping):
        raise VitflyError(f"{source}: hyper_parameters.model_kwargs must be a dict, got {type(model_kwargs).__name__}")
    return {"model": name, "use_state": bool(hparams.get("use_state", True)), "model_kwargs": dict(model_kwargs)}


def network_from_checkpoint_dict(checkpoint: Mapping, source: str) -> nn.Module:
    """Build and load the network described by a vitfly/Lightning checkpoint dict (eval mode)."""
    hparams = network_hparams(checkpoint, source)
    name, model_kwargs = hparams["model"], hparams["model_kwargs"]
    try:
        net = create_model(name, use_state=hparams["use_state"], **model_kwargs)
    except TypeError as err:
        raise VitflyError(f"{source}: hyper_parameters.model_kwargs do not fit model {name!r}: {err}") from None
    state_dict = checkpoint.get("state_dict")
    if not isinstance(state_dict, Mapping):
        raise VitflyError(f"{source}: checkpoint has no state_dict")
    net_state = {k[len(NET_PREFIX) :]: v for k, v in state_dict.items() if k.startswith(NET_PREFIX)}
    if not net_state:
        raise VitflyError(f"{source}: state_dict has no 'net.' entries (expected the network's parameters as net.*)")
    net.load_state_dict(check_state_dict(net, net_state, name, source))
    return net.eval()


def load_network(path: str | os.PathLike, arch: str | None = None) -> nn.Module:
    """The network stored at ``path``, in eval mode.

    Accepts vitfly checkpoints (``save_checkpoint``, ``vitfly convert-checkpoint``), Lightning
    checkpoints written by ``vitfly fit``, and original-project state dicts: with ``arch`` given, or
    recognised from their keys and shapes when ``arch`` is None.
    """
    source = os.fspath(path)
    obj = read_torch_file(path)
    if isinstance(obj, Mapping) and "state_dict" in obj:
        net = network_from_checkpoint_dict(obj, source)
        stored = obj["hyper_parameters"]["model"]
        if arch is not None and stored != arch:
            raise VitflyError(f"{source}: holds a {stored!r} network, but architecture {arch!r} was asked for")
        return net
    if arch is None:
        if isinstance(obj, Mapping) and obj and all(isinstance(v, torch.Tensor) for v in obj.values()):
            arch = identify_architecture(obj)
            if arch is None:
                raise VitflyError(
                    f"{source}: a state dict that matches no registered architecture; pass the architecture "
                    f"name ({', '.join(list_models())}) to see which keys do not fit"
                )
        else:
            raise VitflyError(
                f"{source}: neither a vitfly checkpoint (a dict with state_dict and hyper_parameters) "
                f"nor a state dict (got {type(obj).__name__})"
            )
    net = create_model(arch)
    net.load_state_dict(check_state_dict(net, obj, arch, source))
    return net.eval()
