"""Policies for the batched engine: the expert, straight flight and DAgger's mixture as tensor code, and an
adapter for any other numpy policy of :mod:`vitfly.sim.rollout`.

A batched policy has ``batched = True``, ``needs_depth``, ``reset(num_envs)`` and
``__call__(obs: BatchedObservation)`` returning world-frame velocity commands (E, 3) m/s as a tensor on
the engine's device, or ``(commands, labels)``. :func:`as_batched_policy` turns the built-in numpy
policies into their batched twins and wraps every other policy in :class:`NumpyPolicy`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from vitfly.sim.batched.expert import blocked_lines, expert_commands, obstacles_ahead
from vitfly.sim.batched.scenes import SceneBatch
from vitfly.sim.expert import ExpertConfig
from vitfly.sim.policies import ExpertPolicy, MixturePolicy, StraightPolicy
from vitfly.sim.rollout import LabelledCommands, Observation


@dataclass
class BatchedObservation:
    """What a batched policy sees at one control tick (tensors on the engine's device, world frame, SI).

    depth (E, H, W) in [0, 1] (zeros where not rendered); desired_speed (E,) m/s; quat (E, 4)
    (w, x, y, z) body-to-world; position (E, 3) m; velocity (E, 3) m/s; active (E,) bool; time_s:
    seconds since the episodes' start; tick: control tick index; batch: the scenes (privileged);
    active_host: ``active`` as a numpy array (None: read ``active``).
    """

    depth: torch.Tensor
    desired_speed: torch.Tensor
    quat: torch.Tensor
    position: torch.Tensor
    velocity: torch.Tensor
    active: torch.Tensor
    time_s: float
    tick: int
    batch: SceneBatch
    active_host: np.ndarray | None = None  # ``active`` on the host, where the engine has it without waiting

    def active_on_host(self) -> np.ndarray:
        """``active`` as a numpy array: the engine's host copy, else read from the device."""
        return self.active.cpu().numpy() if self.active_host is None else self.active_host


class BatchedExpert:
    """The privileged expert (:func:`vitfly.sim.batched.expert.expert_commands`) for every env."""

    batched = True
    needs_depth = False

    def __init__(self, config: ExpertConfig | None = None, blocked=None, ahead=None):
        self.config = config or ExpertConfig()
        self._kwargs = {name: fn for name, fn in (("blocked", blocked), ("ahead", ahead)) if fn is not None}

    def reset(self, num_envs: int) -> None:
        pass

    def __call__(self, obs: BatchedObservation) -> torch.Tensor:
        return expert_commands(obs.position, obs.desired_speed, obs.batch, self.config, **self._kwargs)


class BatchedStraight:
    """Straight ahead at the desired speed: (desired_speed, 0, 0) m/s, world frame."""

    batched = True
    needs_depth = False

    def reset(self, num_envs: int) -> None:
        pass

    def __call__(self, obs: BatchedObservation) -> torch.Tensor:
        out = torch.zeros_like(obs.position)
        out[:, 0] = obs.desired_speed
        return out


class BatchedMixture:
    """A :class:`~vitfly.sim.policies.MixturePolicy` in the batched engine: the expert and the student as tensor
    code (their batched twins), so the depth images never leave the engine's device. Which envs fly the
    expert is the mixture's own choice (``MixturePolicy.choose``: its draws and counters, on the host, from the
    tick's host copy of ``active``): the same flights and counts as on the numpy engine.
    """

    batched = True

    def __init__(self, mixture: MixturePolicy, compile: bool = False):
        self.mixture = mixture
        self.expert = as_batched_policy(mixture.expert, compile)
        self.student = None if mixture.student is None else as_batched_policy(mixture.student, compile)
        self.needs_depth = mixture.needs_depth

    def reset(self, num_envs: int) -> None:
        self.mixture.reset(num_envs)  # the generators and counters (and the numpy policies the twins share)
        self.expert.reset(num_envs)
        if self.student is not None:
            self.student.reset(num_envs)

    def __call__(self, obs: BatchedObservation):
        label = _commands_only(self.expert(obs))
        student = label if self.student is None else _commands_only(self.student(obs)).to(label.dtype)
        flies = torch.from_numpy(self.mixture.choose(obs.active_on_host()))
        if label.device.type == "cuda":  # pinned, the copy joins the stream: the host does not wait for the card
            flies = flies.pin_memory()
        flies = flies.to(label.device, non_blocking=True)
        return torch.where(flies[:, None], label, student), label


def _commands_only(out) -> torch.Tensor:
    """A batched policy's commands, without the labels it may add."""
    return out[0] if isinstance(out, tuple) else out


class NumpyPolicy:
    """Runs a numpy policy (:class:`vitfly.sim.rollout.Policy`) in the batched engine: the observation
    goes to the host as an :class:`~vitfly.sim.rollout.Observation` (depth float32, as the numpy engine
    gives it) and the commands (and labels) come back to the device."""

    batched = True

    def __init__(self, policy):
        self.policy = policy
        self.needs_depth = bool(getattr(policy, "needs_depth", True))
        self._obstacles: list[np.ndarray] | None = None

    def reset(self, num_envs: int) -> None:
        self._obstacles = None
        self.policy.reset(num_envs)

    def __call__(self, obs: BatchedObservation):
        scenes = list(obs.batch.scenes)
        if self._obstacles is None:
            self._obstacles = [s.expert_obstacles() for s in scenes]
        n = len(scenes)
        host = Observation(
            depth=obs.depth.detach().to("cpu", torch.float32).numpy(),
            desired_speed=obs.desired_speed.detach().cpu().double().numpy(),
            quat=obs.quat.detach().cpu().double().numpy(),
            position=obs.position.detach().cpu().double().numpy(),
            velocity=obs.velocity.detach().cpu().double().numpy(),
            obstacles=self._obstacles,
            active=obs.active_on_host(),
            time=np.full(n, obs.time_s),
            tick=obs.tick,
            scenes=scenes,
        )
        out = self.policy(host)
        like = dict(dtype=obs.position.dtype, device=obs.position.device)
        if isinstance(out, LabelledCommands):
            return (torch.as_tensor(np.asarray(out.command, dtype=np.float64), **like),
                    torch.as_tensor(np.asarray(out.label, dtype=np.float64), **like))
        return torch.as_tensor(np.asarray(out, dtype=np.float64), **like)


@lru_cache(maxsize=1)
def _compiled_expert_kernels() -> dict:
    return {"blocked": torch.compile(blocked_lines, dynamic=True), "ahead": torch.compile(obstacles_ahead)}


def as_batched_policy(policy, compile: bool = False):
    """``policy`` for the batched engine: batched policies as they are, the numpy expert, straight flight
    and the mixture as their batched twins (same commands), a policy's own ``batched_twin()`` where it gives one
    (e.g. ``vitfly.eval.learned_policy.LearnedPolicy``), any other policy through :class:`NumpyPolicy`.
    ``compile``: the expert's line test and obstacle selection through ``torch.compile``."""
    if compile and type(policy) in (ExpertPolicy, BatchedExpert):
        return BatchedExpert(policy.config, **_compiled_expert_kernels())
    if getattr(policy, "batched", False):
        return policy
    if type(policy) is MixturePolicy:
        return BatchedMixture(policy, compile)
    twin = getattr(policy, "batched_twin", None)  # a policy's own tensor path (a learned policy's network)
    if twin is not None and (batched := twin()) is not None:
        return batched
    if type(policy) is ExpertPolicy:
        return BatchedExpert(policy.config)
    if type(policy) is StraightPolicy:
        return BatchedStraight()
    return NumpyPolicy(policy)
