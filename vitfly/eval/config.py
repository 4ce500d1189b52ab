"""Typed configuration of an evaluation sweep, from YAML (safe loader) with command-line overrides."""

from __future__ import annotations

import dataclasses
import re
import types
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path

from vitfly.errors import VitflyError
from vitfly.packaged import config_path, read_yaml
from vitfly.sim.scenes import ENVS

# inference back ends of learned policies: eager PyTorch, ONNX Runtime float32, ONNX Runtime with int8 products
BACKENDS = ("eager", "compiled", "onnxruntime", "onnxruntime-int8")  # compiled: eager with torch.compile


@dataclass
class SweepConfig:
    """One policy flown over envs x speeds x trials. Units: m/s for speeds, s for times."""

    policy: str = "expert"  # a checkpoint path, "pretrained:NAME", "modular:NAME", "expert" or "straight"
    planner_config: str | None = None  # modular:NAME: planners YAML (default: the shipped configs/planners.yaml)
    arch: str | None = None  # architecture of an original-project checkpoint
    name: str | None = None  # label in reports; default: "expert", "straight", NAME of pretrained:/modular:NAME or the
    # checkpoint's stem
    env: list[str] = field(default_factory=lambda: ["spheres"])
    preset: str = "medium"  # scene density preset
    speeds: list[float] = field(default_factory=lambda: [3.0, 4.0, 5.0, 6.0, 7.0])
    trials: int = 10  # per (env, speed)
    seed: int = 0  # scene seeds derive from (seed, env, trial index): every policy sees the same scenes
    out: str = "runs/eval"
    num_envs: int = 8  # scenes stepped in lockstep (one batched policy call per tick)
    workers: int = 1  # processes
    shard: str | None = None  # "i/n": this process runs shard i (0-based) of n
    device: str = "cpu"  # learned policies' network: "cpu" or "cuda[:N]"
    threads: int = 1  # torch threads per worker
    backend: str = "eager"  # learned policies: one of BACKENDS
    physics: str = "auto"  # rigid-body back end: "pybullet", "native" or "auto" (made concrete by validate)
    sim: str = "numpy"  # simulator engine: "numpy" or "batched" (vitfly.sim.engine; physics native)
    sim_device: str = "cpu"  # the batched engine's device: "cpu" or "cuda[:N]"
    sim_dtype: str = "float64"  # the batched engine's precision: "float64" (exact) or "float32"
    sim_compile: bool = False  # the batched engine's kernels through torch.compile (faster on a CPU after seconds)
    timeout_s: float | None = None  # per trial; default scales with speed (sim's default)
    # the sensor flown with (vitfly.eval.sensor): None = the checkpoint's training sensor, else vitfly's defaults
    camera: dict | None = None  # CameraConfig fields, e.g. {vertical_fov_deg: 70}, or {preset: camera_config_yaml}
    control_hz: float | None = None  # policy and camera rate, Hz
    depth_max_m: float | None = None  # depth range: normalised depth 1 = this many metres
    # a stereo sensor model on the rendered depth (vitfly.sim.sensor_models), e.g. {model: d435, delay_ticks: 1}
    sensor: dict | None = None
    override_sensor: bool = False  # fly with the settings above even where they contradict the checkpoint's
    gif: bool = True  # re-fly one trial with depth frames and write a GIF with the command arrow
    plots: bool = True
    wandb_project: str | None = None  # log the summary and plots to wandb when set
    overwrite: bool = False  # replace this label's trials in ``out`` that were flown with another setup

    def validate(self, source: str = "config") -> SweepConfig:
        for e in self.env:
            if e not in ENVS:
                raise VitflyError(f"{source}: field 'env' has {e!r}; expected one of {', '.join(ENVS)}")
        if not self.speeds or any(s <= 0 for s in self.speeds):
            raise VitflyError(f"{source}: field 'speeds' must be a non-empty list of positive m/s, got {self.speeds}")
        for name in ("trials", "num_envs", "workers", "threads"):
            if getattr(self, name) < 1:
                raise VitflyError(f"{source}: field {name!r} must be >= 1, got {getattr(self, name)}")
        if self.backend not in BACKENDS:
            raise VitflyError(f"{source}: field 'backend' is {self.backend!r}; expected one of {', '.join(BACKENDS)}")
        for name in ("control_hz", "depth_max_m"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise VitflyError(f"{source}: field {name!r} must be a positive number, got {value}")
        parse_shard(self.shard, source)
        from vitfly.sim.sensor_models import sensor_from_dict

        try:
            sensor_from_dict(self.sensor)
        except ValueError as err:
            raise VitflyError(f"{source}: {err}") from None
        self.physics = self.engine.validate(source).physics(self.physics, f"{source}: field 'physics'")
        if self.sensor is not None and self.sim != "numpy":
            raise VitflyError(f"{source}: field 'sensor': sensor models run on the numpy engine only (sim: numpy)")
        return self

    @property
    def engine(self):
        """The simulator engine that flies the trials (:class:`vitfly.sim.engine.SimEngine`)."""
        from vitfly.sim.engine import SimEngine

        return SimEngine(self.sim, self.sim_device, self.sim_dtype, self.sim_compile)

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        if self.policy in ("expert", "straight"):
            return self.policy
        if self.policy.startswith(("pretrained:", "modular:")):
            return self.policy.split(":", 1)[1]
        return Path(self.policy).stem


def parse_shard(text: str | None, source: str = "--shard") -> tuple[int, int]:
    """"i/n" -> (i, n) with 0 <= i < n; None -> (0, 1)."""
    if text is None:
        return 0, 1
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", str(text))
    if not m or int(m[2]) < 1 or int(m[1]) >= int(m[2]):
        raise VitflyError(f"{source}: field 'shard' is {text!r}; expected i/n with 0 <= i < n, e.g. 0/4")
    return int(m[1]), int(m[2])


def _check_type(value, hint, source: str, key: str):
    """Coerce YAML scalars to the field's type (int -> float, scalar -> one-element list)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        hint = next(a for a in args if a is not type(None))
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is dict or origin is dict:
        if isinstance(value, dict):
            return value
        raise VitflyError(f"{source}: field {key!r} must be a mapping, got {value!r}")
    if origin is list:
        items = value if isinstance(value, list) else [value]
        return [_check_type(v, args[0], source, key) for v in items]
    if hint is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if hint is bool and isinstance(value, bool):
        return value
    if hint in (int, str) and isinstance(value, hint) and not isinstance(value, bool):
        return value
    raise VitflyError(f"{source}: field {key!r} has {value!r}; expected {getattr(hint, '__name__', hint)}")


def dataclass_from_dict(cls, data: dict, source: str):
    """Build dataclass ``cls`` from a mapping, naming unknown keys and mistyped values."""
    if not isinstance(data, dict):
        raise VitflyError(f"{source}: expected a mapping of settings, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise VitflyError(f"{source}: unknown field {unknown[0]!r}; known fields: {', '.join(sorted(known))}")
    return cls(**{k: _check_type(v, hints[k], source, k) for k, v in data.items()})


def load_sweep_config(path: str | Path | None = None, overrides: dict | None = None) -> SweepConfig:
    """Defaults < YAML file (a path or a shipped config's name, e.g. ``eval/trees``) < overrides (keys with value
    None are ignored)."""
    path = config_path(path) if path else None
    data = read_yaml(path) if path else {}
    source = str(path) if path else "config"
    if isinstance(data, dict) and "evaluate" in data:  # a combined config file with an evaluate section
        data = data["evaluate"]
    cfg = dataclass_from_dict(SweepConfig, data, source)
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    checked = dataclass_from_dict(SweepConfig, given, "command line")
    return dataclasses.replace(cfg, **{k: getattr(checked, k) for k in given}).validate(source)
