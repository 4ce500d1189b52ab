"""LSTM plumbing shared by the recurrent networks.

``run_lstm`` is ``nn.LSTM`` for training and export; at inference (eval mode, no autograd) it runs
the same cell equations as plain matrix products, which avoids the per-call setup cost of the fused
LSTM kernel at batch 1 (milliseconds on CPU) and matches it to float rounding. On a GPU that holds only for
a control tick's single step: the plain ops launch about seven kernels per layer and step, so a whole
trajectory (validation: ViT+LSTM's 3 layers over ~420 steps) is ~9,000 launches, by count the bulk of the
170 ms a validation trajectory took on an H200; there, sequences of more than one step go to ``nn.LSTM``
(``fused_at_inference``).

On the CPU the training recurrence (forward and backward) runs on one thread: each of its T steps is a
product of a few thousand numbers, far too small to split, and with two threads every step waits at an
OpenMP barrier (profiled: 1 thread 25-50 ms, 2 threads 40 ms to 4 s for ViT+LSTM's LSTM on a
(4, 64) batch, the slow end whenever another process holds a core).
"""

from __future__ import annotations

import torch
from torch import nn

from vitfly.errors import VitflyError
from vitfly.zoo.layers import is_tracing

Hidden = tuple[torch.Tensor, torch.Tensor]


def zero_hidden(lstm: nn.LSTM, batch_size: int, device=None, dtype=None) -> Hidden:
    """Zero ``(h, c)``, each (num_layers, B, hidden_size)."""
    shape = (lstm.num_layers, batch_size, lstm.hidden_size)
    return torch.zeros(shape, device=device, dtype=dtype), torch.zeros(shape, device=device, dtype=dtype)


def check_hidden(lstm: nn.LSTM, hidden: Hidden, batch_size: int) -> None:
    expected = (lstm.num_layers, batch_size, lstm.hidden_size)
    if not isinstance(hidden, (tuple, list)) or len(hidden) != 2:
        raise VitflyError(f"hidden: expected a tuple (h, c), each of shape {expected}, got {type(hidden).__name__}")
    for name, tensor in zip(("h", "c"), hidden, strict=True):
        if tuple(tensor.shape) != expected:
            got = tuple(tensor.shape)
            raise VitflyError(f"hidden {name}: expected shape {expected} = (layers, B, hidden), got {got}")


def run_lstm(lstm: nn.LSTM, x: torch.Tensor, hidden: Hidden | None) -> tuple[torch.Tensor, Hidden]:
    """Run a batch-first ``lstm`` over x (B, T, F) from ``hidden`` (zeros if None)."""
    b = x.shape[0]
    if hidden is None:
        hidden = zero_hidden(lstm, b, x.device, x.dtype)
    elif not is_tracing():
        check_hidden(lstm, hidden, b)
    if lstm.training or torch.is_grad_enabled() or is_tracing() or fused_at_inference(x.device.type, x.shape[1]):
        if x.device.type == "cpu" and torch.is_autocast_enabled("cpu") and not is_tracing():
            # torch 2.15's oneDNN LSTM refuses bf16 on CPUs without AVX512-BF16 ("could not create a primitive
            # descriptor"; seen on an AVX2-only AMD EPYC): the recurrence runs in fp32, the rest stays under autocast
            with torch.autocast("cpu", enabled=False):
                return run_lstm(lstm, x.float(), (hidden[0].float(), hidden[1].float()))
        if x.device.type == "cpu" and torch.get_num_threads() > 1 and not is_tracing():
            return _lstm_one_thread(lstm, x, hidden)
        out, (h, c) = lstm(x, tuple(hidden))
        return out, (h, c)
    return lstm_inference(lstm, x, hidden)


def fused_at_inference(device_type: str, steps: int) -> bool:
    """Whether an eval-mode, no-autograd call over ``steps`` time steps runs the fused ``nn.LSTM`` rather than
    ``lstm_inference``'s step-by-step ops: on CUDA, for more than one step (a kernel launch per op and step
    costs more there than the fused kernel's setup)."""
    return device_type == "cuda" and steps > 1


def _set_threads(threads: int) -> None:
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)


def _lstm_one_thread(lstm: nn.LSTM, x: torch.Tensor, hidden: Hidden) -> tuple[torch.Tensor, Hidden]:
    """``lstm(x, hidden)`` with one intra-op thread, its backward too (the CPU backward runs on this thread)."""
    threads = torch.get_num_threads()
    _set_threads(1)
    try:
        out, (h, c) = lstm(x, tuple(hidden))
    finally:
        _set_threads(threads)
    if out.requires_grad and x.requires_grad:
        # the gradient reaching the LSTM's output starts its backward; the one reaching its input ends it
        out.register_hook(lambda grad: _set_threads(1))
        x.register_hook(lambda grad: _set_threads(threads))
    return out, (h, c)


def lstm_inference(
    lstm: nn.LSTM, x: torch.Tensor | None, hidden: Hidden, first_input_gates: torch.Tensor | None = None
) -> tuple[torch.Tensor, Hidden]:
    """``nn.LSTM`` eval-mode arithmetic as plain tensor ops (no dropout; gate order i, f, g, o).

    ``first_input_gates`` (B, T, 4H), if given, replaces layer 0's ``x W_ih^T + b_ih + b_hh`` (x is
    then unused): lets an inference rewrite fold a preceding linear layer into it.
    """
    h0, c0 = hidden
    size = lstm.hidden_size
    t_steps = (x if first_input_gates is None else first_input_gates).shape[1]
    layer_input = x
    h_last, c_last = [], []
    for layer in range(lstm.num_layers):
        w_hh_t = getattr(lstm, f"weight_hh_l{layer}").t()
        if layer == 0 and first_input_gates is not None:
            input_gates = first_input_gates
        else:
            bias = None
            if lstm.bias:
                bias = getattr(lstm, f"bias_ih_l{layer}") + getattr(lstm, f"bias_hh_l{layer}")
            w_ih = getattr(lstm, f"weight_ih_l{layer}")
            input_gates = torch.nn.functional.linear(layer_input, w_ih, bias)  # (B, T, 4H), all steps at once
        h, c = h0[layer], c0[layer]
        outputs = []
        for t in range(t_steps):
            gates = torch.addmm(input_gates[:, t], h, w_hh_t)
            act = torch.sigmoid(gates)
            g = torch.tanh(gates[:, 2 * size : 3 * size])
            c = torch.addcmul(act[:, size : 2 * size] * c, act[:, :size], g)
            h = act[:, 3 * size :] * torch.tanh(c)
            outputs.append(h)
        layer_input = outputs[0].unsqueeze(1) if t_steps == 1 else torch.stack(outputs, dim=1)
        h_last.append(h)
        c_last.append(c)
    return layer_input, (torch.stack(h_last), torch.stack(c_last))
