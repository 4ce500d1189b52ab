"""ViT+LSTM: the ViT encoder feeding a 3-layer LSTM (3,563,663 parameters; the paper's best model).

Same encoder and fusion as ViT; SN decoder Linear 4608 -> 512; + state (5) ->
LSTM(517 -> 128, 3 layers, dropout 0.1, with biases) -> SN nn_fc2 3.
"""

from __future__ import annotations

import torch
from torch import nn

from vitfly.zoo.base import Hidden
from vitfly.zoo.layers import STATE_DIM, SNLinear
from vitfly.zoo.recurrent import run_lstm, zero_hidden
from vitfly.zoo.registry import register_model
from vitfly.zoo.vit import FUSED_DIM, ViTBackbone


class ViTLSTM(ViTBackbone):
    """Mix-transformer encoder + LSTM over the frames of each sequence."""

    model_name = "vit_lstm"
    is_recurrent = True

    def __init__(self, use_state: bool = True, lstm_dropout: float = 0.1) -> None:
        super().__init__(use_state)
        self.decoder = SNLinear(FUSED_DIM, 512)
        self.lstm = nn.LSTM(512 + STATE_DIM, 128, num_layers=3, dropout=lstm_dropout, batch_first=True)
        self.nn_fc2 = SNLinear(128, 3)

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.fused_features(frames))

    def head(self, features: torch.Tensor, state: torch.Tensor, hidden: Hidden | None = None):
        x, hidden = run_lstm(self.lstm, torch.cat((features, state), dim=-1), hidden)
        return self.nn_fc2(x), hidden

    def initial_hidden(self, batch_size: int, device=None, dtype=None) -> Hidden:
        return zero_hidden(self.lstm, batch_size, device, dtype)


@register_model
def vit_lstm(use_state: bool = True, lstm_dropout: float = 0.1) -> ViTLSTM:
    """The paper's ViT+LSTM (3,563,663 parameters)."""
    return ViTLSTM(use_state=use_state, lstm_dropout=lstm_dropout)
