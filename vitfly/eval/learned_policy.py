"""A zoo network flown as a simulator policy: one batched forward pass per control tick.

The simulator's rollout engine steps N scenes in lockstep and calls ``policy(obs)`` once per tick
(``obs``: depth (N, 60, 90) in [0, 1], desired_speed (N,) m/s, quat (N, 4) (w, x, y, z), position
(N, 3) m world frame, active (N,) bool); the policy returns world-frame velocity commands (N, 3) in
m/s. This adapter keeps one recurrent state per env, zeroed by ``reset`` at the start of each trial,
runs the network only on the active envs, and turns the network output into a command as the paper
deploys it (``deploy_command``, take-off ramp included).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import nn

from vitfly.sim.expert import ExpertConfig, takeoff_ramp

# (depth (B,1,1,60,90), desired_speed (B,1,1), quat (B,1,4), hidden | None) -> (out (B,1,3), hidden | None)
StepFn = Callable[..., tuple]


def deploy_command(
    raw: np.ndarray, desired_speed_mps: np.ndarray, x_m: np.ndarray | None = None, ramp: ExpertConfig | None = None
) -> np.ndarray:
    """Network output (N, 3) (velocity / desired speed) -> world-frame command (N, 3) in m/s.

    Paper deployment (``compute_command_vision_based``): clip the x part to [-1, 1], normalise to a
    unit vector, multiply by the desired speed, then, given the drones' world-frame x (N,) in m,
    apply the expert's take-off ramp to the x command (``vitfly.sim.expert.takeoff_ramp``, constants
    from ``ramp``, default ``ExpertConfig()``). ``x_m`` None skips the ramp. A zero output (no
    direction at all) flies straight ahead.
    """
    v = np.array(raw, dtype=np.float64).reshape(-1, 3)
    v[:, 0] = np.clip(v[:, 0], -1.0, 1.0)
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    unit = np.where(norm > 1e-9, v / np.maximum(norm, 1e-12), np.array([1.0, 0.0, 0.0]))
    speed = np.asarray(desired_speed_mps, dtype=np.float64).reshape(-1)
    command = unit * speed[:, None]
    if x_m is not None:
        command[:, 0] = takeoff_ramp(command[:, 0], np.asarray(x_m, dtype=np.float64).reshape(-1), speed, ramp)
    return command


def _obs_field(obs, name: str):
    return obs[name] if isinstance(obs, dict) else getattr(obs, name)


def zero_hidden_of(net: nn.Module, n: int, device=None, dtype=None):
    """A zoo network's zero recurrent state for ``n`` envs, or None for a feed-forward network."""
    init = getattr(net, "initial_hidden", None)
    recurrent = getattr(net, "is_recurrent", False) and init is not None
    return init(n, device=device, dtype=dtype) if recurrent else None


def one_step_inputs(depth: torch.Tensor, speed: torch.Tensor, quat: torch.Tensor) -> tuple:
    """A tick's depth (N, H, W), desired speed (N,) and quat (N, 4) as the zoo's one-step sequences:
    (N, 1, 1, H, W), (N, 1, 1), (N, 1, 4)."""
    return depth[:, None, None], speed.reshape(-1, 1, 1), quat.reshape(-1, 1, 4)


def _select_hidden(hidden, idx: torch.Tensor):
    return None if hidden is None else tuple(h[:, idx] for h in hidden)


