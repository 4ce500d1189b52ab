"""Load the original ViTfly project's checkpoints (plain ``torch.save(model.state_dict())`` files).

Original files use the old ``torch.nn.utils.spectral_norm`` keys (``weight_orig``/``weight_u``/``weight_v``),
which the zoo's layers keep, so a legacy state dict loads into ``create_model(name)`` unchanged.
Files are read with ``torch.load(..., weights_only=True)``: nothing is unpickled beyond tensors and
plain containers. Every failure is one ``VitflyError`` line naming the file and what is wrong.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import torch
from torch import nn

from vitfly.errors import VitflyError
from vitfly.zoo.registry import create_model, list_models

# architectures the original project trained (resnet18 had no released checkpoint format)
LEGACY_ARCHITECTURES = ("convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm")


def read_torch_file(path: str | os.PathLike) -> object:
    """``torch.load(path, weights_only=True)`` on CPU, with one-line errors for missing or unreadable files."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise VitflyError(f"{path}: no such file")
    if os.path.isdir(path):
        raise VitflyError(f"{path}: is a directory, expected a checkpoint file (.pth/.ckpt)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for truncated / foreign files
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        if len(reason) > 160:
            reason = reason[:160] + "..."
        raise VitflyError(
            f"{path}: not a readable PyTorch checkpoint (truncated, corrupt or not saved with torch.save "
            f"of tensors): {reason}"
        ) from None


def _signature(state_dict: Mapping[str, torch.Tensor]) -> dict[str, tuple[int, ...]]:
    return {k: tuple(v.shape) for k, v in state_dict.items()}


def _model_signature(name: str) -> dict[str, tuple[int, ...]]:
    return _signature(create_model(name).state_dict())


def identify_architecture(state_dict: Mapping[str, torch.Tensor]) -> str | None:
    """Name of the registered model whose keys and shapes equal the state dict's, or None."""
    sig = _signature(state_dict)
    for name in list_models():
        if _model_signature(name) == sig:
            return name
    return None


def _closest_architecture(state_dict: Mapping[str, torch.Tensor]) -> str | None:
    keys = set(state_dict)
    best, best_score = None, 0.0
    for name in list_models():
        model_keys = set(_model_signature(name))
        score = len(keys & model_keys) / max(len(keys | model_keys), 1)
        if score > best_score:
            best, best_score = name, score
    return best if best_score >= 0.5 else None


def _short_list(items: list[str], limit: int = 4) -> str:
    shown = ", ".join(items[:limit])
    return shown + (f", ... ({len(items)} in all)" if len(items) > limit else "")


def check_state_dict(net: nn.Module, state_dict: object, arch: str, source: str) -> dict[str, torch.Tensor]:
    """Validate ``state_dict`` against ``net`` (keys and shapes); return it as a plain dict or raise one line."""
    if not isinstance(state_dict, Mapping) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state_dict.items()
    ):
        raise VitflyError(
            f"{source}: not a state dict (expected a mapping of parameter names to tensors, "
            f"got {type(state_dict).__name__})"
        )
    if not state_dict:
        raise VitflyError(f"{source}: empty state dict, expected the parameters of {arch!r}")
    expected = _signature(net.state_dict())
    given = _signature(state_dict)
    missing = [k for k in expected if k not in given]
    extra = [k for k in given if k not in expected]
    wrong_shape = [
        f"{k} {given[k]} (expected {expected[k]})" for k in expected if k in given and given[k] != expected[k]
    ]
    if missing or extra or wrong_shape:
        guess = identify_architecture(state_dict) or _closest_architecture(state_dict)
        hint = ""
        if guess is not None and guess != arch:
            hint = f"; it looks like a {guess!r} checkpoint (try --arch {guess})"
        problems = []
        if missing:
            problems.append(f"missing keys {_short_list(missing)}")
        if extra:
            problems.append(f"unexpected keys {_short_list(extra)}")
        if wrong_shape:
            problems.append(f"wrong shapes {_short_list(wrong_shape, 2)}")
        raise VitflyError(f"{source}: does not fit architecture {arch!r}: {'; '.join(problems)}{hint}")
    return dict(state_dict)


def load_legacy_checkpoint(name: str, path: str | os.PathLike, **model_kwargs) -> nn.Module:
    """The network ``name`` (e.g. "vit_lstm") carrying the original-format state dict at ``path``, in eval mode.

    Raises VitflyError for an unknown name, an unreadable or truncated file, something that is not a
    state dict, or a state dict of another architecture (naming the keys that do not fit).
    """
    net = create_model(name, **model_kwargs)
    obj = read_torch_file(path)
    if isinstance(obj, Mapping) and "state_dict" in obj and "hyper_parameters" in obj:
        raise VitflyError(
            f"{os.fspath(path)}: is a vitfly/Lightning checkpoint, not an original state dict; "
            "load it with vitfly.zoo.load_network(path)"
        )
    state_dict = check_state_dict(net, obj, name, os.fspath(path))
    net.load_state_dict(state_dict)
    return net.eval()
