"""Pretrained weights trained in vitfly: ``weights/<name>.safetensors`` (fp16) + ``weights/manifest.json``.

``load_pretrained(name)`` gives the network (fp32, eval mode) that ``pretrained:NAME`` names on the
command line; ``save_pretrained(ckpt, name, fields)`` publishes a trained checkpoint there.

Manifest (JSON)::

    {"format": "vitfly.weights", "version": 1,
     "models": {"vit_lstm": {"file": "vit_lstm.safetensors", "sha256": "...", "dtype": "float16",
                             "model": "vit_lstm", "use_state": true, "model_kwargs": {},
                             "vitfly_version": "0.1.0",
                             "epochs": 4, "steps": 480, "source_checkpoint": "...",
                             "preset": "laptop", "dataset_hash": "...", "train_frames": 63124,
                             "closed_loop": {...}, ...}}}

``model``/``use_state``/``model_kwargs`` say which registry network to build; ``vitfly_version`` which vitfly
published it (entries published before it was recorded have none); the rest is provenance (free-form plain
values given by the publisher). Loading is safe: safetensors holds raw tensors only
(no pickle); the file's SHA-256 must equal the manifest's, and its keys and shapes the network's.
Every failure is one line. Floating-point tensors are stored as fp16 (half the size; the networks'
outputs move by about 1e-3) and loaded into the network's own dtype; integer buffers keep theirs.

Where (reading): ``directory`` if given, else ``$VITFLY_WEIGHTS_DIR``, else the shipped weights
(``vitfly.packaged``: the installed package's ``vitfly/weights``, or ``weights/`` at the repository root in a
clone or an editable install) when they hold a manifest, else ``./weights``.

Where (publishing, ``publish_dir``): ``directory``, else ``$VITFLY_WEIGHTS_DIR``, else, in a clone, the
repository's ``weights/`` as for reading. An installed vitfly never writes into its own package: without a
directory, publishing is refused with one line before anything is written.

Publishing writes the weights file and then the manifest, each atomically (temporary file + rename); the same
checkpoint published twice gives the same bytes.
A kill between the two leaves a manifest whose hash does not match the file: loading refuses it with
one line and publishing again repairs it; a half-written file is never visible.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from vitfly import __version__
from vitfly.atomic import atomic_path, write_text
from vitfly.errors import VitflyError
from vitfly.weights_manifest import (  # noqa: F401  (re-exported: the manifest is part of this module's API)
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    MANIFEST_VERSION,
    NAME_PATTERN,
    PRETRAINED_PREFIX,
    WEIGHTS_ENV,
    can_publish,
    check_name,
    empty_manifest,
    is_pretrained_spec,
    manifest_entry,
    pretrained_name,
    publish_dir,
    read_manifest,
    weights_dir,
)
from vitfly.zoo.legacy import check_state_dict, read_torch_file
from vitfly.zoo.registry import create_model, list_models

STORED_DTYPE = torch.float16
RESERVED_FIELDS = ("file", "sha256", "dtype", "model", "use_state", "model_kwargs", "sensor", "vitfly_version")


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _entry_field(entry: Mapping, key: str, kind: type, source: str):
    value = entry.get(key)
    if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
        raise VitflyError(f"{source}: field {key!r} must be a {kind.__name__}, got {value!r}")
    return value


def load_pretrained(name: str, directory: str | os.PathLike | None = None) -> nn.Module:
    """The published network ``name`` (``pretrained:NAME`` also accepted), fp32, in eval mode."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    name = pretrained_name(name)
    root = weights_dir(directory)
    entry = manifest_entry(name, root)
    source = f"{root / MANIFEST_NAME} models.{name}"
    file_name = _entry_field(entry, "file", str, source)
    expected_sha = _entry_field(entry, "sha256", str, source)
    arch = _entry_field(entry, "model", str, source)
    use_state = _entry_field(entry, "use_state", bool, source)
    model_kwargs = entry.get("model_kwargs") or {}
    if not isinstance(model_kwargs, dict):
        raise VitflyError(f"{source}: field 'model_kwargs' must be a mapping, got {model_kwargs!r}")
    if Path(file_name).name != file_name:
        raise VitflyError(f"{source}: field 'file' must be a file name inside {root}, got {file_name!r}")
    path = root / file_name
    if not path.is_file():
        raise VitflyError(f"{path}: missing (the manifest lists it for pretrained:{name}); "
                          "restore it (git checkout weights/) or publish it again")
    actual_sha = file_sha256(path)
    if actual_sha != expected_sha:
        raise VitflyError(f"{path}: sha256 {actual_sha[:12]}... differs from the manifest's {expected_sha[:12]}... "
                          "(changed, truncated or from another publish); refusing to load it")
    if arch not in list_models():
        raise VitflyError(f"{source}: field 'model' is {arch!r}; known models: {', '.join(list_models())}")
    try:
        net = create_model(arch, use_state=use_state, **model_kwargs)
    except TypeError as err:
        raise VitflyError(f"{source}: model_kwargs do not fit model {arch!r}: {err}") from None
    try:
        stored = load_file(str(path), device="cpu")
    except (SafetensorError, OSError, ValueError) as err:
        raise VitflyError(f"{path}: not a readable safetensors file ({str(err).splitlines()[0]})") from None
    stored = check_state_dict(net, stored, arch, str(path))
    own = net.state_dict()
    net.load_state_dict({k: v.to(own[k].dtype) for k, v in stored.items()})
    return net.eval()


