"""Per-tick maps of what a zoo network looks at, over one trial: one documented method per map kind.

Grad-CAM of the command (every architecture that names its ``spatial_layers``; captum's
``LayerGradCam``, Selvaraju et al. 2017): at tick t, with the recurrent state carried from ticks < t,
the network's output at tick t is attributed to its last spatial feature maps A_k (channels k):
``cam = sum_k mean_ij(d target / d A_k) * A_k``, upsampled bilinearly to 60 x 90. Targets, in the
network's output units (velocity / desired speed, world frame):

- ``lateral``: the lateral part y with the sign it has at that tick (``sign(y) * y``: what made the
  network steer the way it did), ReLU;
- ``vertical``: the same for the vertical part z;
- ``command``: ``sign(y) * y + sign(z) * z`` (how far the command turns away from straight ahead),
  i.e. ReLU of the two unrectified maps added.

When the head reads several spatial maps (UNet+LSTM: conv branch and U-Net bottleneck), they form one
cut of the network: their unrectified maps are upsampled and added before the ReLU.

Attention (networks with mix-transformer stages: ViT, ViT+LSTM): every efficient self-attention layer's
weights ``softmax(q k^T / sqrt(d))`` (N, heads, L tokens, L' reduced keys) are averaged over heads and
queries, giving the share of attention each key receives; each key's share is spread evenly over the
tokens its R x R reduction patch covers (tokens no key covers get none) and the token grid is upsampled
to 60 x 90 by nearest neighbour, keeping the total at 1. ``attention_stage<i>`` averages the layers of
stage i; ``attention`` averages the stages. With the paper's ViT the key grids are only 1 x 2 (stage
0, R = 8 on 15 x 23 tokens, covering the top-left 32 x 64 pixels) and 2 x 3 (stage 1): the attention
maps are coarse by construction, the Grad-CAM maps (16 x 24 grid) are the finer view.

All maps are non-negative float32 (T, 60, 90); each map kind is one entry of ``SequenceMaps.maps``.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from captum.attr import LayerAttribution, LayerGradCam
from torch import nn

from vitfly.errors import VitflyError
from vitfly.zoo.mix_transformer import EfficientSelfAttention, MixTransformerStage

IMAGE_HW = (60, 90)
GRADCAM_MAPS = ("command", "lateral", "vertical")

METHODS = {
    "command": "Grad-CAM (captum LayerGradCam) at the last spatial layer(s) of sign(y)*y + sign(z)*z of the output",
    "lateral": "Grad-CAM (captum LayerGradCam) at the last spatial layer(s) of sign(y)*y, the lateral output",
    "vertical": "Grad-CAM (captum LayerGradCam) at the last spatial layer(s) of sign(z)*z, the vertical output",
    "attention": "spatial-reduction attention received per key, head- and query-averaged, mean of the stages",
    "attention_stage": "spatial-reduction attention received per key, head- and query-averaged, mean of the "
    "stage's layers",
}


@dataclass
class SequenceMaps:
    """Maps of one network over one trial.

    maps: map kind -> (T, 60, 90) float32 >= 0; output: (T, 3) the network's output at every tick
    (velocity / desired speed, world frame), with the recurrent state carried through the trial;
    layers: the modules Grad-CAM attributed to (dotted names).
    """

    maps: dict[str, np.ndarray]
    output: np.ndarray
    layers: tuple[str, ...]

    @property
    def primary(self) -> str:
        """The map shown first: attention where the network has it, else the command's Grad-CAM."""
        return "attention" if "attention" in self.maps else "command"


def spatial_layers(net: nn.Module) -> list[tuple[str, nn.Module]]:
    """(name, module) of the network's ``spatial_layers`` (its last spatial feature maps)."""
    modules = dict(net.named_modules())
    names = tuple(getattr(net, "spatial_layers", ()))
    missing = [n for n in names if n not in modules]
    if missing:
        raise VitflyError(f"{type(net).__name__}.spatial_layers names modules it does not have: {', '.join(missing)}")
    return [(n, modules[n]) for n in names]


