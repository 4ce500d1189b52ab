"""Batch norm whose training statistics come from the real frames of a padded batch only.

With ``static_shapes`` the policy module sends every frame of a padded batch through the image encoder, so
that the encoder sees one shape per length bucket (what CUDA graphs need). ``nn.BatchNorm2d`` in training
mode would mix the padding frames into its batch statistics and so change the real frames' outputs.
``MaskedBatchNorm2d`` weighs each frame by a 0/1 weight instead (``FrameWeights``, set by the policy before
each training forward): its statistics, the real frames' outputs, the gradients and the running statistics
are those of ``nn.BatchNorm2d`` over the real frames alone (to float rounding). In eval mode, or when no
weights are set, it is ``nn.BatchNorm2d``. ``mask_batch_norm(net)`` converts a network in place: the same
module objects keep their parameters and buffers, so state dicts and checkpoints do not change.
"""

from __future__ import annotations

import torch
from torch import nn

from vitfly.errors import VitflyError


class FrameWeights:
    """Per-frame weights ``weights`` (N,) float, 1 on real frames and 0 on padding, for the next training
    forward of the network's encoder (None: every frame counts)."""

    def __init__(self) -> None:
        self.weights: torch.Tensor | None = None


class MaskedBatchNorm2d(nn.BatchNorm2d):
    """``nn.BatchNorm2d`` with frame-weighted training statistics (see the module docstring).

    Only made by ``mask_batch_norm``, which sets ``frame_weights``.
    """

    frame_weights: FrameWeights

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weights = self.frame_weights.weights
        batch_stats = self.training or self.running_mean is None
        if weights is None or not batch_stats:
            return super().forward(x)
        self._check_input_dim(x)
        xf = x.float()  # statistics in fp32 whatever the autocast dtype, as cuDNN's batch norm keeps them
        w = weights.to(xf.dtype).view(-1, 1, 1, 1)
        count = (weights.sum() * (x.shape[2] * x.shape[3])).to(xf.dtype).clamp_min(1.0)
        mean = (xf * w).sum(dim=(0, 2, 3)) / count
        centred = xf - mean.view(1, -1, 1, 1)
        var = (centred.square() * w).sum(dim=(0, 2, 3)) / count  # biased, as batch norm normalises
        if self.training and self.track_running_stats and self.num_batches_tracked is not None:
            self._update_running_stats(mean, var, count)
        y = centred * torch.rsqrt(var + self.eps).view(1, -1, 1, 1)
        if self.affine:
            y = y * self.weight.view(1, -1, 1, 1) + self.bias.view(1, -1, 1, 1)
        return y.to(x.dtype)

    @torch.no_grad()
    def _update_running_stats(self, mean: torch.Tensor, var: torch.Tensor, count: torch.Tensor) -> None:
        """nn.BatchNorm's update: momentum (or the cumulative mean when it is None), unbiased variance."""
        self.num_batches_tracked.add_(1)
        factor = self.momentum if self.momentum is not None else 1.0 / self.num_batches_tracked.float()
        unbiased = var * count / (count - 1.0).clamp_min(1.0)
        self.running_mean.lerp_(mean.to(self.running_mean.dtype), factor)
        self.running_var.lerp_(unbiased.to(self.running_var.dtype), factor)


def mask_batch_norm(net: nn.Module) -> FrameWeights | None:
    """Make every ``nn.BatchNorm2d`` of ``net`` a ``MaskedBatchNorm2d`` reading the returned ``FrameWeights``.

    In place, by changing the modules' class: the same objects, so parameters, buffers, state-dict keys,
    hooks and any optimiser holding them stay valid. Returns None when ``net`` has no batch norm. Any other
    batch-norm kind (statistics over the frames it has no masked version of) is one error line.
    """
    holder = FrameWeights()
    found = False
    for name, module in net.named_modules():
        if type(module) is nn.BatchNorm2d or type(module) is MaskedBatchNorm2d:
            module.__class__ = MaskedBatchNorm2d
            module.frame_weights = holder
            found = True
        elif isinstance(module, nn.modules.batchnorm._BatchNorm):
            raise VitflyError(
                f"model.static_shapes: layer {name!r} is a {type(module).__name__}, whose training statistics would "
                "mix padding frames in (only nn.BatchNorm2d has a masked version); set static_shapes: false"
            )
    return holder if found else None
