"""What a trial was flown with, as short stable hashes: trials are keyed by these, never by a label alone.

- ``policy_id``: for a learned policy, the network's weights (every state-dict tensor: name, dtype,
  shape, bytes), its modules' classes and plain options (e.g. ``use_state``, layer sizes) and the
  inference back end; for ``expert``, its ``ExpertConfig``; for ``straight``, its class alone; for
  ``modular:NAME``, the planner's options and the planners' code version;
- ``rollout_id``: the rollout settings (physics back end, physics and control rates, camera, task
  with its timeout and body radius, airframe, controller gains; not whether depth frames are kept)
  and the simulator engine when it is not the numpy one (``vitfly.sim.engine.SimEngine.key``);
- ``scene_id``: the scene generator's settings of one (env, preset);
- the sweep seed and the preset name.

A :class:`Setup` holds these for one env; its ``id`` is part of every trial's key. Hashes are
SHA-256 of canonical JSON (sorted keys, floats as Python writes them), cut to 16 hex digits.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass

import numpy as np

HASH_HEX_DIGITS = 16

# setup field -> how a one-line message names it
FIELD_NAMES = {
    "policy_id": "policy content",  # weights and options of a network, or the expert's config
    "rollout_id": "rollout settings",  # rates, camera, task, airframe, controller
    "sweep_seed": "--seed",
    "preset": "--preset",
    "scene_id": "scene generator settings",
}


def _plain(value):
    """JSON-able form of configs: dataclasses, tuples, numpy values and arrays."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {"__class__": type(value).__qualname__,
                **{f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def digest(value) -> str:
    """Short SHA-256 of the canonical JSON of ``value``."""
    text = json.dumps(_plain(value), sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:HASH_HEX_DIGITS]


_OPTION_TYPES = (bool, int, float, str, type(None))


def network_fingerprint(net) -> str:
    """Hash of a torch network's weights, module classes and plain per-module options."""
    import torch

    h = hashlib.sha256()
    for name, module in sorted(net.named_modules(), key=lambda item: item[0]):
        options = {k: v for k, v in vars(module).items()
                   if not k.startswith("_") and k != "training"
                   and (isinstance(v, _OPTION_TYPES) or (isinstance(v, tuple) and all(
                       isinstance(x, _OPTION_TYPES) for x in v)))}
        h.update(json.dumps([name, type(module).__module__, type(module).__qualname__, _plain(options)],
                            sort_keys=True).encode())
    for name, tensor in sorted(net.state_dict().items()):
        t = tensor.detach().cpu().contiguous()
        h.update(json.dumps([name, str(t.dtype), list(t.shape)]).encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:HASH_HEX_DIGITS]


def policy_fingerprint(source) -> str:
    """``policy_id`` of a :class:`vitfly.eval.policy_source.PolicySource` (loads a checkpoint's network)."""
    if source.is_builtin:
        policy = source.build()
        config = getattr(policy, "config", None)
        return digest({"builtin": source.spec, "class": type(policy).__qualname__, "config": config})
    if source.is_modular:
        from vitfly.planners.policy import PLANNERS_CODE_VERSION

        return digest({"modular": source.spec, "options": source.planner_options(),
                       "code_version": PLANNERS_CODE_VERSION})
    return learned_policy_id(network_fingerprint(source.load_network()), source.backend)


def learned_policy_id(network: str, backend: str) -> str:
    """``policy_id`` of a network (its :func:`network_fingerprint`) flown with the inference ``backend``."""
    return digest({"network": network, "backend": backend})


def rollout_fingerprint(rollout_config, sim: dict | None = None) -> str:
    """``rollout_id`` of a :class:`vitfly.sim.rollout.RolloutConfig`; ``record_depth`` (logging only) is left out,
    and so is an unset ``sensor`` (the ideal camera), so that trials from before sensor models keep their key.

    ``sim``: the engine's key (``SimEngine.key()``), None for the numpy engine, whose ids stay those of
    every sweep flown before the batched engine existed.
    """
    plain = _plain(dataclasses.replace(rollout_config, record_depth=False))
    if plain.get("sensor", 0) is None:
        del plain["sensor"]
    return digest(plain if sim is None else {"rollout": plain, "sim": sim})


def scene_fingerprint(env: str, preset: str) -> str:
    """``scene_id``: the generator settings of (env, preset)."""
    from vitfly.sim.scenes import scene_config

    return digest({"env": env, "preset": preset, "config": scene_config(env, preset)})


@dataclass(frozen=True)
class Setup:
    """What the trials of one policy in one env were flown with; ``id`` goes into every trial's key."""

    policy_id: str
    rollout_id: str
    sweep_seed: int
    preset: str
    scene_id: str

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def id(self) -> str:
        return digest(self.to_dict())

    @classmethod
    def from_dict(cls, data: dict) -> Setup:
        return cls(**{f.name: data[f.name] for f in dataclasses.fields(cls)})


def differences(old: dict, new: dict) -> list[str]:
    """The setup fields that differ, each as 'NAME (OLD, now NEW)'."""
    return [f"{FIELD_NAMES[k]} ({old.get(k)}, now {new.get(k)})" for k in FIELD_NAMES if old.get(k) != new.get(k)]


@dataclass(frozen=True)
class SweepIdentity:
    """The env-independent part of a sweep's setup; ``setup(env)`` completes it."""

    policy_id: str
    rollout_id: str
    sweep_seed: int
    preset: str

    def setup(self, env: str) -> Setup:
        return Setup(self.policy_id, self.rollout_id, int(self.sweep_seed), self.preset,
                     scene_fingerprint(env, self.preset))
