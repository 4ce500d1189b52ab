"""Where vitfly's pretrained weights are, and their manifest (``manifest.json``), read without torch.

``weights_dir`` says which weights directory to read (``directory``, else ``$VITFLY_WEIGHTS_DIR``, else the
shipped weights when they hold a manifest, else ``./weights``) and ``publish_dir`` which to write;
``read_manifest`` and ``manifest_entry`` read and check the manifest. Loading and publishing the weights
themselves is :mod:`vitfly.zoo.pretrained` (which re-exports all of this); listing them (``vitfly weights``)
needs only this module, so it answers without importing torch.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

from vitfly.errors import VitflyError
from vitfly.packaged import shipped_dir, source_root

PRETRAINED_PREFIX = "pretrained:"
WEIGHTS_ENV = "VITFLY_WEIGHTS_DIR"
MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "vitfly.weights"
MANIFEST_VERSION = 1
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


def weights_dir(directory: str | os.PathLike | None = None) -> Path:
    """The weights directory to read: ``directory``, else ``$VITFLY_WEIGHTS_DIR``, else the shipped weights
    (installed package or repository) when they hold a manifest, else ``./weights``."""
    if directory is not None:
        return Path(directory)
    if os.environ.get(WEIGHTS_ENV):
        return Path(os.environ[WEIGHTS_ENV])
    shipped, local = shipped_dir("weights"), Path.cwd() / "weights"
    if shipped is not None and ((shipped / MANIFEST_NAME).is_file() or not (local / MANIFEST_NAME).is_file()):
        return shipped
    return local


def can_publish(directory: str | os.PathLike | None = None) -> bool:
    """Whether ``publish_dir(directory)`` names a directory (false: an installed vitfly, no directory given)."""
    return directory is not None or bool(os.environ.get(WEIGHTS_ENV)) or source_root() is not None


def publish_dir(directory: str | os.PathLike | None = None) -> Path:
    """The weights directory to write: ``directory``, else ``$VITFLY_WEIGHTS_DIR``, else (a clone) the one
    ``weights_dir`` reads; an installed vitfly's own weights are read-only (one line)."""
    if can_publish(directory):
        return weights_dir(directory)
    raise VitflyError(f"vitfly is installed as a package ({shipped_dir('weights') or 'no shipped weights'}), and its "
                      f"shipped weights are not written to: give a weights directory (--weights-dir DIR, "
                      f"train.weights_dir in a reproduce config) or set {WEIGHTS_ENV}")


def is_pretrained_spec(spec: str) -> bool:
    return isinstance(spec, str) and spec.startswith(PRETRAINED_PREFIX)


def pretrained_name(spec: str) -> str:
    """``pretrained:NAME`` -> NAME (checked)."""
    name = spec[len(PRETRAINED_PREFIX):] if is_pretrained_spec(spec) else spec
    check_name(name)
    return name


def check_name(name: str) -> str:
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise VitflyError(f"pretrained name {name!r}: expected letters, digits, '_', '.' or '-' (e.g. vit_lstm)")
    return name


def empty_manifest() -> dict:
    return {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION, "models": {}}


def read_manifest(directory: str | os.PathLike | None = None, missing_ok: bool = False) -> dict:
    """The manifest of the weights directory (an empty one if absent and ``missing_ok``)."""
    path = weights_dir(directory) / MANIFEST_NAME
    if not path.is_file():
        if missing_ok:
            return empty_manifest()
        raise VitflyError(f"{path}: no pretrained weights manifest (publish weights with `vitfly publish-weights` "
                          f"or point {WEIGHTS_ENV} at a weights directory)")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise VitflyError(f"{path}: not a readable JSON manifest ({err})") from None
    if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT:
        raise VitflyError(f"{path}: field 'format' is not {MANIFEST_FORMAT!r}")
    if data.get("version") != MANIFEST_VERSION:
        raise VitflyError(f"{path}: field 'version' is {data.get('version')!r}, expected {MANIFEST_VERSION}")
    if not isinstance(data.get("models"), dict):
        raise VitflyError(f"{path}: field 'models' must be a mapping of names to entries")
    return data


def manifest_entry(name: str, directory: str | os.PathLike | None = None) -> dict:
    """The manifest entry of ``name`` (one line naming the available ones if it has none)."""
    check_name(name)
    manifest = read_manifest(directory)
    entry = manifest["models"].get(name)
    if not isinstance(entry, dict):
        available = ", ".join(sorted(manifest["models"])) or "none yet"
        raise VitflyError(f"pretrained:{name}: not in {weights_dir(directory) / MANIFEST_NAME} "
                          f"(available: {available})")
    return entry
