"""LSTMnet: a small CNN encoder feeding a 2-layer LSTM (2,949,937 parameters).

conv1 (1->4, k5, s3, p1) -> ReLU -> bn1 -> min-pool k3; conv2 (4->10, k3, s2) -> ReLU -> bn2 -> avg-pool k3;
flatten (660) + state (5) -> LSTM(665 -> 395, 2 layers, dropout 0.15, no biases)
-> SN fc1 64 (leaky ReLU) -> SN fc2 16 (leaky ReLU) -> SN fc3 3. Parameter names follow the original.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vitfly.zoo.base import DepthPolicyNet, Hidden
from vitfly.zoo.layers import STATE_DIM, SNLinear, min_pool2d
from vitfly.zoo.recurrent import run_lstm, zero_hidden
from vitfly.zoo.registry import register_model


class LSTMNet(DepthPolicyNet):
    """CNN encoder + LSTM over the frames of each sequence."""

    model_name = "lstmnet"
    spatial_layers = ("feature_map",)
    is_recurrent = True
    feature_dim = 10 * 6 * 11

    def __init__(self, use_state: bool = True, lstm_dropout: float = 0.15) -> None:
        super().__init__(use_state)
        self.conv1 = nn.Conv2d(1, 4, kernel_size=5, stride=3, padding=1)
        self.bn1 = nn.BatchNorm2d(4)
        self.conv2 = nn.Conv2d(4, 10, kernel_size=3, stride=2)
        self.bn2 = nn.BatchNorm2d(10)
        self.feature_map = nn.Identity()  # hook point: the last spatial features (no parameters)
        self.lstm = nn.LSTM(
            self.feature_dim + STATE_DIM, 395, num_layers=2, dropout=lstm_dropout, bias=False, batch_first=True
        )
        self.fc1 = SNLinear(395, 64)
        self.fc2 = SNLinear(64, 16)
        self.fc3 = SNLinear(16, 3)

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        x = min_pool2d(self.bn1(F.relu(self.conv1(frames))), 3, 1)  # (N, 4, 18, 28)
        x = self.feature_map(F.avg_pool2d(self.bn2(F.relu(self.conv2(x))), 3, 1))  # (N, 10, 6, 11)
        return x.flatten(1)

    def head(self, features: torch.Tensor, state: torch.Tensor, hidden: Hidden | None = None):
        x, hidden = run_lstm(self.lstm, torch.cat((features, state), dim=-1), hidden)
        x = F.leaky_relu(self.fc1(x))
        x = F.leaky_relu(self.fc2(x))
        return self.fc3(x), hidden

    def initial_hidden(self, batch_size: int, device=None, dtype=None) -> Hidden:
        return zero_hidden(self.lstm, batch_size, device, dtype)


@register_model
def lstmnet(use_state: bool = True, lstm_dropout: float = 0.15) -> LSTMNet:
    """The paper's LSTMnet (2,949,937 parameters)."""
    return LSTMNet(use_state=use_state, lstm_dropout=lstm_dropout)
