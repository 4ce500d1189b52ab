"""`vitfly explain` and vitfly.eval.explain: maps with known answers, edge masks, metrics, the command end to end."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch
from PIL import Image
from torch import nn

from vitfly.cli import main
from vitfly.eval.explain import (
    EdgeConfig,
    edge_mass_share,
    explain_sequence,
    obstacle_edge_mask,
    received_attention_map,
    scene_edge_masks,
    temporal_consistency,
)
from vitfly.sim.camera import CameraConfig
from vitfly.sim.scenes import Scene
from vitfly.zoo import create_model, save_checkpoint
from vitfly.zoo.base import DepthPolicyNet
from vitfly.zoo.mix_transformer import EfficientSelfAttention

torch.set_num_threads(1)


class HalvesNet(DepthPolicyNet):
    """Feature channel 0 = the depth's left half (right half zeroed), channel 1 = its right half.

    Output: x = 1, y = w * sum(channel 0), z = -v * sum(channel 1): only the left half can move the
    lateral part, only the right half the vertical part.
    """

    spatial_layers = ("feature_map",)

    def __init__(self, w: float = 0.5, v: float = 0.25):
        super().__init__(use_state=True)
        self.w, self.v = w, v
        self.feature_map = nn.Identity()
        left = torch.zeros(60, 90)
        left[:, :45] = 1.0
        self.register_buffer("left", left)

    def encode(self, frames):
        return self.feature_map(torch.cat((frames * self.left, frames * (1 - self.left)), dim=1)).flatten(1)

    def head(self, features, state, hidden=None):
        f = features.reshape(*features.shape[:2], 2, 60 * 90)
        y = self.w * f[..., 0, :].sum(-1)
        z = -self.v * f[..., 1, :].sum(-1)
        return torch.stack((torch.ones_like(y), y, z), dim=-1), None


def _trial(t: int = 3, seed: int = 0):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.1, 1.0, (t, 60, 90)).astype(np.float32)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (t, 1))
    return depth, np.full(t, 5.0), quat


def test_gradcam_puts_each_part_of_the_command_where_it_comes_from():
    depth, speed, quat = _trial()
    seq = explain_sequence(HalvesNet(w=0.5, v=0.25), depth, speed, quat)
    # by hand (Grad-CAM: alpha_k = mean gradient over the map, cam = relu(sum_k alpha_k A_k)):
    # y = 0.5 sum(A0) > 0, so the lateral target is y: alpha_0 = 0.5, alpha_1 = 0 -> 0.5 * depth on the left;
    # z = -0.25 sum(A1) < 0, so the vertical target is -z: alpha_1 = 0.25 -> 0.25 * depth on the right
    left = np.zeros((60, 90), bool)
    left[:, :45] = True
    expected_lateral = np.where(left, 0.5 * depth, 0.0)
    expected_vertical = np.where(left, 0.0, 0.25 * depth)
    np.testing.assert_allclose(seq.maps["lateral"], expected_lateral, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(seq.maps["vertical"], expected_vertical, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(seq.maps["command"], expected_lateral + expected_vertical, rtol=1e-5, atol=1e-7)
    assert seq.maps["lateral"][:, ~left].sum() == 0.0  # all of the lateral map's mass on the left half
    assert seq.layers == ("feature_map",)
    np.testing.assert_allclose(seq.output[:, 1], 0.5 * np.where(left, depth, 0).sum(axis=(1, 2)), rtol=1e-5)


@pytest.mark.parametrize("name", ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18"])
def test_every_architecture_gets_its_maps_and_the_carried_state_gives_the_flight_outputs(name):
    torch.manual_seed(0)
    net = create_model(name).eval()
    depth, speed, quat = _trial(3)
    seq = explain_sequence(net, depth, speed, quat)
    expected = {"command", "lateral", "vertical"}
    if name.startswith("vit"):
        expected |= {"attention", "attention_stage0", "attention_stage1"}
    assert set(seq.maps) == expected
    for m in seq.maps.values():
        assert m.shape == (3, 60, 90) and np.all(np.isfinite(m)) and m.min() >= 0.0
    # tick by tick with the carried state (and the attention hooks on) == one pass over the sequence
    with torch.no_grad():
        speed_t = torch.tensor(speed, dtype=torch.float32).reshape(1, 3, 1)
        whole, _ = net(torch.from_numpy(depth)[None, :, None], speed_t, torch.tensor(quat, dtype=torch.float32)[None])
    np.testing.assert_allclose(seq.output, whole[0].double().numpy(), rtol=1e-4, atol=1e-6)


def _hand_set_attention(s: float, t: float) -> EfficientSelfAttention:
    """2 channels, 1 head, R = 2: reduced token (i, j) = LayerNorm of token (2i, 2j); keys s * that, values
    that, query (t, -t), identity output layer."""
    attn = EfficientSelfAttention(channels=2, reduction_ratio=2, num_heads=1)
    with torch.no_grad():
        attn.cn1.weight.zero_()
        attn.cn1.weight[0, 0, 0, 0] = attn.cn1.weight[1, 1, 0, 0] = 1.0
        attn.cn1.bias.zero_()
        attn.keyValueExtractor.weight.copy_(torch.cat((s * torch.eye(2), torch.eye(2))))
        attn.keyValueExtractor.bias.zero_()
        attn.query.weight.zero_()
        attn.query.bias.copy_(torch.tensor([t, -t]))
        attn.finalLayer.weight.copy_(torch.eye(2))
        attn.finalLayer.bias.zero_()
    return attn


def test_hand_set_attention_layer_weights_output_and_map():
    s, t = 1.5, 2.0
    attn = _hand_set_attention(s, t)
    # 4 x 4 tokens: channels (a, b) = (1, -1) at token (0, 0), (-1, 1) elsewhere, so key 0 normalises to
    # +n (1, -1) and keys 1..3 to -n (1, -1), n = 1 / sqrt(1 + eps) (LayerNorm of (+-1, -+1), eps 1e-5)
    grid = torch.tensor([-1.0, 1.0]).repeat(4, 4, 1)
    grid[0, 0] = torch.tensor([1.0, -1.0])
    x = grid.reshape(1, 16, 2)
    n = 1.0 / math.sqrt(1.0 + 1e-5)
    z = 2.0 * n * s * t / math.sqrt(2.0)  # q . k / sqrt(d) for key 0; -z for the others
    p0 = math.exp(z) / (math.exp(z) + 3.0 * math.exp(-z))
    p1 = (1.0 - p0) / 3.0
    weights = attn.attention_weights(x, 4, 4).detach()
    assert weights.shape == (1, 1, 16, 4)
    np.testing.assert_allclose(weights[0, 0].numpy(), np.tile([p0, p1, p1, p1], (16, 1)), rtol=1e-5)
    # the forward pass (fused kernel) gives sum_k p_k v_k, values = the normalised keys (identity output layer)
    out = attn(x, 4, 4).detach().numpy()
    np.testing.assert_allclose(out[0], np.tile([n * (p0 - 3 * p1), -n * (p0 - 3 * p1)], (16, 1)), rtol=1e-5, atol=1e-6)
    # the image map: key 0 covers the top-left 2 x 2 tokens = 4 x 4 pixels of an 8 x 8 image, p0 / 16 each
    image = received_attention_map(weights, (4, 4), 2, out_hw=(8, 8))[0].numpy()
    expected = np.full((8, 8), p1 / 16)
    expected[:4, :4] = p0 / 16
    np.testing.assert_allclose(image, expected, rtol=1e-5)


def test_vit_stage0_keys_cover_only_the_top_left_of_the_image():
    torch.manual_seed(0)
    depth, speed, quat = _trial(2)
    seq = explain_sequence(create_model("vit").eval(), depth, speed, quat)
    # stage 0: 15 x 23 tokens (stride 4), R = 8 -> a 1 x 2 key grid covering tokens rows 0-7, columns 0-15,
    # i.e. image rows 0-31 and columns up to 62 (column c shows token floor(c * 23 / 90)); nothing else
    stage0 = seq.maps["attention_stage0"]
    assert stage0[:, 32:, :].max() == 0.0 and stage0[:, :, 63:].max() == 0.0
    assert (stage0[:, :32, :63] > 0).all()
    # stage 1: 8 x 12 tokens, R = 4 -> 2 x 3 keys covering every token
    assert (seq.maps["attention_stage1"] > 0).all()
    for kind in ("attention_stage0", "attention_stage1", "attention"):
        np.testing.assert_allclose(seq.maps[kind].sum(axis=(1, 2)), 1.0, rtol=1e-5)


def test_obstacle_edges_are_the_near_side_of_jumps_on_obstacles_only():
    inf = np.inf
    depth = np.full((10, 10), inf)
    obstacle = np.full((10, 10), inf)
    obstacle[3:7, 3:7] = 3.0  # a square obstacle 3 m away
    depth[3:7, 3:7] = 3.0
    depth[8, :], depth[9, :] = 9.8, 8.0  # ground, nothing within range above it: a 0.2 m and a 1.8 m jump
    mask = obstacle_edge_mask(depth, obstacle, 10.0, EdgeConfig(jump_m=0.5, width_px=0))
    ring = np.zeros((10, 10), bool)
    ring[3:7, 3:7] = True
    ring[4:6, 4:6] = False  # the square's border pixels, nothing on the ground
    np.testing.assert_array_equal(mask, ring)
    wide = obstacle_edge_mask(depth, obstacle, 10.0, EdgeConfig(jump_m=0.5, width_px=1))
    assert wide[2:8, 2:8].all() and wide.sum() == 36


def test_scene_edges_of_a_box_face_match_its_projection():
    # the front face of a box (x = 5 m, y in [-1, 1], z in [2.5, 4.5]) seen from (0, 0, 3.5) looking along +x:
    # by hand, pixel ray (1, u, v) hits it when |5 u| <= 1 and |5 v| <= 1; edges = face pixels with a
    # 4-neighbour off the face (10 m of nothing or the far ground behind); the ground's own jumps do not count
    scene = Scene("window", "medium", 0, np.zeros((0, 4)), np.zeros((0, 5)), np.array([[5, -1, 2.5, 6, 1, 4.5]]))
    # a square-pixel 90 degree camera at the body origin keeps the hand arithmetic short (any geometry works)
    camera = CameraConfig(horizontal_fov_deg=90.0, vertical_fov_deg=2 * math.degrees(math.atan(2 / 3)),
                          mount_offset_m=(0.0, 0.0, 0.0))
    masks, mismatch = scene_edge_masks(scene, camera, np.array([[0.0, 0.0, 3.5]]), np.array([[1.0, 0, 0, 0]]),
                                       config=EdgeConfig(width_px=0))  # fmt: skip
    tan_h = 1.0  # tan(90 deg / 2)
    u = tan_h * (1 - 2 * (np.arange(90) + 0.5) / 90)
    v = tan_h * 60 / 90 * (1 - 2 * (np.arange(60) + 0.5) / 60)
    face = (np.abs(5 * v)[:, None] <= 1) & (np.abs(5 * u)[None, :] <= 1)
    padded = np.pad(face, 1)
    interior = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    np.testing.assert_array_equal(masks[0], face & ~interior)
    assert mismatch == 0.0


def test_temporal_consistency_by_hand():
    a = np.random.default_rng(0).random((60, 90))
    assert temporal_consistency(np.stack([a, a, a])) == {"consistency": pytest.approx(1.0), "consistency_pairs": 2}
    flipped = a.max() - a  # perfectly anti-correlated with a
    assert temporal_consistency(np.stack([a, flipped, a]))["consistency"] == pytest.approx(-1.0)
    # a blank map has no correlation with anything: its pairs are left out
    assert temporal_consistency(np.stack([np.zeros_like(a), a, a])) == {"consistency": pytest.approx(1.0),
                                                                         "consistency_pairs": 1}


def test_edge_mass_share_by_hand():
    edges = np.zeros((3, 60, 90), bool)
    edges[0, :, :9] = True  # 10 % of the pixels
    edges[1, :6, :] = True  # 10 %
    uniform = np.ones((3, 60, 90))
    out = edge_mass_share(uniform, edges)  # tick 2 has no edges: left out
    assert out["edge_ticks"] == 2
    assert out["edge_mass_share"] == pytest.approx(0.1) and out["edge_lift"] == pytest.approx(1.0)
    on_edges = edge_mass_share(edges.astype(float), edges)
    assert on_edges["edge_mass_share"] == pytest.approx(1.0) and on_edges["edge_lift"] == pytest.approx(10.0)


def test_explain_command_end_to_end(tmp_path, capsys):
    ckpt = tmp_path / "tiny.ckpt"
    torch.manual_seed(0)
    save_checkpoint(create_model("convnet"), "convnet", True, ckpt)
    out = tmp_path / "out"
    args = ["explain", "--policy", str(ckpt), "random:vit_lstm", "--env", "spheres", "--seed", "1", "--speed", "7",
            "--max-ticks", "6", "--frames", "3", "--gif-stride", "2", "--out", str(out)]
    assert main(args) == 0
    summary = json.loads((out / "explain.json").read_text())
    assert [m["label"] for m in summary["models"]] == ["tiny", "vit_lstm (random weights)"]
    assert [m["random_weights"] for m in summary["models"]] == [False, True]
    assert summary["models"][0]["gradcam_layers"] == ["feature_map"]
    # the scene re-rendered at the logged poses reproduces the frames the models saw: exact edges
    assert summary["trial"]["edge_source"] == "scene" and summary["trial"]["edge_rerender_mismatch_share"] == 0.0
    assert summary["trial"]["ticks"] == 6 and summary["strip_ticks"] == [0, 2, 5]
    with open(out / "explain.csv") as f:
        rows = list(csv.DictReader(f))
    assert {(r["model"], r["map"]) for r in rows} == {
        *(("tiny", k) for k in ("command", "lateral", "vertical")),
        *(("vit_lstm (random weights)", k) for k in ("command", "lateral", "vertical", "attention",
                                                     "attention_stage0", "attention_stage1")),
    }
    for name in ("strip_tiny.png", "strip_vit_lstm_random_weights.png", "side_by_side.png"):
        with Image.open(out / name) as im:
            assert im.size[0] > 400
    for name in ("tiny.gif", "vit_lstm_random_weights.gif", "side_by_side.gif"):
        with Image.open(out / name) as im:
            assert im.n_frames == 3  # ticks 0, 2, 4
    assert "attention" in capsys.readouterr().out


def test_explain_replays_a_collected_trajectory_with_exact_edges(tmp_path, capsys):
    data = tmp_path / "d.h5"
    assert main(["collect", "--out", str(data), "--trajectories", "1", "--speeds", "7", "7", "--seed", "3"]) == 0
    out = tmp_path / "out"
    assert main(["explain", "--data", str(data), "--trajectory", "0", "--policy", "random:convnet",
                 "--max-ticks", "4", "--no-gif", "--out", str(out)]) == 0  # fmt: skip
    summary = json.loads((out / "explain.json").read_text())
    # the scene rebuilt from the file's collect config reproduces its stored (uint8) frames
    assert summary["trial"]["edge_source"] == "scene" and summary["trial"]["source"] == "recorded"
    assert not list(out.glob("*.gif"))


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--policy", "missing.ckpt"], "missing.ckpt: no such checkpoint"),
        (["--policy", "pretrained:resnet18"], "pretrained:resnet18: not in"),
        (["--policy", "random:vit_gru"], "unknown model 'vit_gru'"),
        (["--policy", "random:convnet", "--data", "x.h5", "--seed", "3"], "--seed only apply to a flown trial"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    assert main(["explain", *extra, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not out.exists()
