"""ViT: a two-stage mix-transformer encoder with a fully connected head (3,101,199 parameters).

Encoder: stage 0 (1 -> 32 ch, (15, 23) tokens), stage 1 (32 -> 64 ch, (8, 12) tokens); fusion:
PixelShuffle(2) of stage 1 + bilinear upsampling of stage 0 to (16, 24), concat (48 ch),
down_sample conv -> (12, 16, 24) -> flatten 4608 -> decoder Linear 512. Head: + state (5) ->
SN nn_fc1 256 (leaky ReLU) -> SN nn_fc2 3. ``ViTBackbone`` is shared with ViT+LSTM.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vitfly.zoo.base import DepthPolicyNet, Hidden
from vitfly.zoo.layers import STATE_DIM, SNLinear
from vitfly.zoo.mix_transformer import MixTransformerStage
from vitfly.zoo.registry import register_model

FUSED_SHAPE = (12, 16, 24)
FUSED_DIM = 12 * 16 * 24


class ViTBackbone(DepthPolicyNet):
    """The two mix-transformer stages and their fusion; ``fused_features`` gives (N, 4608)."""

    spatial_layers = ("down_sample",)  # the fused (N, 12, 16, 24) map, flattened into the decoder

    def __init__(self, use_state: bool = True) -> None:
        super().__init__(use_state)
        self.encoder_blocks = nn.ModuleList(
            [
                MixTransformerStage(1, 32, patch_size=7, stride=4, padding=3, n_layers=2, reduction_ratio=8,
                                    num_heads=1, expansion=8),
                MixTransformerStage(32, 64, patch_size=3, stride=2, padding=1, n_layers=2, reduction_ratio=4,
                                    num_heads=2, expansion=8),
            ]
        )  # fmt: skip
        self.pixel_shuffle = nn.PixelShuffle(2)
        self.upsample = nn.Upsample(size=FUSED_SHAPE[1:], mode="bilinear", align_corners=True)
        self.down_sample = nn.Conv2d(48, FUSED_SHAPE[0], kernel_size=3, padding=1)

    def stages(self, frames: torch.Tensor) -> list[torch.Tensor]:
        """Token grids of both stages: (N, 32, 15, 23) and (N, 64, 8, 12)."""
        outputs = []
        x = frames
        for stage in self.encoder_blocks:
            x = stage(x)
            outputs.append(x)
        return outputs

    def fused_features(self, frames: torch.Tensor) -> torch.Tensor:
        first, second = self.stages(frames)
        shuffled = self.pixel_shuffle(second)  # (N, 16, 16, 24)
        upsampled = self.upsample(first)  # (N, 32, 16, 24)
        return self.down_sample(torch.cat((shuffled, upsampled), dim=1)).flatten(1)


class ViT(ViTBackbone):
    """Mix-transformer encoder + fully connected head; frames are independent (hidden is always None)."""

    model_name = "vit"

    def __init__(self, use_state: bool = True) -> None:
        super().__init__(use_state)
        self.decoder = nn.Linear(FUSED_DIM, 512)
        self.nn_fc1 = SNLinear(512 + STATE_DIM, 256)
        self.nn_fc2 = SNLinear(256, 3)

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.fused_features(frames))

    def head(self, features: torch.Tensor, state: torch.Tensor, hidden: Hidden | None = None):
        x = F.leaky_relu(self.nn_fc1(torch.cat((features, state), dim=-1)))
        return self.nn_fc2(x), None


@register_model
def vit(use_state: bool = True) -> ViT:
    """The paper's ViT (3,101,199 parameters)."""
    return ViT(use_state=use_state)