def load_weights(spec: str | os.PathLike, arch: str | None = None) -> nn.Module:
    """The network ``spec`` names: ``pretrained:NAME`` (the weights directory) or a checkpoint path
    (``vitfly.zoo.load_network``, ``arch`` for original-project state dicts)."""
    from vitfly.zoo.checkpoint import load_network

    return load_pretrained(str(spec)) if is_pretrained_spec(str(spec)) else load_network(spec, arch=arch)


def weights_identity(spec: str | os.PathLike) -> dict:
    """``{"model", "use_state"}`` of the network ``spec`` names, read without building it (manifest entry or
    checkpoint hyper-parameters)."""
    from vitfly.zoo.checkpoint import network_hparams

    if is_pretrained_spec(str(spec)):
        entry = manifest_entry(pretrained_name(str(spec)))
        return {"model": entry.get("model"), "use_state": entry.get("use_state")}
    hparams = network_hparams(read_torch_file(spec), str(spec))
    return {"model": hparams["model"], "use_state": hparams["use_state"]}


def _checkpoint_parts(ckpt_path: str | os.PathLike) -> tuple[nn.Module, dict, dict]:
    """(network, hyper_parameters, the checkpoint's own provenance: epochs, steps) of a vitfly checkpoint."""
    from vitfly.zoo.checkpoint import network_from_checkpoint_dict, read_sensor

    source = os.fspath(ckpt_path)
    obj = read_torch_file(ckpt_path)
    if not isinstance(obj, Mapping) or "state_dict" not in obj:
        raise VitflyError(f"{source}: not a vitfly/Lightning checkpoint (a dict with state_dict and "
                          "hyper_parameters); convert original state dicts with `vitfly convert-checkpoint` first")
    net = network_from_checkpoint_dict(obj, source)
    hparams = dict(obj["hyper_parameters"])
    provenance = {"source_checkpoint": os.path.abspath(source)}
    sensor = read_sensor(obj, source)
    if sensor is not None:  # the depth range, camera and control rate the network was trained with
        provenance["sensor"] = sensor
    if "epoch" in obj:
        provenance["epochs"] = int(obj["epoch"]) + 1  # Lightning stores the index of the last finished epoch
    if "global_step" in obj:
        provenance["steps"] = int(obj["global_step"])  # optimiser steps (one per TBPTT chunk)
    return net, hparams, provenance


def fp16_state_dict(net: nn.Module, source: str) -> dict[str, torch.Tensor]:
    """The network's state dict with floating tensors as fp16 (refused if a value does not fit fp16)."""
    out = {}
    for key, value in net.state_dict().items():
        value = value.detach().cpu().contiguous()
        if value.is_floating_point():
            half = value.to(STORED_DTYPE)
            if not torch.isfinite(half).all() and torch.isfinite(value).all():
                raise VitflyError(f"{source}: tensor {key} has values beyond fp16's range (|x| > 65504)")
            value = half
        out[key] = value.clone()
    return out