def attention_layers(net: nn.Module) -> list[list[EfficientSelfAttention]]:
    """The attention layers of each mix-transformer stage, stage by stage (empty for other networks)."""
    return [list(m._attn) for m in net.modules() if isinstance(m, MixTransformerStage)]


def received_attention_map(
    weights: torch.Tensor, token_hw: tuple[int, int], reduction: int, out_hw: tuple[int, int] = IMAGE_HW
) -> torch.Tensor:
    """Image map (N, H, W), summing to 1, of the attention each key receives.

    weights: (N, heads, L, L') attention rows over L' keys, L = h * w tokens, the keys in row-major
    order of the (h // R, w // R) reduced grid. Each key's head- and query-averaged weight is spread
    evenly over its R x R tokens; tokens covered by no key get 0; nearest-neighbour upsampling.
    """
    h, w = token_hw
    hr, wr = h // reduction, w // reduction
    n = weights.shape[0]
    received = weights.float().mean(dim=(1, 2)).reshape(n, hr, wr)  # sums to 1 over the keys
    patch = received.repeat_interleave(reduction, 1).repeat_interleave(reduction, 2) / reduction**2
    tokens = weights.new_zeros((n, h, w), dtype=torch.float32)
    tokens[:, : hr * reduction, : wr * reduction] = patch
    image = F.interpolate(tokens[:, None], size=out_hw, mode="nearest")[:, 0]
    return image / image.sum(dim=(1, 2), keepdim=True).clamp_min(1e-12)  # replication is uneven (23 -> 90)


class AttentionRecorder:
    """Forward hooks on every efficient self-attention layer: each records its image map while enabled."""

    def __init__(self, stages: list[list[EfficientSelfAttention]]):
        self.stages = stages
        self.enabled = False
        self.last: dict[int, torch.Tensor] = {}  # id(layer) -> (N, 60, 90)
        self._handles = [layer.register_forward_hook(self._hook) for stage in stages for layer in stage]

    def _hook(self, module: EfficientSelfAttention, inputs: tuple, _output) -> None:
        if not self.enabled:
            return
        x, h, w = inputs
        with torch.no_grad():
            weights = module.attention_weights(x, h, w)
        self.last[id(module)] = received_attention_map(weights, (h, w), module.cn1.kernel_size[0])

    @contextlib.contextmanager
    def recording(self):
        self.enabled, self.last = True, {}
        try:
            yield
        finally:
            self.enabled = False

    def stage_maps(self) -> list[torch.Tensor]:
        """Per stage, the mean over its layers of the last recorded maps (N, 60, 90)."""
        return [torch.stack([self.last[id(layer)] for layer in stage]).mean(0) for stage in self.stages]

    def remove(self) -> None:
        for handle in self._handles:
            handle.remove()


def _expand_hidden(hidden, n: int):
    return None if hidden is None else tuple(h.expand(-1, n, -1).contiguous() for h in hidden)


def gradcam_tick(
    net: nn.Module,
    layers: list[nn.Module],
    depth: torch.Tensor,
    desired_speed: torch.Tensor,
    quat: torch.Tensor,
    hidden,
    output: torch.Tensor,
) -> torch.Tensor:
    """Unrectified Grad-CAM (2, 60, 90) of one tick: row 0 for sign(y) * y, row 1 for sign(z) * z.

    depth (1, 1, 1, 60, 90), desired_speed (1, 1, 1), quat (1, 1, 4), hidden the state before this
    tick (None for feed-forward networks), output (3,) the network's output at this tick. The frame is
    duplicated so one backward pass per layer serves both targets.
    """
    signs = torch.where(output[1:] < 0, -1.0, 1.0).to(depth)
    hidden2 = _expand_hidden(hidden, 2)

    def targets(frames: torch.Tensor) -> torch.Tensor:  # (2, 1, 60, 90) -> (2, 2)
        n = frames.shape[0]
        out, _ = net(frames[:, None], desired_speed.expand(n, 1, 1), quat.expand(n, 1, 4), hidden2)
        return out[:, 0, 1:] * signs

    # the frames require grad so that every layer output does, parameters before it or not
    frames = depth.reshape(1, 1, *IMAGE_HW).expand(2, 1, *IMAGE_HW).clone().requires_grad_(True)
    total = torch.zeros((2, *IMAGE_HW), device=depth.device)
    for layer in layers:
        cam = LayerGradCam(targets, layer).attribute(frames, target=[0, 1], relu_attributions=False)
        total += LayerAttribution.interpolate(cam.detach().float(), IMAGE_HW, interpolate_mode="bilinear")[:, 0]
    return total


