"""SegFormer-style mix-transformer stage used by the ViT models (MODELS.md "ViT").

A stage is an overlapping patch embedding followed by ``n_layers`` post-norm transformer layers
``x = x + attention(x); x = x + mix_ffn(x); x = layer_norm(x)`` and returns the token grid as
(N, C, H, W). Attribute names (``patchMerge``, ``_attn``, ``_ffn``, ``_lNorm``, ...) follow the original
checkpoints so their state dicts load unchanged.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def tokens_to_grid(x: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(N, H*W, C) tokens -> (N, C, H, W)."""
    return x.transpose(1, 2).reshape(x.shape[0], x.shape[2], h, w)


def grid_to_tokens(x: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) -> (N, H*W, C) tokens."""
    return x.flatten(2).transpose(1, 2)


class OverlapPatchEmbed(nn.Module):
    """Conv2d patch embedding (overlapping patches), then LayerNorm over channels."""

    def __init__(self, in_channels: int, channels: int, patch_size: int, stride: int, padding: int) -> None:
        super().__init__()
        self.cn1 = nn.Conv2d(in_channels, channels, kernel_size=patch_size, stride=stride, padding=padding)
        self.layerNorm = nn.LayerNorm(channels)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, int, int]:
        x = self.cn1(x)
        h, w = x.shape[2], x.shape[3]
        return self.layerNorm(grid_to_tokens(x)), h, w


class EfficientSelfAttention(nn.Module):
    """Multi-head attention whose keys/values come from a strided-conv reduction of the token grid.

    Key/value features split as [kv (2)][head][head_dim]; queries as [head][head_dim].
    """

    def __init__(self, channels: int, reduction_ratio: int, num_heads: int) -> None:
        super().__init__()
        if channels % num_heads:
            raise ValueError(f"channels ({channels}) must be divisible by num_heads ({num_heads})")
        self.num_heads = num_heads
        self.cn1 = nn.Conv2d(channels, channels, kernel_size=reduction_ratio, stride=reduction_ratio)
        self.ln1 = nn.LayerNorm(channels)
        self.keyValueExtractor = nn.Linear(channels, 2 * channels)
        self.query = nn.Linear(channels, channels)
        self.finalLayer = nn.Linear(channels, channels)

    def reduce(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """``cn1`` (kernel = stride = R, no padding) on the token grid, as one product over R x R patches.

        Same arithmetic as the convolution, without its per-call set-up cost on tiny outputs (2 or 6
        tokens here); returns tokens (N, L', C).
        """
        r = self.cn1.kernel_size[0]
        c = x.shape[-1]
        hr, wr = h // r, w // r
        grid = x.reshape(-1, h, w, c)[:, : hr * r, : wr * r]  # the rows/columns the convolution covers
        patches = grid.reshape(-1, hr, r, wr, r, c).permute(0, 1, 3, 5, 2, 4).reshape(-1, hr * wr, c * r * r)
        return torch.nn.functional.linear(patches, self.cn1.weight.reshape(self.cn1.out_channels, -1), self.cn1.bias)

    def key_grid(self, h: int, w: int) -> tuple[int, int]:
        """(rows, columns) of the reduced key/value grid for an (h, w) token grid: (h // R, w // R).

        Key (i, j) summarises tokens [i R, (i + 1) R) x [j R, (j + 1) R); the last h % R rows and
        w % R columns of tokens are never keys (the reduction convolution has no padding).
        """
        r = self.cn1.kernel_size[0]
        return h // r, w // r

    def project(self, x: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Queries (N, heads, L, d) from the tokens; keys and values (N, heads, L', d) from the reduced grid."""
        n, length, c = x.shape
        d = c // self.num_heads
        reduced = self.ln1(self.reduce(x, h, w))  # (N, L', C)
        kv = self.keyValueExtractor(reduced).reshape(n, -1, 2, self.num_heads, d).permute(2, 0, 3, 1, 4)
        q = self.query(x).reshape(n, length, self.num_heads, d).transpose(1, 2)  # (N, heads, L, d)
        return q, kv[0], kv[1]

    def attention_weights(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """softmax(q k^T / sqrt(d)): (N, heads, L, L'), each query's weights over the keys (rows sum to 1).

        The forward pass gets the same weights inside a fused kernel that does not return them; call
        this (e.g. from a forward hook on this module, with its inputs) to see them. Keys are in
        row-major order of ``key_grid(h, w)``.
        """
        q, k, _ = self.project(x, h, w)
        return torch.softmax((q @ k.transpose(-2, -1)) * q.shape[-1] ** -0.5, dim=-1)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        n, length, c = x.shape
        q, k, v = self.project(x, h, w)
        if torch.is_autocast_enabled(q.device.type):
            # in fp32 even under bf16 autocast: 2 or 6 keys make it cheap, and the CPU's bf16 attention
            # backward was 4-6x slower than the fp32 one (profiled, benchmarks/profile_train_step.py)
            with torch.autocast(q.device.type, enabled=False):
                out = F.scaled_dot_product_attention(q.float(), k.float(), v.float())
        else:
            out = F.scaled_dot_product_attention(q, k, v)  # softmax(q k^T / sqrt(d)) v
        return self.finalLayer(out.transpose(1, 2).reshape(n, length, c))


class MixFFN(nn.Module):
    """Linear C -> C*E, 3x3 grouped conv (groups = C) on the token grid, GELU, Linear C*E -> C."""

    def __init__(self, channels: int, expansion: int) -> None:
        super().__init__()
        hidden = channels * expansion
        self.mlp1 = nn.Linear(channels, hidden)
        self.depthwise = nn.Conv2d(hidden, hidden, kernel_size=3, padding="same", groups=channels)
        self.mlp2 = nn.Linear(hidden, channels)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        n, length, _ = x.shape
        # a channels-last view of the token grid: the convolution reads it in place and writes channels-last,
        # so neither direction needs a transposed copy of the widest tensor
        y = self.mlp1(x).reshape(n, h, w, -1).permute(0, 3, 1, 2)
        y = F.gelu(self.depthwise(y))
        return self.mlp2(y.permute(0, 2, 3, 1).reshape(n, length, -1))


class MixTransformerStage(nn.Module):
    """Patch embedding + ``n_layers`` post-norm (attention, mix-FFN) layers; returns (N, C, H, W)."""

    def __init__(
        self,
        in_channels: int,
        channels: int,
        patch_size: int,
        stride: int,
        padding: int,
        n_layers: int,
        reduction_ratio: int,
        num_heads: int,
        expansion: int,
    ) -> None:
        super().__init__()
        self.patchMerge = OverlapPatchEmbed(in_channels, channels, patch_size, stride, padding)
        self._attn = nn.ModuleList(
            [EfficientSelfAttention(channels, reduction_ratio, num_heads) for _ in range(n_layers)]
        )
        self._ffn = nn.ModuleList([MixFFN(channels, expansion) for _ in range(n_layers)])
        self._lNorm = nn.ModuleList([nn.LayerNorm(channels) for _ in range(n_layers)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x, h, w = self.patchMerge(x)
        for attn, ffn, norm in zip(self._attn, self._ffn, self._lNorm, strict=True):
            x = x + attn(x, h, w)
            x = x + ffn(x, h, w)
            x = norm(x)
        return tokens_to_grid(x, h, w)
