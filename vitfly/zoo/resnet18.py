"""ResNet-18: timm's resnet18 with one input channel as the image encoder (paper: "also trained").

Encoder: ``timm.create_model("resnet18", in_chans=1, num_classes=0, pretrained=False)`` -> pooled 512
features; head: + state (5) -> Linear 256 (leaky ReLU) -> Linear 3. Nothing is ever downloaded.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vitfly.zoo.base import DepthPolicyNet, Hidden
from vitfly.zoo.layers import STATE_DIM
from vitfly.zoo.registry import register_model


class ResNet18Policy(DepthPolicyNet):
    """timm ResNet-18 encoder + small MLP head; frames are independent (hidden is always None)."""

    model_name = "resnet18"
    spatial_layers = ("encoder.layer4",)  # (N, 512, 2, 3) before timm's global pooling

    def __init__(self, use_state: bool = True, head_hidden: int = 256) -> None:
        super().__init__(use_state)
        import timm  # here, not at the top: timm imports torchvision, seconds that only ResNet-18 needs

        self.encoder = timm.create_model("resnet18", pretrained=False, in_chans=1, num_classes=0)
        self.fc1 = nn.Linear(self.encoder.num_features + STATE_DIM, head_hidden)
        self.fc2 = nn.Linear(head_hidden, 3)

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        return self.encoder(frames)

    def head(self, features: torch.Tensor, state: torch.Tensor, hidden: Hidden | None = None):
        x = F.leaky_relu(self.fc1(torch.cat((features, state), dim=-1)))
        return self.fc2(x), None


@register_model
def resnet18(use_state: bool = True, head_hidden: int = 256) -> ResNet18Policy:
    """timm ResNet-18 (1 input channel, random init) with the state vector and an MLP head."""
    return ResNet18Policy(use_state=use_state, head_hidden=head_hidden)
