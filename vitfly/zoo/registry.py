"""Name -> network builder registry.

A new architecture registers itself from its own file::

    @register_model
    def my_net(use_state: bool = True, **kwargs) -> nn.Module:
        return MyNet(use_state=use_state, **kwargs)

and is then available as ``create_model("my_net")``. vitfly's own files are imported by
``vitfly/zoo/__init__.py``; another package's are found through its entry points in the group
``vitfly.models`` (docs/models.md, "Your own model as a plug-in"), loaded the first time the registry is
consulted, so every ``vitfly`` command knows them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING

from torch import nn

from vitfly.errors import VitflyError

if TYPE_CHECKING:
    from importlib.metadata import EntryPoint

ModelBuilder = Callable[..., nn.Module]
PLUGIN_GROUP = "vitfly.models"

log = logging.getLogger(__name__)

_BUILDERS: dict[str, ModelBuilder] = {}
_plugins_loaded = False
_loading_plugin: str | None = None  # the entry point being loaded, for the name-clash message
_plugin_clash: VitflyError | None = None  # kept: every later look-up fails the same way until it is fixed


class PluginNameClash(VitflyError):
    """A plug-in registered a model name that another package already uses."""


def register_model(fn: ModelBuilder | None = None, *, name: str | None = None):
    """Decorator: register ``fn`` under ``name`` (default: the function's name)."""

    def add(builder: ModelBuilder) -> ModelBuilder:
        key = name or builder.__name__
        if key in _BUILDERS and _BUILDERS[key] is not builder:
            owner = _BUILDERS[key].__module__
            if _loading_plugin is not None:
                raise PluginNameClash(f"model plug-in {_loading_plugin} registers model {key!r}, which {owner} "
                                      "already registers; rename the plug-in's model")
            raise ValueError(f"model name {key!r} is already registered by {owner}")
        _BUILDERS[key] = builder
        return builder

    return add(fn) if fn is not None else add


def _describe(ep: EntryPoint) -> str:
    dist = ep.dist.name if ep.dist is not None else "(unknown distribution)"
    return f"{dist} (entry point {ep.name} = {ep.value})"


def _load_plugin(ep: EntryPoint) -> None:
    """Import one entry point; a callable that is not itself a builder is a hook that registers when called."""
    global _loading_plugin
    _loading_plugin = _describe(ep)
    try:
        target = ep.load()
        if callable(target) and not isinstance(target, ModuleType) and target not in _BUILDERS.values():
            target()
    except PluginNameClash:
        raise
    except Exception as err:  # a broken plug-in costs its own models only
        why = " ".join(f"{type(err).__name__}: {err}".split())  # one line, whatever the exception prints
        log.warning("vitfly: warning: model plug-in %s skipped: %s", _loading_plugin, why)
    finally:
        _loading_plugin = None


def load_plugins() -> None:
    """Load the ``vitfly.models`` entry points of the installed packages, once."""
    global _plugins_loaded, _plugin_clash
    if not _plugins_loaded:
        from importlib.metadata import entry_points  # here: scanning the installed packages waits for a look-up

        _plugins_loaded = True  # first: a plug-in that consults the registry while loading must not recurse
        for ep in entry_points(group=PLUGIN_GROUP):
            try:
                _load_plugin(ep)
            except PluginNameClash as err:
                _plugin_clash = _plugin_clash or err
    if _plugin_clash is not None:
        raise _plugin_clash


def list_models() -> list[str]:
    """Registered model names (vitfly's and the plug-ins'), sorted."""
    load_plugins()
    return sorted(_BUILDERS)


def create_model(name: str, **kwargs) -> nn.Module:
    """Build the bare network registered as ``name`` (kwargs go to its builder, e.g. use_state)."""
    load_plugins()
    try:
        builder = _BUILDERS[name]
    except KeyError:
        raise VitflyError(f"unknown model {name!r}; known models: {', '.join(list_models())}") from None
    return builder(**kwargs)
