"""A Lightning checkpoint as two plain files, ``NAME.safetensors`` (its tensors) and ``NAME.json`` (the rest).

Run states that land in the repository (``carry/``, docs/reproduce.md "Runs outlive the session") use this form:
no pickle, any safetensors and JSON reader can open them, and ``read`` gives back the dict ``torch.save`` would
have written, for Lightning to resume from. The JSON mirrors the checkpoint's nesting; a tensor stands there as
``{"__tensor__": KEY}`` (its key in the safetensors file: the path of names to it), a tuple as
``{"__tuple__": [...]}``, a dict with keys other than strings (the optimiser's parameter ids) as
``{"__items__": [[key, value], ...]}``. Anything else (a class, a numpy array, a set) is refused with its path.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from vitfly.errors import VitflyError

TENSOR, TUPLE, ITEMS = "__tensor__", "__tuple__", "__items__"
TAGS = (TENSOR, TUPLE, ITEMS)


def _encode(obj, path: str, tensors: dict, source: str):
    import torch

    if isinstance(obj, torch.Tensor):
        tensors[path] = obj.detach().cpu().contiguous().clone()  # clone: safetensors refuses shared storage
        return {TENSOR: path}
    if isinstance(obj, dict):
        if all(isinstance(k, str) and k not in TAGS for k in obj):
            return {k: _encode(v, f"{path}/{k}", tensors, source) for k, v in obj.items()}
        return {ITEMS: [[_key(k, path, source), _encode(v, f"{path}/{k}", tensors, source)] for k, v in obj.items()]}
    if isinstance(obj, (list, tuple)):
        items = [_encode(v, f"{path}/{i}", tensors, source) for i, v in enumerate(obj)]
        return {TUPLE: items} if isinstance(obj, tuple) else items
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    raise VitflyError(f"{source}: {path or '/'}: a {type(obj).__name__} has no plain form (tensors, numbers, "
                      "strings, None, lists, tuples and dicts only)")


def _key(k, path: str, source: str):
    if k is None or isinstance(k, (bool, int, float, str)):
        return k
    raise VitflyError(f"{source}: {path or '/'}: a dict key of type {type(k).__name__} has no plain form")


def _decode(obj, tensors: dict, source: str):
    if isinstance(obj, list):
        return [_decode(v, tensors, source) for v in obj]
    if not isinstance(obj, dict):
        return obj
    if TENSOR in obj:
        if obj[TENSOR] not in tensors:
            raise VitflyError(f"{source}: tensor {obj[TENSOR]!r} is named in the JSON but missing from the "
                              "safetensors file")
        return tensors[obj[TENSOR]]
    if TUPLE in obj:
        return tuple(_decode(v, tensors, source) for v in obj[TUPLE])
    if ITEMS in obj:
        return {k: _decode(v, tensors, source) for k, v in obj[ITEMS]}
    return {k: _decode(v, tensors, source) for k, v in obj.items()}


def paths(folder: str | os.PathLike, name: str) -> tuple[Path, Path]:
    """The two files of checkpoint ``name`` in ``folder``: (tensors, the rest)."""
    return Path(folder) / f"{name}.safetensors", Path(folder) / f"{name}.json"


def write(checkpoint: dict, folder: str | os.PathLike, name: str) -> int:
    """``checkpoint`` as ``folder/name.safetensors`` + ``folder/name.json``, each written atomically (a file
    beside it, then renamed); returns their bytes."""
    from safetensors.torch import save_file

    tensor_file, json_file = paths(folder, name)
    tensors: dict = {}
    skeleton = _encode(checkpoint, "", tensors, str(json_file))
    Path(folder).mkdir(parents=True, exist_ok=True)
    for target, save in ((tensor_file, lambda p: save_file(tensors, str(p))),
                         (json_file, lambda p: p.write_text(json.dumps(skeleton, allow_nan=True) + "\n"))):
        tmp = target.with_name(target.name + ".tmp")
        save(tmp)
        os.replace(tmp, target)
    return tensor_file.stat().st_size + json_file.stat().st_size


def read(folder: str | os.PathLike, name: str) -> dict:
    """The checkpoint ``write`` wrote as ``folder/name.*``; one line naming the file if either is missing or
    unreadable."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    tensor_file, json_file = paths(folder, name)
    try:
        skeleton = json.loads(json_file.read_text())
        tensors = load_file(str(tensor_file))
    except (OSError, ValueError, SafetensorError) as err:
        raise VitflyError(f"{folder}: checkpoint {name!r} unreadable ({type(err).__name__}: {err}); expected "
                          f"{tensor_file.name} and {json_file.name} written by vitfly.training.checkpoint_files"
                          ) from None
    return _decode(skeleton, tensors, str(json_file))


def exists(folder: str | os.PathLike, name: str) -> bool:
    return all(p.exists() for p in paths(folder, name))
