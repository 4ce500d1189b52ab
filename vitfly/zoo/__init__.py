"""Model zoo: the paper's five networks plus ResNet-18, behind one registry; pretrained weights by name."""

# the architecture modules register their builders on import
from vitfly.zoo import convnet, lstmnet, resnet18, unet_lstm, vit, vit_lstm  # noqa: F401
from vitfly.zoo.checkpoint import load_network, save_checkpoint
from vitfly.zoo.legacy import load_legacy_checkpoint
from vitfly.zoo.pretrained import load_pretrained, save_pretrained
from vitfly.zoo.registry import create_model, list_models, register_model


def __getattr__(name: str):  # loaded on first use: Lightning, and torch's compiler (1.5 s of imports)
    if name in ("PolicyModule", "create_policy"):
        from vitfly.zoo import policy

        return getattr(policy, name)
    if name == "compile_encoder":
        from vitfly.zoo.compiled import compile_encoder

        return compile_encoder
    raise AttributeError(f"module 'vitfly.zoo' has no attribute {name!r}")


__all__ = [
    "PolicyModule",
    "compile_encoder",
    "create_policy",
    "create_model",
    "list_models",
    "load_legacy_checkpoint",
    "load_network",
    "load_pretrained",
    "register_model",
    "save_checkpoint",
    "save_pretrained",
]
