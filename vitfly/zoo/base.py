"""The call contract every zoo network follows (DESIGN.md "Model zoo").

``net(depth[B, T, 1, 60, 90], desired_speed[B, T, 1], quat[B, T, 4], hidden=None)
-> (velocity[B, T, 3], hidden)``

``depth`` is normalised depth in [0, 1] (metric depth / 10 m); ``desired_speed`` the desired forward
speed in m/s; ``quat`` the body-to-world attitude (w, x, y, z). The output is the world-frame velocity
command divided by the desired speed. Subclasses implement ``encode`` (the image encoder, one frame at a
time) and ``head`` (state concatenation, optional LSTM over T, output layers), timm-style.
"""

from __future__ import annotations

import torch
from torch import nn

from vitfly.errors import VitflyError
from vitfly.zoo.layers import state_vector

IMAGE_HEIGHT = 60
IMAGE_WIDTH = 90

Hidden = tuple[torch.Tensor, torch.Tensor]


def check_inputs(depth: torch.Tensor, desired_speed: torch.Tensor, quat: torch.Tensor) -> tuple[int, int]:
    """Return (B, T) or raise VitflyError naming the input and the expected shape."""
    shape = tuple(depth.shape)
    if len(shape) != 5 or shape[2:] != (1, IMAGE_HEIGHT, IMAGE_WIDTH):
        raise VitflyError(f"depth: expected shape (B, T, 1, {IMAGE_HEIGHT}, {IMAGE_WIDTH}), got {shape}")
    b, t = shape[0], shape[1]
    if tuple(desired_speed.shape) != (b, t, 1):
        raise VitflyError(f"desired_speed: expected shape ({b}, {t}, 1) = (B, T, 1), got {tuple(desired_speed.shape)}")
    if tuple(quat.shape) != (b, t, 4):
        raise VitflyError(f"quat: expected shape ({b}, {t}, 4) = (B, T, 4) (w, x, y, z), got {tuple(quat.shape)}")
    return b, t


class DepthPolicyNet(nn.Module):
    """Base class: input checks, frame flattening and the state vector; subclasses give encode/head."""

    is_recurrent: bool = False
    model_name: str = ""  # the registry name of the architecture
    # dotted names of the modules whose outputs (N, C, h, w) are the encoder's last spatial feature maps:
    # together they carry everything the image passes to the head (Grad-CAM attributes there)
    spatial_layers: tuple[str, ...] = ()

    def __init__(self, use_state: bool = True) -> None:
        super().__init__()
        self.use_state = use_state

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Image features (N, F) of depth frames (N, 1, 60, 90)."""
        raise NotImplementedError

    def head(
        self, features: torch.Tensor, state: torch.Tensor, hidden: Hidden | None
    ) -> tuple[torch.Tensor, Hidden | None]:
        """Velocity / desired speed (B, T, 3) from features (B, T, F) and state (B, T, 5)."""
        raise NotImplementedError

    def initial_hidden(self, batch_size: int, device=None, dtype=None) -> Hidden | None:
        """Zero recurrent state ``(h, c)``, each (layers, B, hidden); None for feed-forward networks."""
        return None

    def forward(
        self,
        depth: torch.Tensor,
        desired_speed: torch.Tensor,
        quat: torch.Tensor,
        hidden: Hidden | None = None,
    ) -> tuple[torch.Tensor, Hidden | None]:
        b, t = check_inputs(depth, desired_speed, quat)
        features = self.encode(depth.reshape(b * t, 1, IMAGE_HEIGHT, IMAGE_WIDTH))
        state = state_vector(desired_speed, quat, self.use_state)
        return self.head(features.reshape(b, t, -1), state, hidden)
