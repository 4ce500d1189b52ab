"""The network -> simulator policy adapter, with real (untrained) zoo networks."""

import numpy as np
import pytest
import torch

from vitfly.eval.learned_policy import LearnedPolicy, deploy_command
from vitfly.sim.expert import takeoff_ramp
from vitfly.zoo import create_model


def test_deploy_command_clips_x_normalises_and_scales():
    raw = np.array([[2.0, 0.0, 0.0], [0.5, 0.5, 0.0], [-3.0, 0.0, 4.0], [0.0, 0.0, 0.0]])
    cmd = deploy_command(raw, np.array([5.0, 2.0, 2.0, 3.0]))
    s = np.sqrt(0.5)
    assert cmd[0] == pytest.approx([5.0, 0.0, 0.0])  # x clipped to 1, unit, x5
    assert cmd[1] == pytest.approx([2 * s, 2 * s, 0.0])
    assert cmd[2] == pytest.approx(np.array([-1.0, 0.0, 4.0]) / np.sqrt(17.0) * 2.0)  # x clipped to -1 first
    assert cmd[3] == pytest.approx([3.0, 0.0, 0.0])  # no direction at all: straight ahead
    assert np.linalg.norm(cmd, axis=1) == pytest.approx([5.0, 2.0, 2.0, 3.0])


def _obs(rng, n, active=None):
    q = rng.normal(size=(n, 4))
    return {
        "depth": rng.uniform(0, 1, size=(n, 60, 90)).astype(np.float32),
        "desired_speed": rng.uniform(3, 7, size=n),
        "quat": q / np.linalg.norm(q, axis=1, keepdims=True),
        "position": np.tile([10.0, 0.0, 3.5], (n, 1)),  # past the take-off ramp
        "active": np.ones(n, bool) if active is None else np.asarray(active),
    }


def test_convnet_batched_call_matches_single_frames():
    torch.manual_seed(0)
    net = create_model("convnet").eval()
    policy = LearnedPolicy(net)
    policy.reset(3)
    obs = _obs(np.random.default_rng(0), 3)
    cmd = policy(obs)
    with torch.no_grad():
        for i in range(3):
            raw, _ = net(torch.from_numpy(obs["depth"][i])[None, None, None],
                         torch.tensor([[[obs["desired_speed"][i]]]], dtype=torch.float32),
                         torch.tensor(obs["quat"][i], dtype=torch.float32)[None, None])
            expected = deploy_command(raw.reshape(1, 3).numpy(), obs["desired_speed"][i : i + 1])[0]
            assert cmd[i] == pytest.approx(expected, abs=1e-5)
    assert np.linalg.norm(cmd, axis=1) == pytest.approx(obs["desired_speed"])


def test_lstm_state_is_per_env_carried_and_reset():
    torch.manual_seed(0)
    net = create_model("lstmnet").eval()
    policy = LearnedPolicy(net)
    rng = np.random.default_rng(1)
    ticks = [_obs(rng, 2) for _ in range(3)]
    ticks[2]["active"] = np.array([True, False])  # env 1 finished its trial after tick 1

    def sequence_output(env, t_end):
        """The network over env's first t_end frames as one sequence from a zero state."""
        d = torch.from_numpy(np.stack([o["depth"][env] for o in ticks[:t_end]]))[None, :, None]
        s = torch.tensor([[[o["desired_speed"][env]] for o in ticks[:t_end]]], dtype=torch.float32)
        q = torch.tensor(np.stack([o["quat"][env] for o in ticks[:t_end]])[None], dtype=torch.float32)
        with torch.no_grad():
            return net(d, s, q)[0][0, -1].numpy()

    policy.reset(2)
    outs = [policy.raw_output(o) for o in ticks]
    assert outs[2][0] == pytest.approx(sequence_output(0, 3), rel=1e-4)
    assert outs[1][1] == pytest.approx(sequence_output(1, 2), rel=1e-4)
    assert outs[2][1] == pytest.approx([0, 0, 0])  # inactive: not computed
    # the state matters: the third frame alone gives another output
    assert not np.allclose(outs[2][0], policy.raw_output({**ticks[0], "active": np.array([False, False])})[0])
    # reset zeroes the state: the first tick again gives the first output
    policy.reset(2)
    assert policy.raw_output(ticks[0]) == pytest.approx(outs[0], abs=1e-6)
    policy.raw_output(ticks[1])
    policy.reset_envs([1])
    again = policy.raw_output(ticks[0])
    assert again[1] == pytest.approx(outs[0][1], abs=1e-6)  # env 1 restarted
    assert not np.allclose(again[0], outs[0][0], atol=1e-6)  # env 0 carried on


