"""The whole closed loop with gradients (vitfly.sim.batched.differentiable): the same flight as the batched engine,
gradients through camera, policy, controller and physics over several ticks checked against finite differences,
truncation, and a policy improved by gradient descent through the simulator. float64 on the CPU throughout."""

import numpy as np
import pytest
import torch

from vitfly.eval.learned_policy import DifferentiablePolicy
from vitfly.sim.batched.differentiable import clearance, fly_differentiable
from vitfly.sim.batched.dynamics import hover_state
from vitfly.sim.batched.policies import BatchedExpert
from vitfly.sim.batched.rollout import run_batched
from vitfly.sim.batched.scenes import scene_batch
from vitfly.sim.camera import CameraConfig
from vitfly.sim.collision import signed_distances
from vitfly.sim.policies import ExpertPolicy
from vitfly.sim.rollout import RolloutConfig, TaskConfig
from vitfly.sim.scenes import Scene, make_scene
from vitfly.zoo import create_model

F64 = torch.float64

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def sphere_ahead_scene(y_m: float = 0.4, x_m: float = 6.0, radius_m: float = 1.0) -> Scene:
    """One sphere at (x_m, y_m, 3.5 m): ahead of the start, y_m to its left."""
    return Scene("spheres", "test", 0, np.array([[x_m, y_m, 3.5, radius_m]]), np.zeros((0, 5)), np.zeros((0, 6)))


class LinearDepthPolicy:
    """Straight ahead at the desired speed, plus W @ (the depth image's column means) + b m/s."""

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor):
        self.weight, self.bias = weight, bias

    def __call__(self, obs):
        ahead = torch.zeros_like(obs.position)
        ahead[:, 0] = obs.desired_speed
        return ahead + obs.depth.mean(1) @ self.weight.T + self.bias


