"""Small building blocks shared by the zoo's networks.

- ``min_pool2d``: the paper's "min-pool" (max-pool of the negated map, negated back).
- ``state_vector``: the 5 values appended after every image encoder,
  ``[0.1 * desired_speed (m/s), q_w, q_x, q_y, q_z]``.
- ``SNLinear``: a Linear layer with spectral normalisation, state-dict compatible with the
  original project's ``torch.nn.utils.spectral_norm`` (keys ``weight_orig``/``weight_u``/``weight_v``),
  with the normalised weight cached for inference.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

# the networks scale the desired speed before concatenating it (paper code)
SPEED_SCALE = 0.1
STATE_DIM = 5
INIT_POWER_ITERATIONS = 15


def is_tracing() -> bool:
    """True while torch.jit / torch.export / torch.compile / the ONNX exporter trace the network."""
    return (
        torch.jit.is_tracing()
        or torch.onnx.is_in_onnx_export()
        or torch.compiler.is_compiling()
        or torch.compiler.is_exporting()
    )


def min_pool2d(x: torch.Tensor, kernel_size: int, stride: int = 1) -> torch.Tensor:
    """Min-pool: ``-max_pool2d(-x)``."""
    return -F.max_pool2d(-x, kernel_size, stride)


def state_vector(desired_speed: torch.Tensor, quat: torch.Tensor, use_state: bool) -> torch.Tensor:
    """``[0.1 * speed, w, x, y, z]`` along the last axis; zeros (same shape) when ``use_state`` is False.

    desired_speed: (..., 1) m/s; quat: (..., 4) body-to-world attitude (w, x, y, z).
    """
    if not use_state:
        return quat.new_zeros((*quat.shape[:-1], STATE_DIM))
    return torch.cat((desired_speed * SPEED_SCALE, quat), dim=-1)


class SNLinear(nn.Module):
    """Linear layer with spectral normalisation of its weight (one power iteration per training step).

    Same parameters, buffers and arithmetic as ``torch.nn.utils.spectral_norm(nn.Linear(...))``:
    ``weight = weight_orig / sigma`` with ``sigma = u . (weight_orig v)``. In training mode one
    power-iteration step first updates ``u`` and ``v`` in place; in eval mode the stored ``u``/``v`` are
    used as they are, so outputs are reproducible. Under eval + no-grad (inference) the normalised
    weight is computed once and cached until a parameter or buffer changes (tracked through the
    tensors' version counters), which removes a matrix-vector product and a full weight copy per call.
    """

    def __init__(self, in_features: int, out_features: int, bias: bool = True, eps: float = 1e-12) -> None:
        super().__init__()
        self.in_features = in_features
        self.out_features = out_features
        self.eps = eps
        linear = nn.Linear(in_features, out_features, bias=bias)  # reuse its default initialisation
        self.weight_orig = nn.Parameter(linear.weight.detach().clone())
        self.bias = nn.Parameter(linear.bias.detach().clone()) if bias else None
        self.register_buffer("weight_u", F.normalize(torch.randn(out_features), dim=0, eps=eps))
        self.register_buffer("weight_v", F.normalize(torch.randn(in_features), dim=0, eps=eps))
        # start from a converged estimate (as torch.nn.utils.parametrizations.spectral_norm does) so an
        # untrained network already has sensible output scales; loading a state dict replaces u and v
        with torch.no_grad():
            for _ in range(INIT_POWER_ITERATIONS):
                self.weight_v.copy_(F.normalize(torch.mv(self.weight_orig.t(), self.weight_u), dim=0, eps=eps))
                self.weight_u.copy_(F.normalize(torch.mv(self.weight_orig, self.weight_v), dim=0, eps=eps))
        self._cache_key: tuple | None = None
        self._cached_weight: torch.Tensor | None = None

    def _normalised_weight(self) -> torch.Tensor:
        w = self.weight_orig
        u, v = self.weight_u, self.weight_v
        if self.training:
            with torch.no_grad():
                v.copy_(F.normalize(torch.mv(w.t(), u), dim=0, eps=self.eps))
                u.copy_(F.normalize(torch.mv(w, v), dim=0, eps=self.eps))
            # clones so autograd does not see the in-place update of the next step
            u, v = u.clone(), v.clone()
        sigma = torch.dot(u, torch.mv(w, v))
        return w / sigma

    @property
    def weight(self) -> torch.Tensor:
        """The spectrally normalised weight (out_features, in_features)."""
        if self.training or torch.is_grad_enabled() or is_tracing():
            return self._normalised_weight()
        w, u, v = self.weight_orig, self.weight_u, self.weight_v
        if w.is_inference() or u.is_inference() or v.is_inference():
            return self._normalised_weight()  # inference tensors keep no version counter to key a cache on
        key = (w._version, u._version, v._version, w.data_ptr(), u.data_ptr(), v.data_ptr(), w.dtype, w.device)
        if key != self._cache_key or self._cached_weight is None:
            self._cached_weight = self._normalised_weight()
            self._cache_key = key
        return self._cached_weight

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x, self.weight, self.bias)

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, bias={self.bias is not None}"