def test_onnxruntime_step_gives_the_eager_commands():
    from vitfly.deploy.onnx import OnnxPolicyRunner

    torch.manual_seed(0)
    net = create_model("lstmnet").eval()
    eager, onnx = LearnedPolicy(net), LearnedPolicy(net, step_fn=OnnxPolicyRunner(net))
    rng = np.random.default_rng(2)
    ticks = [_obs(rng, 3) for _ in range(3)]
    ticks[2]["active"] = np.array([True, False, True])
    eager.reset(3)
    onnx.reset(3)
    for obs in ticks:
        a, b = eager.raw_output(obs), onnx.raw_output(obs)
        assert b == pytest.approx(a, rel=1e-3, abs=1e-3)


# Take-off ramp as the original `compute_command_vision_based` applies it after clip/normalise/scale:
# while x < 2 m, vx = max(1, x / 2 * desired speed). Expected commands worked out by hand per x in RAMP_X.
RAMP_X = (0.0, 0.5, 1.9, 2.1)
RAMP_CASES = [
    # raw network output, desired speed m/s, expected command at x = 0, 0.5, 1.9, 2.1 m
    ((0.5, 0.0, 0.0), 5.0, [(1.0, 0, 0), (1.25, 0, 0), (4.75, 0, 0), (5.0, 0, 0)]),
    # x clipped to 1: (1, 4, 0) / sqrt(17) * 7 = (1.69775, 6.79100, 0); the ramp replaces vx only
    ((3.0, 4.0, 0.0), 7.0, [(1.0, 6.79100, 0), (1.75, 6.79100, 0), (6.65, 6.79100, 0), (1.69775, 6.79100, 0)]),
    # unit already: (1.8, 0, -2.4) at 3 m/s; at x = 0.5 the ramp's 0.75 m/s is raised to the 1 m/s floor
    ((0.6, 0.0, -0.8), 3.0, [(1.0, 0, -2.4), (1.0, 0, -2.4), (2.85, 0, -2.4), (1.8, 0, -2.4)]),
    # backwards (x clipped to -1): the ramp still commands forward flight while x < 2 m
    ((-2.0, 0.0, 0.0), 4.0, [(1.0, 0, 0), (1.0, 0, 0), (3.8, 0, 0), (-4.0, 0, 0)]),
]


def test_takeoff_ramp_by_hand():
    # max(1, x / 2 * speed) below 2 m, the given vx from 2 m on
    vx = takeoff_ramp(np.full(5, 6.0), np.array([0.0, 0.2, 1.0, 2.0, 3.0]), np.full(5, 6.0))
    assert vx == pytest.approx([1.0, 1.0, 3.0, 6.0, 6.0])


def _constant_convnet(raw):
    """A real ConvNet whose last layer has zero weights and bias ``raw``: it outputs ``raw`` for any input."""
    net = create_model("convnet").eval()
    with torch.no_grad():
        net.fc3.weight.zero_()
        net.fc3.bias.copy_(torch.tensor(raw))
    return net


@pytest.mark.parametrize(("raw", "speed", "expected"), RAMP_CASES)
def test_commands_with_the_takeoff_ramp_eager_and_onnxruntime(raw, speed, expected):
    from vitfly.deploy.onnx import OnnxPolicyRunner

    net = _constant_convnet(raw)
    n = len(RAMP_X)
    obs = {**_obs(np.random.default_rng(3), n), "desired_speed": np.full(n, speed),
           "position": np.array([[x, 0.0, 3.5] for x in RAMP_X])}
    for policy in (LearnedPolicy(net), LearnedPolicy(net, step_fn=OnnxPolicyRunner(net))):
        policy.reset(n)
        assert policy(obs) == pytest.approx(np.array(expected, dtype=np.float64), abs=1e-5)
    # vitfly's variant without the ramp: the full-speed command everywhere
    policy = LearnedPolicy(net, takeoff_ramp=False)
    policy.reset(n)
    assert policy(obs) == pytest.approx(np.tile(expected[-1], (n, 1)), abs=1e-5)


def test_ramp_needs_the_position():
    policy = LearnedPolicy(create_model("convnet"))
    policy.reset(1)
    obs = _obs(np.random.default_rng(4), 1)
    del obs["position"]
    with pytest.raises(ValueError, match="position"):
        policy(obs)
