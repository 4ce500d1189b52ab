"""vitfly checkpoints: save a network so that the rest of vitfly loads it by path alone.

Format (contract 2 in the conventions; the same shape as Lightning checkpoints written by ``vitfly fit``):
a dict saved with ``torch.save`` holding ``state_dict`` (the network's entries prefixed ``net.``),
``hyper_parameters`` = {``model``: registry name, ``use_state``: bool, ``model_kwargs``: dict} and
``pytorch-lightning_version`` (so Lightning's ``load_from_checkpoint`` accepts it). Everything loads
with ``torch.load(..., weights_only=True)``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import torch
from torch import nn

from vitfly.atomic import atomic_path
from vitfly.errors import VitflyError
from vitfly.zoo.legacy import check_state_dict, identify_architecture, read_torch_file
from vitfly.zoo.registry import create_model, list_models

NET_PREFIX = "net."
CHECKPOINT_FORMAT = "vitfly.checkpoint"
CHECKPOINT_VERSION = 1


def _lightning_version() -> str:
    try:
        import lightning

        return lightning.__version__
    except ImportError:  # lightning is a dependency, but the zoo must not need it to save weights
        return "2.0.0"


def save_checkpoint(
    net: nn.Module,
    name: str,
    use_state: bool,
    path: str | os.PathLike,
    model_kwargs: Mapping | None = None,
    metadata: Mapping | None = None,
) -> None:
    """Write ``net`` (registered as ``name``) as a vitfly checkpoint at ``path``, atomically.

    ``model_kwargs`` are the builder's extra keyword arguments (plain values); ``metadata`` (plain values)
    is stored under ``vitfly`` for provenance (e.g. the original file it was converted from).
    """
    if name not in list_models():
        raise VitflyError(f"unknown model {name!r}; known models: {', '.join(list_models())}")
    path = os.fspath(path)
    checkpoint = {
        "state_dict": {NET_PREFIX + k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
        "hyper_parameters": {"model": name, "use_state": bool(use_state), "model_kwargs": dict(model_kwargs or {})},
        "pytorch-lightning_version": _lightning_version(),
        "vitfly": {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **dict(metadata or {})},
    }
    with atomic_path(path) as tmp:
        torch.save(checkpoint, tmp)


def network_from_checkpoint_dict(checkpoint: Mapping, source: str) -> nn.Module:
    """Build and load the network described by a vitfly/Lightning checkpoint dict (eval mode)."""
    hparams = checkpoint.get("hyper_parameters")
    if not isinstance(hparams, Mapping) or "model" not in hparams:
        raise VitflyError(f"{source}: checkpoint has no hyper_parameters.model (the registry name of the network)")
    name = hparams["model"]
    if not isinstance(name, str):
        raise VitflyError(f"{source}: hyper_parameters.model must be a registry name (str), got {type(name).__name__}")
    if name not in list_models():
        known = ", ".join(list_models())
        raise VitflyError(f"{source}: hyper_parameters.model {name!r} is not a known model; known: {known}")
    model_kwargs = hparams.get("model_kwargs") or {}
    if not isinstance(model_kwargs, Mapping):
        raise VitflyError(f"{source}: hyper_parameters.model_kwargs must be a dict, got {type(model_kwargs).__name__}")
    try:
        net = create_model(name, use_state=bool(hparams.get("use_state", True)), **dict(model_kwargs))
    except TypeError as err:
        raise VitflyError(f"{source}: hyper_parameters.model_kwargs do not fit model {name!r}: {err}") from None
    state_dict = checkpoint.get("state_dict")
    if not isinstance(state_dict, Mapping):
        raise VitflyError(f"{source}: checkpoint has no state_dict")
    net_state = {k[len(NET_PREFIX) :]: v for k, v in state_dict.items() if k.startswith(NET_PREFIX)}
    if not net_state:
        raise VitflyError(f"{source}: state_dict has no 'net.' entries (expected the network's parameters as net.*)")
    net.load_state_dict(check_state_dict(net, net_state, name, source))
    return net.eval()


def load_network(path: str | os.PathLike, arch: str | None = None) -> nn.Module:
    """The network stored at ``path``, in eval mode.

    Accepts vitfly checkpoints (``save_checkpoint``, ``vitfly convert-checkpoint``), Lightning
    checkpoints written by ``vitfly fit``, and original-project state dicts: with ``arch`` given, or
    recognised from their keys and shapes when ``arch`` is None.
    """
    source = os.fspath(path)
    obj = read_torch_file(path)
    if isinstance(obj, Mapping) and "state_dict" in obj:
        net = network_from_checkpoint_dict(obj, source)
        stored = obj["hyper_parameters"]["model"]
        if arch is not None and stored != arch:
            raise VitflyError(f"{source}: holds a {stored!r} network, but architecture {arch!r} was asked for")
        return net
    if arch is None:
        if isinstance(obj, Mapping) and obj and all(isinstance(v, torch.Tensor) for v in obj.values()):
            arch = identify_architecture(obj)
            if arch is None:
                raise VitflyError(
                    f"{source}: a state dict that matches no registered architecture; pass the architecture "
                    f"name ({', '.join(list_models())}) to see which keys do not fit"
                )
        else:
            raise VitflyError(
                f"{source}: neither a vitfly checkpoint (a dict with state_dict and hyper_parameters) "
                f"nor a state dict (got {type(obj).__name__})"
            )
    net = create_model(arch)
    net.load_state_dict(check_state_dict(net, obj, arch, source))
    return net.eval()
