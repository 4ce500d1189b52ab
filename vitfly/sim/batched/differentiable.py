"""The whole closed loop with gradients: camera -> policy -> controller -> physics, for E scenes and T ticks.

:func:`run_batched` flies episodes to their end and keeps what the metrics need; it decides goals, bounds,
timeouts and contacts, which are discrete. :func:`fly_differentiable` flies the same loop (the same camera,
controller and physics step, in the same order) for a fixed number of control ticks and keeps the autograd
graph: every position, velocity, attitude, depth image and command it returns is a differentiable function
of the policy's parameters, of the start state and of the obstacles (a :class:`SceneBatch` whose tensors
require grad), so a loss on the flight can be minimised through the simulator, as DiffPhysDrone does.
``clearance`` gives each drone's signed distance (m) to its nearest obstacle at every tick, the smooth
quantity such losses penalise.

What has no gradient: which pixels a shape's window covers and which surface is nearest (discrete; the
depth of the chosen surface is smooth), pixels beyond the camera's range (they read 1), and the clamps of
the controller (tilt, climb and rotor limits) where they bind. Contacts, goal and bounds are not decided
here: the flight goes on for ``ticks`` ticks whatever happens. Camera noise and dropout are left out.

Example::

    batch = scene_batch([make_scene("spheres", "medium", s) for s in range(16)])
    flight = fly_differentiable(batch, policy, torch.full((16,), 5.0, dtype=torch.float64), ticks=30)
    loss = torch.relu(1.0 - flight.clearance).square().mean() + (flight.velocity[..., 0] - 5.0).square().mean()
    loss.backward()          # gradients in the policy's parameters (and the batch's, if they require grad)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from vitfly.sim.batched.camera import BatchedCamera
from vitfly.sim.batched.contact import signed_distances
from vitfly.sim.batched.controller import velocity_control
from vitfly.sim.batched.dynamics import DroneTensors, hover_state, physics_step
from vitfly.sim.batched.policies import BatchedObservation
from vitfly.sim.batched.scenes import SceneBatch
from vitfly.sim.rollout import RolloutConfig


class Flight(NamedTuple):
    """E drones flown for T control ticks (world frame, SI units), every tensor part of the autograd graph.

    position, velocity (T + 1, E, 3) m and m/s, and quat (T + 1, E, 4) (w, x, y, z) body-to-world: at the
    start of each tick and after the last; clearance (T + 1, E) m: signed distance from each drone's centre
    to its nearest obstacle at those instants (negative inside one, +inf in a scene without obstacles);
    depth (T, E, H, W) in [0, 1]: the image each tick's policy saw (zeros when ``render`` was off);
    command (T, E, 3) m/s: each tick's world-frame velocity command.
    """

    position: torch.Tensor
    velocity: torch.Tensor
    quat: torch.Tensor
    clearance: torch.Tensor
    depth: torch.Tensor
    command: torch.Tensor


def _physics_substep(state: DroneTensors, command: torch.Tensor, airframe, gains, dt: float) -> DroneTensors:
    """One physics step of the native back end under the cascaded controller tracking ``command`` (E, 3) m/s."""
    return physics_step(state, velocity_control(command, state, airframe, gains), airframe, dt)


def clearance(position: torch.Tensor, batch: SceneBatch) -> torch.Tensor:
    """(E,) signed distance (m) from each drone's centre ``position`` (E, 3) to its scene's nearest obstacle."""
    distances = signed_distances(position, batch)
    if distances.shape[1] == 0:
        return torch.full(position.shape[:1], torch.inf, dtype=position.dtype, device=position.device)
    return distances.amin(1)


def fly_differentiable(
    batch: SceneBatch,
    policy: Callable[[BatchedObservation], torch.Tensor],
    desired_speed: torch.Tensor,
    ticks: int,
    config: RolloutConfig | None = None,
    start: DroneTensors | None = None,
    render: bool = True,
    detach_every: int | None = None,
    compile: bool | str = False,
) -> Flight:
    """Fly the E scenes of ``batch`` for ``ticks`` control ticks under ``policy``, keeping the autograd graph.

    ``policy(obs)`` gets a :class:`BatchedObservation` (depth (E, H, W) in [0, 1], desired speed, attitude,
    position, velocity, every env active) and returns world-frame velocity commands (E, 3) m/s as a tensor
    that may depend on parameters requiring grad; its ``reset(E)`` is called first where it has one.
    ``desired_speed`` (E,) m/s; ``config`` gives the rates, camera, airframe, gains and start position
    (``config.physics`` is not used: this is the native back end's step); ``start`` replaces the hover
    start (e.g. a state that requires grad). ``detach_every`` k cuts the graph between the state of every
    k-th tick and the ones before (truncated backpropagation through time: bounded memory, shorter
    gradients), the policy's own state too where it has a ``detach_state()`` (a recurrent network's, as
    ``DifferentiablePolicy``); None keeps it whole. ``compile`` runs the physics step (controller included)
    and the camera's kernels through ``torch.compile``, their backward passes too (about a minute of compiling
    in a fresh process on a CPU; docs/performance.md says what it gains); a string names torch.compile's
    backend (True: inductor; "aot_eager" traces and differentiates the same graphs without generating code,
    in seconds, for checks). Runs on the batch's device and dtype.
    """
    cfg = config or RolloutConfig()
    e = batch.num_envs
    if ticks < 1:
        raise ValueError(f"ticks: expected at least 1, got {ticks}")
    if detach_every is not None and detach_every < 1:
        raise ValueError(f"detach_every: expected a positive number of ticks or None, got {detach_every}")
    like = dict(dtype=batch.dtype, device=batch.device)
    speed = torch.as_tensor(desired_speed, **like)
    if speed.shape != (e,):
        raise ValueError(f"desired_speed: expected shape ({e},) for the batch's {e} scenes, got {tuple(speed.shape)}")
    if start is not None and start.position.shape != (e, 3):
        got = tuple(start.position.shape)
        raise ValueError(f"start: expected the state of {e} drones, positions (E, 3); got positions of shape {got}")
    substeps, dt = cfg.physics_steps_per_tick, 1.0 / cfg.physics_hz
    af, gains = cfg.airframe, cfg.gains
    backend = "inductor" if compile is True else compile
    compiler = (lambda fn: torch.compile(fn, dynamic=True, backend=backend)) if backend else None
    camera = BatchedCamera(cfg.camera, batch.device, batch.dtype, compile=compiler) if render else None
    step = torch.compile(_physics_substep, backend=backend) if backend else _physics_substep
    state = start if start is not None else hover_state(torch.as_tensor(cfg.task.start, **like).expand(e, 3), af)
    active = torch.ones(e, dtype=torch.bool, device=batch.device)
    active_host = np.ones(e, dtype=bool)
    if hasattr(policy, "reset"):
        policy.reset(e)
    blank = torch.zeros(e, cfg.camera.height, cfg.camera.width, **like)
    positions, velocities, quats, clear, depths, commands = [], [], [], [], [], []

    def keep(state: DroneTensors) -> None:
        positions.append(state.position)
        velocities.append(state.velocity)
        quats.append(state.quat)
        clear.append(clearance(state.position, batch))

    time_s = 0.0
    for tick in range(ticks):
        if detach_every is not None and tick > 0 and tick % detach_every == 0:
            state = DroneTensors(*(t.detach() for t in state))
            if hasattr(policy, "detach_state"):
                policy.detach_state()
        keep(state)
        depth = camera.render(batch, state.position, state.rotation, active) if camera is not None else blank
        obs = BatchedObservation(depth, speed, state.quat, state.position, state.velocity, active, time_s, tick,
                                 batch, active_host)
        command = policy(obs)
        if isinstance(command, tuple):  # a policy that adds labels (the mixture): fly its commands
            command = command[0]
        if command.shape != (e, 3):
            raise ValueError(f"policy returned commands of shape {tuple(command.shape)} (expected ({e}, 3))")
        if camera is not None:
            depths.append(depth)
        commands.append(command)
        for _ in range(substeps):
            state = step(state, command, af, gains, dt)
            time_s += dt
    keep(state)
    # without rendering, the images are one zero frame seen T times (a view: no T x E x H x W of zeros)
    depth = torch.stack(depths) if depths else blank.expand(ticks, *blank.shape)
    return Flight(position=torch.stack(positions), velocity=torch.stack(velocities), quat=torch.stack(quats),
                  clearance=torch.stack(clear), depth=depth, command=torch.stack(commands))
