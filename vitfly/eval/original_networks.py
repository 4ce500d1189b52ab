"""The original project's five networks, imported from a checkout the user points at, for side-by-side timing.

Nothing of the original is part of vitfly: ``load_original_models(repo)`` imports ``REPO/models/model.py``
(which imports its sibling ``ViTsubmodules.py`` by a bare name, so ``REPO/models`` is put on ``sys.path``
for the import) and ``original_step`` calls a network the way the original deployment does
(``envtest/ros/user_code.py``): one frame per call under ``torch.no_grad``, the inputs as a list
``[image (1, 1, 60, 90), desired velocity (1, 1), quaternion (1, 4)]`` plus, for the LSTM classes, the
hidden state ``(h, c)``, each ``(layers, hidden)``, zeros at the start and then whatever the previous call
returned.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from vitfly.errors import VitflyError


@dataclass(frozen=True)
class OriginalNetwork:
    """How the original deployment names and calls one network."""

    class_name: str
    state_shape: tuple[int, int] | None  # (LSTM layers, hidden size) as user_code sets them; None: no state


# vitfly registry name -> the original class and its LSTM state (user_code.compute_command_vision_based)
ORIGINAL_NETWORKS: dict[str, OriginalNetwork] = {
    "convnet": OriginalNetwork("ConvNet", None),
    "lstmnet": OriginalNetwork("LSTMNet", (2, 395)),
    "unet_lstm": OriginalNetwork("UNetConvLSTMNet", (2, 200)),
    "vit": OriginalNetwork("ViT", None),
    "vit_lstm": OriginalNetwork("LSTMNetVIT", (3, 128)),
}


def load_original_models(repo: str | Path) -> types.ModuleType:
    """Import ``repo/models/model.py`` of an original-project checkout as a fresh module.

    Raises VitflyError (one line) when the file is missing, fails to import, or lacks one of the five classes.
    """
    models_dir = Path(repo).expanduser().resolve() / "models"
    path = models_dir / "model.py"
    if not path.is_file():
        raise VitflyError(f"--original-repo {repo}: no models/model.py (expected a checkout of the original project)")
    spec = importlib.util.spec_from_file_location(f"_vitfly_original_model_{abs(hash(str(path)))}", path)
    module = importlib.util.module_from_spec(spec)
    before_modules = set(sys.modules)
    sys.path.insert(0, str(models_dir))  # model.py does `from ViTsubmodules import *`
    try:
        spec.loader.exec_module(module)
    except Exception as err:
        raise VitflyError(f"{path}: import failed: {type(err).__name__}: {str(err).splitlines()[0][:200]}") from None
    finally:
        sys.path.remove(str(models_dir))
        for name in set(sys.modules) - before_modules:  # the bare-named sibling must not shadow anything later
            if getattr(sys.modules[name], "__file__", None) and Path(sys.modules[name].__file__).parent == models_dir:
                del sys.modules[name]
    names = [n.class_name for n in ORIGINAL_NETWORKS.values()]
    missing = [n for n in names if not isinstance(getattr(module, n, None), type)]
    if missing:
        raise VitflyError(f"{path}: no class {', '.join(missing)} (expected the original project's models)")
    return module


def original_network(module: types.ModuleType, name: str, seed: int = 0) -> nn.Module:
    """The original class for vitfly model ``name``, randomly initialised (``seed``), in eval mode."""
    if name not in ORIGINAL_NETWORKS:
        raise VitflyError(f"no original network for model {name!r}; known: {', '.join(ORIGINAL_NETWORKS)}")
    torch.manual_seed(seed)
    return getattr(module, ORIGINAL_NETWORKS[name].class_name)().float().eval()


def original_step(
    net: nn.Module, name: str, depth: torch.Tensor, desired_speed_mps: float, quat: torch.Tensor
) -> Callable[[], torch.Tensor]:
    """A closure running one deployment call of the original ``net`` (see the module docstring).

    depth: (60, 90) in [0, 1]; quat: (4,) (w, x, y, z). The LSTM state starts at zero and is carried.
    """
    image = depth.reshape(1, 1, *depth.shape[-2:]).float()
    speed = torch.tensor(float(desired_speed_mps)).view(1, 1).float()
    q = quat.reshape(1, -1).float()
    shape = ORIGINAL_NETWORKS[name].state_shape
    state = {"hidden": None if shape is None else (torch.zeros(*shape), torch.zeros(*shape))}

    def step():
        with torch.no_grad():
            inputs = [image, speed, q] if state["hidden"] is None else [image, speed, q, state["hidden"]]
            out, hidden = net(inputs)
        if shape is not None:
            state["hidden"] = hidden
        return out

    return step
