"""Resume states squeezed for the trip to and from the GPU machine: lossless, a quarter smaller.

A device call carries 64 MiB of files each way, and a run's resume state is mostly floats: network weights and
Adam's two moments. A float's low mantissa bytes are close to random, but its sign-and-exponent byte repeats,
so the file's bytes are first split into planes (every 4-byte word's first byte, then every second byte, ...)
and then compressed with zlib. A 4-byte stride suits both fp32 and bf16 values: a pair of bf16s splits into
two low-byte and two high-byte planes. Tensors in a ``torch.save`` file and in a safetensors file start on
aligned offsets, so the planes line up with the values. Measured on the carried states
(``benchmarks/carry_compression.py``; ViT+LSTM, LSTMnet and ConvNet, 7 to 100 epochs): 0.82-0.83 of the bytes
with fp32 moments, 0.735-0.75 with bf16 moments, where plain zlib keeps 0.92 and 0.84; about 2 s for ViT+LSTM's
41 MiB on this 2-core CPU.

A squeezed file is ``NAME.bpz`` beside nothing: ``squeeze_file`` replaces ``NAME`` with it, ``unsqueeze_file``
puts ``NAME`` back, bit for bit (length and CRC-32 checked), and ``unsqueeze_tree`` does so for a whole run folder
before anything reads it. The format: the magic ``VFBPZ1``, the stride (1 byte), the original length (8 bytes,
little-endian), its CRC-32 (4 bytes), then the zlib stream of the planes.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

SUFFIX = ".bpz"
MAGIC = b"VFBPZ1"
HEADER = struct.Struct("<BQI")  # stride, original length, CRC-32
STRIDE = 4
LEVEL = 6  # zlib's default: level 9 took 3-4x the time for 0.3 % fewer bytes


def to_planes(data: bytes, stride: int = STRIDE) -> bytes:
    """``data``'s bytes regrouped: byte 0 of every ``stride``-byte word, then byte 1, ...; a tail shorter than a
    word stays at the end as it is."""
    n = len(data) - len(data) % stride
    return np.frombuffer(data, np.uint8, n).reshape(-1, stride).T.tobytes() + data[n:]


def from_planes(data: bytes, stride: int = STRIDE) -> bytes:
    """``to_planes`` undone."""
    n = len(data) - len(data) % stride
    return np.frombuffer(data, np.uint8, n).reshape(stride, -1).T.tobytes() + data[n:]


def squeeze(data: bytes, level: int = LEVEL) -> bytes:
    return MAGIC + HEADER.pack(STRIDE, len(data), zlib.crc32(data)) + zlib.compress(to_planes(data), level)


def unsqueeze(blob: bytes, source: str = "<bytes>") -> bytes:
    """The bytes ``squeeze`` was given; one line naming ``source`` if ``blob`` is not a whole squeezed file."""
    start = len(MAGIC) + HEADER.size
    if blob[:len(MAGIC)] != MAGIC or len(blob) < start:
        raise SystemExit(f"{source}: not a squeezed file (expected the magic {MAGIC.decode()}, written by "
                         "scripts/gpu_squeeze.py)")
    stride, length, crc = HEADER.unpack_from(blob, len(MAGIC))
    if stride < 1:
        raise SystemExit(f"{source}: damaged (its header gives a byte stride of {stride}); carry or return it again")
    try:
        data = from_planes(zlib.decompress(blob[start:]), stride)
    except zlib.error as err:
        raise SystemExit(f"{source}: damaged ({err}); carry or return it again") from None
    if len(data) != length or zlib.crc32(data) != crc:
        raise SystemExit(f"{source}: damaged (length {len(data)} of {length}, or its CRC-32 differs); carry or "
                         "return it again")
    return data


def read_plain(path: Path) -> bytes:
    """The bytes of ``path`` as they were before ``squeeze_file`` (a plain file: as it is)."""
    data = Path(path).read_bytes()
    return unsqueeze(data, str(path)) if Path(path).name.endswith(SUFFIX) else data


def plain_bytes(path: Path) -> int:
    """The bytes of ``path`` as it was before ``squeeze_file`` (its header says; a plain file: its size)."""
    if not path.name.endswith(SUFFIX):
        return path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(len(MAGIC) + HEADER.size)
    if head[:len(MAGIC)] != MAGIC or len(head) < len(MAGIC) + HEADER.size:
        raise SystemExit(f"{path}: not a squeezed file (expected the magic {MAGIC.decode()})")
    return HEADER.unpack_from(head, len(MAGIC))[1]


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def squeeze_file(path: Path) -> Path:
    """``path`` replaced by ``path.bpz``; returns the new path."""
    out = path.with_name(path.name + SUFFIX)
    _write_atomic(out, squeeze(path.read_bytes()))
    path.unlink()
    return out


def unsqueeze_file(path: Path) -> Path:
    """``NAME.bpz`` replaced by ``NAME``, as it was before ``squeeze_file``; returns ``NAME``."""
    out = path.with_name(path.name[:-len(SUFFIX)])
    _write_atomic(out, read_plain(path))
    path.unlink()
    return out


def unsqueeze_tree(folder: Path) -> list[Path]:
    """Every squeezed file under ``folder`` back in its plain form (nothing to do in a plain folder)."""
    return [unsqueeze_file(p) for p in sorted(Path(folder).rglob(f"*{SUFFIX}")) if p.is_file()]


def squeezed(path: Path) -> Path:
    """``path``, or its squeezed form where only that exists."""
    alt = path.with_name(path.name + SUFFIX)
    return alt if not path.exists() and alt.exists() else path