class LearnedPolicy:
    """Sim policy protocol (``reset(num_envs)``, ``__call__(obs) -> (N, 3)``) over a zoo network.

    ``step_fn`` replaces the eager network call (e.g. an ONNX Runtime session with the same
    inputs and outputs); by default the network runs under ``torch.no_grad`` on ``device`` (not
    inference_mode: the per-env state is updated in place between calls). A ``step_fn`` with a
    ``bind(batch_size)`` method (``vitfly.deploy.onnx.OnnxPolicyRunner``) is called on buffers bound once
    per ``reset``: while every env is active a tick copies the observation in and the command out, with no
    per-tick allocation and no torch tensors (the recurrent state stays in the bound buffers); ticks with
    some envs finished take the general path on those buffers. ``takeoff_ramp`` False is vitfly's variant
    without the paper's take-off ramp (full speed from the start).
    """

    def __init__(
        self,
        net: nn.Module,
        device: str | torch.device = "cpu",
        step_fn: StepFn | None = None,
        takeoff_ramp: bool = True,
    ):
        self.net = net.eval().to(device)
        self.device = torch.device(device)
        self.takeoff_ramp = bool(takeoff_ramp)
        self.is_recurrent = bool(getattr(net, "is_recurrent", False))
        self._step = step_fn or self._eager_step
        self._bind = getattr(step_fn, "bind", None)
        self._bound = None  # the step_fn's bound buffers for num_envs (see the class docstring)
        self._hidden = None
        self.num_envs = 0

    def _eager_step(self, depth, speed, quat, hidden):
        with torch.no_grad():
            return self.net(depth, speed, quat, hidden)

    def _zero_hidden(self, n: int):
        return zero_hidden_of(self.net, n, self.device)

    def reset(self, num_envs: int) -> None:
        """Start a new trial in every env: zero recurrent state."""
        self.num_envs = int(num_envs)
        if self._bind is not None:
            if self._bound is None or self._bound.depth.shape[0] != self.num_envs:
                self._bound = self._bind(self.num_envs)
            self._bound.reset()
            self._hidden = None
            return
        self._hidden = self._zero_hidden(self.num_envs)

    def reset_envs(self, env_indices: Sequence[int]) -> None:
        """Start a new trial in some envs only (their recurrent state is zeroed)."""
        if self._bound is not None and self._bound.hidden is not None and len(env_indices):
            for h in self._bound.hidden:
                h[:, list(env_indices)] = 0.0
        if self._hidden is not None and len(env_indices):
            idx = torch.as_tensor(list(env_indices), dtype=torch.long, device=self.device)
            for h in self._hidden:
                h[:, idx] = 0.0

    def raw_output(self, obs) -> np.ndarray:
        """Network output (N, 3) for all envs (zeros for inactive ones); advances the recurrent state."""
        depth = np.asarray(_obs_field(obs, "depth"), dtype=np.float32)
        n = depth.shape[0]
        if n != self.num_envs:
            raise ValueError(f"policy was reset for {self.num_envs} envs but got observations of {n}")
        active = np.asarray(_obs_field(obs, "active"), dtype=bool) if _has(obs, "active") else np.ones(n, bool)
        out = np.zeros((n, 3), dtype=np.float64)
        if not active.any():
            return out
        if self._bound is not None:
            return self._bound_output(obs, depth, active, out)
        idx_np = np.flatnonzero(active)
        idx = torch.as_tensor(idx_np, dtype=torch.long, device=self.device)
        d = torch.from_numpy(depth[idx_np]).to(self.device)
        s = torch.as_tensor(np.asarray(_obs_field(obs, "desired_speed"), np.float32)[idx_np], device=self.device)
        q = torch.as_tensor(np.asarray(_obs_field(obs, "quat"), np.float32)[idx_np], device=self.device)
        out[idx_np] = self.network_rows(idx, d, s, q).double().cpu().numpy()
        return out

    def network_rows(self, idx: torch.Tensor, depth: torch.Tensor, speed: torch.Tensor,
                     quat: torch.Tensor) -> torch.Tensor:
        """Network output (K, 3) for the K envs ``idx`` (long, on ``self.device``), from their depth (K, H, W),
        desired speed (K,) m/s and quat (K, 4), float32 on ``self.device``; advances their recurrent state."""
        all_active = len(idx) == self.num_envs
        hidden_in = self._hidden if all_active else _select_hidden(self._hidden, idx)
        pred, hidden_out = self._step(*one_step_inputs(depth, speed, quat), hidden_in)
        if self._hidden is not None and hidden_out is not None:
            if all_active:
                self._hidden = tuple(h.clone() for h in hidden_out)
            else:
                for h, h_new in zip(self._hidden, hidden_out, strict=True):
                    h[:, idx] = h_new
        return torch.as_tensor(pred).reshape(-1, 3)

    def _bound_output(self, obs, depth: np.ndarray, active: np.ndarray, out: np.ndarray) -> np.ndarray:
        bound, n = self._bound, self.num_envs
        speed = np.asarray(_obs_field(obs, "desired_speed")).reshape(n)
        quat = np.asarray(_obs_field(obs, "quat")).reshape(n, 4)
        if active.all():  # the flight loop's usual tick: copies only
            np.copyto(bound.depth.reshape(depth.shape), depth)
            np.copyto(bound.desired_speed.reshape(n), speed, casting="same_kind")
            np.copyto(bound.quat.reshape(n, 4), quat, casting="same_kind")
            np.copyto(out, bound().reshape(n, 3))
            return out
        idx = np.flatnonzero(active)  # some envs done: the active rows through the unbound call, state kept
        state = bound.hidden
        hidden = None if state is None else tuple(np.ascontiguousarray(h[:, idx]) for h in state)
        pred, hidden = self._step(np.ascontiguousarray(depth[idx, None, None]),
                                  speed[idx].astype(np.float32).reshape(-1, 1, 1),
                                  quat[idx].astype(np.float32).reshape(-1, 1, 4), hidden)  # fmt: skip
        if state is not None:
            for h, h_new in zip(state, hidden, strict=True):
                h[:, idx] = h_new
        out[idx] = np.asarray(pred).reshape(-1, 3)
        return out

    def batched_twin(self) -> BatchedLearnedPolicy | None:
        """This policy for the batched engine with tensors in and out (``vitfly.sim.batched.policies``), or None
        when its step takes host arrays (ONNX Runtime): the engine's numpy adapter runs it then."""
        return BatchedLearnedPolicy(self) if self._bind is None else None

    def __call__(self, obs) -> np.ndarray:
        x_m = None
        if self.takeoff_ramp:
            if not _has(obs, "position"):
                raise ValueError("observation has no 'position' (N, 3) m: the take-off ramp needs the drones' x")
            x_m = np.asarray(_obs_field(obs, "position"), dtype=np.float64).reshape(-1, 3)[:, 0]
        raw = self.raw_output(obs)
        return deploy_command(raw, np.asarray(_obs_field(obs, "desired_speed"), dtype=np.float64), x_m)


