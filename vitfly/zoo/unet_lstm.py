"""UNet+LSTM: a small U-Net whose output and bottleneck feed a conv branch and a 2-layer LSTM.

2,955,822 parameters. Layer facts in MODELS.md; parameter names follow the original checkpoints.
The conv branch sees the depth image stacked with the U-Net's output; the LSTM sees
[conv branch (660), U-Net bottleneck (2400), state (5)] = 3065 features per frame.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vitfly.zoo.base import DepthPolicyNet, Hidden
from vitfly.zoo.layers import STATE_DIM, SNLinear, min_pool2d
from vitfly.zoo.recurrent import run_lstm, zero_hidden
from vitfly.zoo.registry import register_model


def _conv3(c_in: int, c_out: int) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, kernel_size=3, padding=1)


class UNetLSTM(DepthPolicyNet):
    """U-Net encoder/decoder + conv branch + LSTM head."""

    model_name = "unet_lstm"
    # the head sees the conv branch and the U-Net bottleneck: both spatial maps, together
    spatial_layers = ("branch_map", "bottleneck_map")
    is_recurrent = True
    feature_dim = 10 * 6 * 11 + 16 * 10 * 15

    def __init__(self, use_state: bool = True, lstm_dropout: float = 0.15) -> None:
        super().__init__(use_state)
        self.unet_e11, self.unet_e12 = _conv3(1, 4), _conv3(4, 4)
        self.unet_pool1 = nn.MaxPool2d(kernel_size=2, stride=3)
        self.unet_e21, self.unet_e22 = _conv3(4, 8), _conv3(8, 8)
        self.unet_pool2 = nn.MaxPool2d(kernel_size=2, stride=2)
        self.unet_e31, self.unet_e32 = _conv3(8, 16), _conv3(16, 16)
        self.unet_upconv1 = nn.ConvTranspose2d(16, 8, kernel_size=2, stride=2)
        self.unet_d11, self.unet_d12 = _conv3(16, 8), _conv3(8, 8)
        self.unet_upconv2 = nn.ConvTranspose2d(8, 4, kernel_size=3, stride=3)
        self.unet_d21, self.unet_d22 = _conv3(8, 4), _conv3(4, 4)
        self.unet_out = nn.Conv2d(4, 1, kernel_size=1)
        self.conv_conv1 = nn.Conv2d(2, 4, kernel_size=5, stride=3)
        self.conv_bn1 = nn.BatchNorm2d(4)
        self.conv_conv2 = nn.Conv2d(4, 10, kernel_size=5, stride=2)
        # hook points (no parameters): the two spatial maps the head reads
        self.branch_map = nn.Identity()
        self.bottleneck_map = nn.Identity()
        self.lstm = nn.LSTM(
            self.feature_dim + STATE_DIM, 200, num_layers=2, dropout=lstm_dropout, bias=False, batch_first=True
        )
        self.nn_fc1 = SNLinear(200, 64)
        self.nn_fc2 = SNLinear(64, 32)
        self.nn_fc3 = SNLinear(32, 3)

    def unet(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """U-Net output (N, 1, 60, 90) and bottleneck features (N, 16, 10, 15)."""
        y_e1 = F.relu(self.unet_e12(F.relu(self.unet_e11(frames))))  # (N, 4, 60, 90)
        y_e2 = F.relu(self.unet_e22(F.relu(self.unet_e21(self.unet_pool1(y_e1)))))  # (N, 8, 20, 30)
        y_e3 = F.relu(self.unet_e32(F.relu(self.unet_e31(self.unet_pool2(y_e2)))))  # (N, 16, 10, 15)
        y = torch.cat((self.unet_upconv1(y_e3), y_e2), dim=1)
        y = F.relu(self.unet_d12(F.relu(self.unet_d11(y))))  # (N, 8, 20, 30)
        y = torch.cat((self.unet_upconv2(y), y_e1), dim=1)
        y = F.relu(self.unet_d22(F.relu(self.unet_d21(y))))  # (N, 4, 60, 90)
        return self.unet_out(y), y_e3

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        y_unet, y_e3 = self.unet(frames)
        x = torch.cat((frames, y_unet), dim=1)
        x = min_pool2d(F.relu(self.conv_bn1(self.conv_conv1(x))), 2, 1)  # (N, 4, 18, 28)
        x = self.branch_map(F.avg_pool2d(F.relu(self.conv_conv2(x)), 2, 1))  # (N, 10, 6, 11)
        return torch.cat((x.flatten(1), self.bottleneck_map(y_e3).flatten(1)), dim=1)

    def head(self, features: torch.Tensor, state: torch.Tensor, hidden: Hidden | None = None):
        x, hidden = run_lstm(self.lstm, torch.cat((features, state), dim=-1), hidden)
        x = F.leaky_relu(self.nn_fc1(x))
        x = F.leaky_relu(self.nn_fc2(x))
        return self.nn_fc3(x), hidden

    def initial_hidden(self, batch_size: int, device=None, dtype=None) -> Hidden:
        return zero_hidden(self.lstm, batch_size, device, dtype)


@register_model
def unet_lstm(use_state: bool = True, lstm_dropout: float = 0.15) -> UNetLSTM:
    """The paper's UNet+LSTM (2,955,822 parameters)."""
    return UNetLSTM(use_state=use_state, lstm_dropout=lstm_dropout)