def _plain(value: Any, source: str, key: str) -> Any:
    try:
        return json.loads(json.dumps(value, allow_nan=False))
    except (TypeError, ValueError):
        raise VitflyError(f"{source}: manifest field {key!r} must be plain JSON (numbers, text, lists, maps), "
                          f"got {value!r}") from None


def save_pretrained(ckpt_path: str | os.PathLike, name: str, manifest_fields: Mapping | None = None,
                    directory: str | os.PathLike | None = None) -> Path:
    """Publish a trained vitfly checkpoint as ``<dir>/<name>.safetensors`` (fp16) + its manifest entry.

    ``manifest_fields`` (plain values: preset, dataset_hash, train_frames, closed_loop, ...) join the
    entry beside what the checkpoint itself says (registry model, use_state, model_kwargs, epochs,
    steps). Returns the weights file's path.
    """
    from safetensors.torch import save_file

    check_name(name)
    source = os.fspath(ckpt_path)
    fields = dict(manifest_fields or {})
    clash = sorted(set(fields) & set(RESERVED_FIELDS))
    if clash:
        raise VitflyError(f"{source}: manifest field {clash[0]!r} is written by the publisher itself")
    fields = {k: _plain(v, source, k) for k, v in fields.items()}
    root = publish_dir(directory)
    manifest = read_manifest(root, missing_ok=True)  # a broken manifest is refused before anything is written
    net, hparams, provenance = _checkpoint_parts(ckpt_path)
    tensors = fp16_state_dict(net, source)
    model_kwargs = dict(hparams.get("model_kwargs") or {})
    header = {"format": MANIFEST_FORMAT, "model": str(hparams["model"]),
              "use_state": json.dumps(bool(hparams.get("use_state", True))), "model_kwargs": json.dumps(model_kwargs)}
    path = root / f"{name}.safetensors"
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=header)
        _sort_metadata(tmp)
    entry = {"file": path.name, "sha256": file_sha256(path), "dtype": "float16", "model": str(hparams["model"]),
             "use_state": bool(hparams.get("use_state", True)),
             "model_kwargs": _plain(model_kwargs, source, "model_kwargs"), "vitfly_version": __version__,
             **provenance, **fields}
    manifest["models"][name] = entry
    manifest["models"] = dict(sorted(manifest["models"].items()))
    write_text(root / MANIFEST_NAME, json.dumps(manifest, indent=2) + "\n")
    return path


def _sort_metadata(path: Path) -> None:
    """Rewrite a safetensors file's header with its metadata in key order, in place.

    safetensors writes the metadata map in a random order (a Rust HashMap), so the same weights published twice
    gave two files and two sha256s (and a binary diff in git). The header is JSON of a fixed length: sorted, the
    same text has the same length, and the tensors' bytes after it do not move.
    """
    with open(path, "r+b") as f:
        size = int.from_bytes(f.read(8), "little")
        raw = f.read(size)
        header = json.loads(raw)
        header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
        text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
        if len(text) != len(raw.rstrip(b" ")):
            return  # a header safetensors spelt otherwise: leave it as written (still valid, only unsorted)
        f.seek(8)
        f.write(text.ljust(size))


def update_manifest(name: str, fields: Mapping, directory: str | os.PathLike | None = None) -> dict:
    """Add or replace provenance ``fields`` of a published entry (e.g. its closed-loop numbers)."""
    root = publish_dir(directory)
    entry = manifest_entry(name, root)
    source = f"{root / MANIFEST_NAME} models.{name}"
    clash = sorted(set(fields) & set(RESERVED_FIELDS))
    if clash:
        raise VitflyError(f"{source}: field {clash[0]!r} is written by the publisher itself")
    manifest = read_manifest(root)
    entry = {**entry, **{k: _plain(v, source, k) for k, v in fields.items()}}
    manifest["models"][name] = entry
    write_text(root / MANIFEST_NAME, json.dumps(manifest, indent=2) + "\n")
    return entry
