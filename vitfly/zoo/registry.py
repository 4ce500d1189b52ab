"""Name -> network builder registry.

A new architecture registers itself from its own file::

    @register_model
    def my_net(use_state: bool = True, **kwargs) -> nn.Module:
        return MyNet(use_state=use_state, **kwargs)

and is then available as ``create_model("my_net")`` (the file must be imported once, e.g. from
``vitfly/zoo/__init__.py`` or by the user before calling ``create_model``).
"""

from __future__ import annotations

from collections.abc import Callable

from torch import nn

from vitfly.errors import VitflyError

ModelBuilder = Callable[..., nn.Module]

_BUILDERS: dict[str, ModelBuilder] = {}


def register_model(fn: ModelBuilder | None = None, *, name: str | None = None):
    """Decorator: register ``fn`` under ``name`` (default: the function's name)."""

    def add(builder: ModelBuilder) -> ModelBuilder:
        key = name or builder.__name__
        if key in _BUILDERS and _BUILDERS[key] is not builder:
            raise ValueError(f"model name {key!r} is already registered by {_BUILDERS[key].__module__}")
        _BUILDERS[key] = builder
        return builder

    return add(fn) if fn is not None else add


def list_models() -> list[str]:
    """Registered model names, sorted."""
    return sorted(_BUILDERS)


def create_model(name: str, **kwargs) -> nn.Module:
    """Build the bare network registered as ``name`` (kwargs go to its builder, e.g. use_state)."""
    try:
        builder = _BUILDERS[name]
    except KeyError:
        raise VitflyError(f"unknown model {name!r}; known models: {', '.join(list_models())}") from None
    return builder(**kwargs)