@pytest.mark.parametrize("env", ["spheres", "trees", "window"])
def test_the_flight_is_the_batched_engines_flight(env):
    # the expert from 12 m short of the obstacles, 40 ticks (1.3 s): the obstacles fill the images
    if env == "window":
        scenes = sorted((make_scene(env, "medium", s) for s in range(60)), key=lambda s: abs(s.boxes[0, 0] - 25.0))[:2]
        start = (20.0, 0.0, 3.5)
    else:
        scenes, start = [make_scene(env, "hard", s) for s in range(2)], (8.0, 0.0, 3.5)
    # the reference's episodes end at 1.5 s (45 ticks), after the compared ticks
    cfg = RolloutConfig(physics="native", record_depth=True,
                        task=TaskConfig(start=start, timeout_s=1.5, timeout_speed_factor=0.0))
    ticks, speeds = 40, [5.0, 7.0]
    reference = run_batched(scenes, speeds, ExpertPolicy(), cfg)
    flight = fly_differentiable(scene_batch(scenes), BatchedExpert(), torch.tensor(speeds, dtype=F64), ticks, cfg)
    assert flight.position.shape == (ticks + 1, 2, 3) and flight.depth.shape == (ticks, 2, 60, 90)
    for i, r in enumerate(reference):
        assert len(r.log) > ticks  # the episodes go on past the compared ticks
        np.testing.assert_allclose(flight.position[:ticks, i].numpy(), r.log.position[:ticks], rtol=0, atol=1e-12)
        np.testing.assert_allclose(flight.velocity[:ticks, i].numpy(), r.log.velocity[:ticks], rtol=0, atol=1e-12)
        np.testing.assert_allclose(flight.quat[:ticks, i].numpy(), r.log.quat[:ticks], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(flight.command[:, i].numpy(), r.log.command[:ticks])
        np.testing.assert_array_equal(flight.depth[:, i].to(torch.float32).numpy(), r.log.depth[:ticks])
        assert (flight.depth[:, i] < 1).float().mean() > 0.05  # the obstacles are in view
    # clearance: the numpy engine's signed distances (vitfly.sim.collision), nearest obstacle, every tick
    for t in range(0, ticks + 1, 10):
        for i, scene in enumerate(scenes):
            expected = signed_distances(flight.position[t, i].numpy(), scene).min()
            assert float(flight.clearance[t, i]) == pytest.approx(expected, abs=1e-12)


def test_gradients_through_several_ticks_of_the_whole_loop():
    # a 6 x 8 camera sees the sphere; the policy steers by its image; two ticks (16 physics steps): the final
    # state and clearance are differentiable in the policy's weights and in the sphere's parameters
    cfg = RolloutConfig(physics="native", camera=CameraConfig(height=6, width=8, render_ground=False))
    batch = scene_batch([sphere_ahead_scene(0.4, 4.0, 1.5)])
    g = torch.Generator().manual_seed(0)
    weight = (2.0 * torch.randn(3, 8, generator=g, dtype=F64)).requires_grad_()
    bias = torch.tensor([0.0, 0.3, 0.1], dtype=F64, requires_grad=True)
    sphere = batch.spheres.clone().requires_grad_()

    def fly(weight, bias, sphere):
        flight = fly_differentiable(batch.replace(spheres=sphere), LinearDepthPolicy(weight, bias),
                                    torch.tensor([5.0], dtype=F64), 2, cfg)
        return flight.position[-1], flight.velocity[-1], flight.clearance[-1]

    flight = fly_differentiable(batch, LinearDepthPolicy(weight, bias), torch.tensor([5.0], dtype=F64), 2, cfg)
    assert ((flight.depth > 0) & (flight.depth < 1)).sum() >= 8  # the sphere fills part of both images
    assert torch.autograd.gradcheck(fly, (weight, bias, sphere), eps=1e-7, atol=1e-6)


@pytest.mark.parametrize("model", ["convnet", "lstmnet"])
def test_a_zoo_networks_gradient_through_the_simulator_equals_finite_differences(model):
    # the paper's network on the real 60 x 90 camera, 3 ticks, two scenes: d(loss)/d(parameter) by autograd
    # against central differences, for a weight of the first layer (through every image) and an output bias
    torch.manual_seed(0)
    net = create_model(model).double().eval()
    batch = scene_batch([sphere_ahead_scene(0.4), sphere_ahead_scene(-0.8)])
    cfg = RolloutConfig(physics="native", task=TaskConfig(start=(1.0, 0.0, 3.5)))
    speed = torch.tensor([5.0, 6.0], dtype=F64)
    first = next(p for name, p in net.named_parameters() if name.endswith("weight") and p.dim() == 4)
    last_bias = [p for name, p in net.named_parameters() if name.endswith("bias")][-1]

    def loss():
        flight = fly_differentiable(batch, DifferentiablePolicy(net), speed, 3, cfg)
        return (torch.relu(2.0 - flight.clearance).square().sum() + flight.position[-1, :, 1].square().sum()
                + (flight.velocity[..., 0] - speed).square().mean())

    net.zero_grad()
    loss().backward()
    for param in (first, last_bias):
        index = np.unravel_index(int(param.grad.abs().argmax()), param.shape)  # its most telling element
        analytic = float(param.grad[index])
        with torch.no_grad():
            h, original = 1e-6, float(param[index])
            param[index] = original + h
            up = float(loss())
            param[index] = original - h
            down = float(loss())
            param[index] = original
        numeric = (up - down) / (2 * h)
        assert abs(analytic) > 1e-6  # the parameter matters to the loss
        assert analytic == pytest.approx(numeric, rel=1e-5, abs=1e-9)


def test_detach_every_cuts_the_graph_between_ticks_without_changing_the_flight():
    batch = scene_batch([sphere_ahead_scene()])
    cfg = RolloutConfig(physics="native", camera=CameraConfig(height=4, width=6))
    policy = LinearDepthPolicy(torch.zeros(3, 6, dtype=F64), torch.zeros(3, dtype=F64))
    speed = torch.tensor([4.0], dtype=F64)

    def final_x(detach_every):
        start = torch.tensor([[0.0, 0.0, 3.5]], dtype=F64, requires_grad=True)
        state = hover_state(start, cfg.airframe)
        flight = fly_differentiable(batch, policy, speed, 4, cfg, start=state, detach_every=detach_every)
        (grad,) = torch.autograd.grad(flight.position[-1, 0, 0], start, allow_unused=True)
        return float(flight.position[-1, 0, 0].detach()), grad

    whole, truncated = final_x(None), final_x(2)
    assert whole[0] == truncated[0]  # the same flight
    assert float(whole[1][0, 0]) == pytest.approx(1.0, abs=1e-6)  # a shifted start shifts the end alike
    assert truncated[1] is None or float(truncated[1].abs().max()) == 0.0  # no path back past tick 2


def test_detach_every_cuts_a_recurrent_policys_state_too():
    net = create_model("lstmnet").double().eval()
    policy = DifferentiablePolicy(net)
    cuts = []
    detach = policy.detach_state
    policy.detach_state = lambda: (cuts.append(len(cuts)), detach())
    batch = scene_batch([sphere_ahead_scene()])
    speed = torch.tensor([4.0], dtype=F64)
    fly_differentiable(batch, policy, speed, 5, detach_every=2, render=False)
    assert len(cuts) == 2  # before ticks 2 and 4
    hidden = [h.clone() for h in policy._hidden]
    assert all(h.requires_grad for h in policy._hidden)  # tick 4 ran after the last cut
    policy.detach_state()
    assert not any(h.requires_grad for h in policy._hidden)
    assert all(torch.equal(a, b) for a, b in zip(hidden, policy._hidden, strict=True))


def test_a_policy_learns_to_pass_beside_the_sphere_by_gradient_descent_through_the_simulator():
    # one parameter, the lateral command (m/s); the loss wants 1.5 m of clearance from a sphere 0.3 m left of the
    # straight line and no more sideways flight than needed: gradient descent through 30 ticks (1 s; physics at
    # 120 Hz for the test's time) steps right, away from it
    batch = scene_batch([sphere_ahead_scene(0.3)])
    cfg = RolloutConfig(physics="native", physics_hz=120.0, task=TaskConfig(start=(3.0, 0.0, 3.5)))
    lateral = torch.zeros(1, dtype=F64, requires_grad=True)

    def policy(obs):
        command = torch.zeros_like(obs.position)
        command[:, 0] = obs.desired_speed
        command[:, 1] = lateral
        return command

    def loss(flight):
        return torch.relu(1.5 - flight.clearance).square().sum() + 0.01 * flight.command[..., 1].square().mean()

    speed = torch.tensor([4.0], dtype=F64)
    with torch.no_grad():
        straight = fly_differentiable(batch, policy, speed, 30, cfg, render=False)
    assert float(clearance(straight.position[0], batch)) == pytest.approx(np.hypot(3.0, 0.3) - 1.0, abs=1e-12)
    assert float(straight.clearance.min()) < 0  # flying straight, the drone goes into the sphere
    first = float(loss(straight))
    optimiser = torch.optim.Adam([lateral], lr=0.8)
    for _ in range(8):
        optimiser.zero_grad()
        loss(fly_differentiable(batch, policy, speed, 30, cfg, render=False)).backward()
        optimiser.step()
    with torch.no_grad():
        flight = fly_differentiable(batch, policy, speed, 30, cfg, render=False)
    assert float(flight.clearance.min()) > 1.0  # it now passes the sphere well clear
    assert float(loss(flight)) < 0.05 * first
    assert float(lateral.detach()) < -1.0  # by stepping right (-y), away from the sphere


def test_bad_arguments_are_one_line_each():
    batch = scene_batch([sphere_ahead_scene()])
    def policy(obs):
        return torch.zeros_like(obs.position)

    speed = torch.tensor([4.0], dtype=F64)
    with pytest.raises(ValueError, match="ticks: expected at least 1"):
        fly_differentiable(batch, policy, speed, 0)
    with pytest.raises(ValueError, match=r"desired_speed: expected shape \(1,\)"):
        fly_differentiable(batch, policy, torch.tensor([4.0, 5.0], dtype=F64), 1)
    with pytest.raises(ValueError, match="detach_every"):
        fly_differentiable(batch, policy, speed, 1, detach_every=0)
    with pytest.raises(ValueError, match=r"policy returned commands of shape \(1, 2\)"):
        fly_differentiable(batch, lambda obs: torch.zeros(1, 2, dtype=F64), speed, 1)


def test_the_compiled_flight_and_its_gradients_equal_the_eager_ones():
    # every physics step and camera kernel traced by torch.compile and differentiated by AOT autograd (the
    # "aot_eager" backend: inductor's code generation would take a minute here; its gradients are compared with
    # eager ones by benchmarks/sim_gradients.py --compile)
    cfg = RolloutConfig(physics="native", camera=CameraConfig(height=6, width=8, render_ground=False))
    batch = scene_batch([sphere_ahead_scene(0.4, 4.0, 1.5), sphere_ahead_scene(-0.5, 5.0, 1.2)])
    g = torch.Generator().manual_seed(1)
    weight = (2.0 * torch.randn(3, 8, generator=g, dtype=F64)).requires_grad_()
    bias = torch.tensor([0.0, 0.3, 0.1], dtype=F64, requires_grad=True)
    speed = torch.tensor([5.0, 4.0], dtype=F64)

    def flown(compile):
        flight = fly_differentiable(batch, LinearDepthPolicy(weight, bias), speed, 3, cfg, compile=compile)
        loss = torch.relu(2.0 - flight.clearance).square().sum() + flight.position[-1, :, 1].square().sum()
        grads = torch.autograd.grad(loss, (weight, bias))
        return flight, grads

    (eager, eager_grads), (compiled, compiled_grads) = flown(False), flown("aot_eager")
    assert ((compiled.depth > 0) & (compiled.depth < 1)).sum() >= 8
    for a, b in zip(eager, compiled, strict=True):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-12)
    for a, b in zip(eager_grads, compiled_grads, strict=True):
        assert float(a.abs().max()) > 0
        torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-12)
