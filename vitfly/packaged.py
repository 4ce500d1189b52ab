"""The configs and pretrained weights that ship with vitfly, found wherever it runs.

In a wheel (``pip install vitfly``, ``pip install .``) they are package data: ``vitfly/configs`` and
``vitfly/weights``, which ``pyproject.toml`` maps from the repository's ``configs/`` and ``weights/``. In a
source tree (a clone, an editable install, ``PYTHONPATH``) they are the repository's own ``configs/`` and
``weights/`` beside the package. Either way ``shipped_dir`` gives the directory.

A config is named by path or by name: ``config_path(spec)`` takes ``spec`` as a path when that file exists
(a clone's ``configs/quickstart.yaml``, a user's own YAML), else as the name of a shipped config: its path
under ``configs/`` without ``.yaml`` (``quickstart``, ``fit/vit_lstm``, ``collect/spheres``); a leading
``configs/`` and a ``.yaml`` suffix are accepted, so paths that configs write to each other
(``collect_config: configs/collect/spheres.yaml``) resolve from any directory.
"""

from __future__ import annotations

import os
import platform
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from vitfly import __version__
from vitfly.errors import VitflyError

PACKAGE_DIR = Path(__file__).resolve().parent
SHIPPED = ("configs", "weights")
CONFIG_SUFFIX = ".yaml"
NAME_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*")


def _installed_dir(kind: str) -> Path | None:
    """``vitfly/<kind>`` inside an installed package (wheel), read through importlib.resources."""
    found = resources.files("vitfly") / kind
    return found if isinstance(found, Path) and found.is_dir() else None


def source_root() -> Path | None:
    """The repository root when vitfly runs from its source tree (clone, editable install, PYTHONPATH), else None."""
    root = PACKAGE_DIR.parent
    if _installed_dir("configs") is None and (root / "pyproject.toml").is_file() and (root / "configs").is_dir():
        return root
    return None


def shipped_dir(kind: str) -> Path | None:
    """The directory of the shipped ``configs`` or ``weights``: the package's own (a wheel), else the source
    tree's; None when neither exists (an install built without them)."""
    if kind not in SHIPPED:
        raise ValueError(f"kind must be one of {SHIPPED}, got {kind!r}")
    installed = _installed_dir(kind)
    if installed is not None:
        return installed
    root = source_root()
    return root / kind if root is not None else None


def config_name(spec: str | os.PathLike) -> str | None:
    """The shipped-config name ``spec`` stands for (``configs/fit/vit.yaml`` -> ``fit/vit``), or None if it
    cannot be one (an absolute path, characters a name never has)."""
    text = os.fspath(spec).replace(os.sep, "/")
    text = text.removeprefix("./").removeprefix("configs/")
    text = text.removesuffix(CONFIG_SUFFIX).removesuffix(".yml")
    return text if NAME_PATTERN.fullmatch(text) and ".." not in text.split("/") else None


def shipped_config(spec: str | os.PathLike) -> Path | None:
    """The shipped config file that ``spec`` names (``fit/vit_lstm``, ``configs/fit/vit_lstm.yaml``), or None."""
    name, root = config_name(spec), shipped_dir("configs")
    path = root / f"{name}{CONFIG_SUFFIX}" if name is not None and root is not None else None
    return path if path is not None and path.is_file() else None


def config_path(spec: str | os.PathLike) -> Path:
    """``spec`` as a path if that file exists, else the shipped config it names; one line if neither."""
    path = Path(spec)
    if path.is_file():
        return path
    found = shipped_config(spec)
    if found is None:
        raise VitflyError(f"{os.fspath(spec)}: config file not found, nor a config shipped with vitfly by that name "
                          "(`vitfly configs` lists them)")
    return found


def find_config(spec: str | os.PathLike) -> Path | None:
    """``config_path`` that answers None instead of raising (for arguments handed on to LightningCLI)."""
    try:
        return config_path(spec)
    except VitflyError:
        return None


@dataclass(frozen=True)
class ShippedConfig:
    name: str  # what --config takes, e.g. fit/vit_lstm
    command: str  # the vitfly subcommand it configures, e.g. "vitfly fit"
    about: str  # one line from its header comment
    path: Path


def _header(path: Path) -> list[str]:
    lines = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        lines.append(line.lstrip("#").strip())
    return lines


def _first_clause(text: str) -> str:
    return text.split(": ", 1)[0].split(". ", 1)[0].rstrip(".")


def describe(path: Path, name: str) -> ShippedConfig:
    """A config's name, command and one-line description, from its header comment: the text after " — " on the
    first line (``vitfly fit --config ...  —  ViT (3,101,199 parameters)``), else the second line's first clause;
    overlays (composed after a model config) say so."""
    header = _header(path) + ["", ""]
    first = header[0]
    match = re.search(r"vitfly [a-z-]+", first)
    about = first.split("—", 1)[1].strip() if "—" in first else _first_clause(header[1])
    if first.startswith("Compose after") or first.count("--config") > 1:
        about = f"overlay: {about}"
    return ShippedConfig(name=name, command=match.group(0) if match else "", about=about, path=path)


def shipped_configs() -> list[ShippedConfig]:
    """Every shipped config, sorted by name."""
    root = shipped_dir("configs")
    if root is None:
        return []
    paths = sorted(root.rglob(f"*{CONFIG_SUFFIX}"))
    return [describe(p, p.relative_to(root).with_suffix("").as_posix()) for p in paths]


def version_line() -> str:
    """What ``vitfly --version`` prints: ``vitfly X.Y.Z from DIR (Python X.Y.Z)``."""
    return f"vitfly {__version__} from {PACKAGE_DIR} (Python {platform.python_version()})"


def read_yaml(path: str | Path) -> dict:
    """A config file's mapping (safe YAML); a missing file or bad YAML is one line naming the file."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise VitflyError(f"{path}: config file not found") from None
    except yaml.YAMLError as err:
        raise VitflyError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from None
    return data or {}
