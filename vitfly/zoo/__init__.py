"""Model zoo: the paper's five networks plus ResNet-18, behind one registry."""

from vitfly.zoo.registry import create_model, list_models, register_model

__all__ = ["create_model", "list_models", "register_model"]