def explain_sequence(
    net: nn.Module,
    depth: np.ndarray,
    desired_speed: np.ndarray,
    quat: np.ndarray,
    device: str | torch.device = "cpu",
) -> SequenceMaps:
    """All maps of ``net`` over one trial (depth (T, 60, 90) in [0, 1], desired_speed (T,) m/s, quat (T, 4)).

    The network runs tick by tick as in flight (eval mode, recurrent state zeroed at the start and
    carried); each tick's maps explain that tick's output.
    """
    device = torch.device(device)
    net = net.eval().to(device)
    named = spatial_layers(net)
    stages = attention_layers(net)
    if not named and not stages:
        raise VitflyError(f"{type(net).__name__} declares no spatial_layers and has no attention layers: "
                          "nothing to explain (set spatial_layers on the class)")
    layers = [m for _, m in named]
    t_steps = len(depth)
    depth_t = torch.as_tensor(np.asarray(depth, dtype=np.float32), device=device)
    speed_t = torch.as_tensor(np.asarray(desired_speed, dtype=np.float32), device=device).reshape(-1, 1, 1, 1)
    quat_t = torch.as_tensor(np.asarray(quat, dtype=np.float32), device=device).reshape(-1, 1, 1, 4)
    maps: dict[str, np.ndarray] = {}
    if layers:
        maps.update({k: np.zeros((t_steps, *IMAGE_HW), np.float32) for k in GRADCAM_MAPS})
    if stages:
        maps.update({f"attention_stage{i}": np.zeros((t_steps, *IMAGE_HW), np.float32) for i in range(len(stages))})
        maps["attention"] = np.zeros((t_steps, *IMAGE_HW), np.float32)
    outputs = np.zeros((t_steps, 3), np.float64)
    recorder = AttentionRecorder(stages) if stages else None
    init = getattr(net, "initial_hidden", None)
    hidden = init(1, device=device) if getattr(net, "is_recurrent", False) and init is not None else None
    # cuDNN's RNN backward refuses eval mode; the attribution passes need it in eval mode
    no_cudnn = torch.backends.cudnn.flags(enabled=False) if device.type == "cuda" else contextlib.nullcontext()
    try:
        with no_cudnn:
            for t in range(t_steps):
                d = depth_t[t].reshape(1, 1, 1, *IMAGE_HW)
                with torch.no_grad(), recorder.recording() if recorder else contextlib.nullcontext():
                    out, hidden_next = net(d, speed_t[t], quat_t[t], hidden)
                outputs[t] = out.reshape(3).double().cpu().numpy()
                if recorder:
                    stage_maps = recorder.stage_maps()
                    for i, m in enumerate(stage_maps):
                        maps[f"attention_stage{i}"][t] = m[0].cpu().numpy()
                    maps["attention"][t] = torch.stack(stage_maps).mean(0)[0].cpu().numpy()
                if layers:
                    with torch.enable_grad():
                        raw = gradcam_tick(net, layers, d, speed_t[t], quat_t[t], hidden, out.reshape(3).detach())
                    maps["lateral"][t] = F.relu(raw[0]).cpu().numpy()
                    maps["vertical"][t] = F.relu(raw[1]).cpu().numpy()
                    maps["command"][t] = F.relu(raw[0] + raw[1]).cpu().numpy()
                hidden = None if hidden_next is None else tuple(h.detach() for h in hidden_next)
    finally:
        if recorder:
            recorder.remove()
    return SequenceMaps(maps=maps, output=outputs, layers=tuple(n for n, _ in named))
