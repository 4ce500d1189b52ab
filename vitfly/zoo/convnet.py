"""ConvNet: the paper's lightweight CNN baseline (235,269 parameters).

conv1 (1->4, k3, s3) -> ReLU -> bn1 -> min-pool k2; conv2 (4->10, k3, s2) -> ReLU -> avg-pool k3;
flatten (840) + state (5) -> fc0 256 -> fc1 64 (leaky ReLU) -> fc2 32 (tanh) -> fc3 3.
Parameter names follow the original checkpoints.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vitfly.zoo.base import DepthPolicyNet, Hidden
from vitfly.zoo.layers import STATE_DIM, min_pool2d
from vitfly.zoo.registry import register_model


class ConvNet(DepthPolicyNet):
    """Feed-forward CNN; every frame is processed independently (hidden is always None)."""

    model_name = "convnet"
    spatial_layers = ("feature_map",)
    feature_dim = 10 * 7 * 12

    def __init__(self, use_state: bool = True) -> None:
        super().__init__(use_state)
        self.conv1 = nn.Conv2d(1, 4, kernel_size=3, stride=3)
        self.bn1 = nn.BatchNorm2d(4)
        self.conv2 = nn.Conv2d(4, 10, kernel_size=3, stride=2)
        self.feature_map = nn.Identity()  # hook point: the last spatial features (no parameters)
        self.fc0 = nn.Linear(self.feature_dim + STATE_DIM, 256, bias=False)
        self.fc1 = nn.Linear(256, 64, bias=False)
        self.fc2 = nn.Linear(64, 32, bias=False)
        self.fc3 = nn.Linear(32, 3)

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        x = min_pool2d(self.bn1(F.relu(self.conv1(frames))), 2, 1)  # (N, 4, 19, 29)
        x = self.feature_map(F.avg_pool2d(F.relu(self.conv2(x)), 3, 1))  # (N, 10, 7, 12)
        return x.flatten(1)

    def head(self, features: torch.Tensor, state: torch.Tensor, hidden: Hidden | None = None):
        x = torch.cat((features, state), dim=-1)
        x = F.leaky_relu(self.fc0(x))
        x = F.leaky_relu(self.fc1(x))
        x = torch.tanh(self.fc2(x))
        return self.fc3(x), None


@register_model
def convnet(use_state: bool = True) -> ConvNet:
    """The paper's ConvNet (235,269 parameters)."""
    return ConvNet(use_state=use_state)