class BatchedLearnedPolicy:
    """A :class:`LearnedPolicy` in the batched engine: the observation's tensors go from the engine's device to
    the network's, the commands come back, with no trip through host memory (none at all when the engine and
    the network share a card). The same inputs and deployment as the numpy path, in float64 torch."""

    batched = True
    needs_depth = True

    def __init__(self, policy: LearnedPolicy):
        self.policy = policy

    def reset(self, num_envs: int) -> None:
        self.policy.reset(num_envs)

    def __call__(self, obs) -> torch.Tensor:
        p = self.policy
        n = obs.depth.shape[0]
        if n != p.num_envs:
            raise ValueError(f"policy was reset for {p.num_envs} envs but got observations of {n}")
        raw = torch.zeros(n, 3, dtype=torch.float64, device=obs.depth.device)
        # the tick's active rows by index: one nonzero (on a GPU, the call's one wait for the device); a boolean
        # mask would wait again at every gather and at the scatter
        idx = torch.nonzero(obs.active).flatten()
        if len(idx):
            f32 = dict(device=p.device, dtype=torch.float32)
            rows = p.network_rows(idx.to(p.device), obs.depth.index_select(0, idx).to(**f32),
                                  obs.desired_speed.index_select(0, idx).to(**f32),
                                  obs.quat.index_select(0, idx).to(**f32))
            raw.index_copy_(0, idx, rows.to(raw))
        x_m = obs.position[:, 0].to(raw) if p.takeoff_ramp else None
        return deploy_command_torch(raw, obs.desired_speed.to(raw), x_m).to(obs.position.dtype)


class DifferentiablePolicy:
    """A zoo network as a batched policy whose commands keep the autograd graph, for flying it through
    :func:`vitfly.sim.batched.differentiable.fly_differentiable` and training it through the simulator.

    The same inputs and deployment as :class:`BatchedLearnedPolicy` (the tick's depth, desired speed and
    attitude into the network, its output turned into a command by ``deploy_command_torch``, take-off ramp
    included unless ``takeoff_ramp`` is False), but no ``no_grad``, every env in every call, and the recurrent
    state carried from tick to tick inside the graph (``reset`` zeroes it). The network runs in the mode, on
    the device and in the dtype it has (``net.train()`` or ``net.eval()``, ``net.double()`` for float64).
    """

    batched = True
    needs_depth = True

    def __init__(self, net: nn.Module, takeoff_ramp: bool = True):
        self.net = net
        self.takeoff_ramp = bool(takeoff_ramp)
        self._hidden = None

    def reset(self, num_envs: int) -> None:
        p = next(self.net.parameters())
        self._hidden = zero_hidden_of(self.net, int(num_envs), p.device, p.dtype)

    def detach_state(self) -> None:
        """Cut the recurrent state from the graph before it (same values): truncated backpropagation."""
        if self._hidden is not None:
            self._hidden = tuple(h.detach() for h in self._hidden)

    def __call__(self, obs) -> torch.Tensor:
        p = next(self.net.parameters())
        like = dict(device=p.device, dtype=p.dtype)
        inputs = one_step_inputs(obs.depth.to(**like), obs.desired_speed.to(**like), obs.quat.to(**like))
        raw, self._hidden = self.net(*inputs, self._hidden)
        out = obs.position
        x_m = out[:, 0] if self.takeoff_ramp else None
        return deploy_command_torch(raw.reshape(-1, 3).to(out), obs.desired_speed.to(out), x_m)


def deploy_command_torch(raw: torch.Tensor, desired_speed_mps: torch.Tensor, x_m: torch.Tensor | None = None,
                         ramp: ExpertConfig | None = None) -> torch.Tensor:
    """:func:`deploy_command` on float64 tensors (N, 3), (N,), (N,), with the same operations in the same order
    (and no in-place writes, so that gradients flow through it: :class:`DifferentiablePolicy`)."""
    v = torch.cat([raw[:, :1].clamp(-1.0, 1.0), raw[:, 1:]], 1)
    norm = torch.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])[:, None]
    ahead = torch.zeros(3, dtype=v.dtype, device=v.device)  # filled on the device: no copy from the host
    ahead[0] = 1.0
    unit = torch.where(norm > 1e-9, v / norm.clamp_min(1e-12), ahead)
    command = unit * desired_speed_mps[:, None]
    if x_m is not None:
        cfg = ramp or ExpertConfig()
        ramped = (x_m / cfg.ramp_distance_m * desired_speed_mps).clamp_min(cfg.ramp_min_speed_mps)
        forward = torch.where(x_m < cfg.ramp_distance_m, ramped, command[:, 0])
        command = torch.cat([forward[:, None], command[:, 1:]], 1)
    return command


def _has(obs, name: str) -> bool:
    return name in obs if isinstance(obs, dict) else hasattr(obs, name)
