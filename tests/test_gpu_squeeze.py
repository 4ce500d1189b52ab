"""scripts/gpu_squeeze.py: the byte planes by hand, the round trip bit for bit, damage refused, and the gain on
floats worked out from their bytes."""

from __future__ import annotations

import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from scripts import gpu_squeeze as sq  # noqa: E402


def test_planes_put_each_words_bytes_together_and_keep_the_tail():
    # 1.0 = 0x3F800000 and 2.0 = 0x40000000, little-endian 00 00 80 3F and 00 00 00 40; then a 2-byte tail
    data = np.array([1.0, 2.0], dtype=np.float32).tobytes() + b"\x07\x09"
    assert sq.to_planes(data) == bytes([0, 0, 0, 0, 0x80, 0, 0x3F, 0x40, 7, 9])
    assert sq.from_planes(sq.to_planes(data)) == data
    # bf16 1.0 (0x3F80) and 0.5 (0x3F00) as one 4-byte word: 80 3F 00 3F -> planes of one byte each
    assert sq.to_planes(bytes([0x80, 0x3F, 0x00, 0x3F])) == bytes([0x80, 0x3F, 0x00, 0x3F])
    words = bytes([0x80, 0x3F, 0x00, 0x3F] * 3)  # three words: the low bytes, then the high bytes, together
    assert sq.to_planes(words) == bytes([0x80] * 3 + [0x3F] * 3 + [0x00] * 3 + [0x3F] * 3)


@pytest.mark.parametrize("n", [0, 1, 3, 4, 1001])
def test_squeeze_round_trips_any_bytes_with_a_header_that_says_what_it_holds(n):
    data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    blob = sq.squeeze(data)
    assert blob[:6] == b"VFBPZ1" and struct.unpack_from("<BQI", blob, 6) == (4, n, zlib.crc32(data))
    assert sq.unsqueeze(blob) == data


def test_floats_squeeze_by_the_bytes_that_repeat():
    """Values in [1, 2) with random mantissas: the top byte of each fp32 is always 0x3F (sign 0, exponent 127's
    high bits), the next one 0x80 plus 7 random bits, the two low ones random. The planes compress to about
    (0 + 7/8 + 1 + 1) / 4 = 0.72 of the bytes; zlib alone sees the bytes interleaved and keeps over 0.1 more."""
    values = 1.0 + np.random.default_rng(0).random(100_000).astype(np.float32) * 0.999
    data = values.tobytes()
    ratio = len(sq.squeeze(data)) / len(data)
    assert 0.70 < ratio < 0.75
    assert len(zlib.compress(data, sq.LEVEL)) / len(data) > ratio + 0.1


def test_damage_is_refused_in_one_line(tmp_path):
    data = np.arange(1000, dtype=np.float32).tobytes()
    blob = bytearray(sq.squeeze(data))
    with pytest.raises(SystemExit, match=r"^x\.bpz: not a squeezed file"):
        sq.unsqueeze(b"PK\x03\x04" + bytes(blob[4:]), "x.bpz")
    with pytest.raises(SystemExit, match=r"^x\.bpz: damaged"):
        sq.unsqueeze(bytes(blob[:-10]), "x.bpz")  # cut short
    no_stride = blob[:6] + b"\x00" + blob[7:]  # the header's stride byte
    with pytest.raises(SystemExit, match=r"^x\.bpz: damaged \(its header gives a byte stride of 0\)"):
        sq.unsqueeze(bytes(no_stride), "x.bpz")
    wrong_crc = blob[:15] + bytes([blob[15] ^ 1]) + blob[16:]  # the CRC field's last byte
    with pytest.raises(SystemExit, match=r"^x\.bpz: damaged \(length 4000 of 4000, or its CRC-32 differs\)"):
        sq.unsqueeze(bytes(wrong_crc), "x.bpz")


def test_files_and_folders_are_squeezed_in_place_and_read_back(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    ckpt = run / "checkpoints" / "last.ckpt"
    torch.save({"w": torch.linspace(-1, 1, 5000)}, ckpt)
    original = ckpt.read_bytes()
    (run / "metrics.csv").write_text("epoch\n0\n")
    squeezed = sq.squeeze_file(ckpt)
    assert squeezed.name == "last.ckpt.bpz" and not ckpt.exists() and sq.squeezed(ckpt) == squeezed
    assert sq.plain_bytes(squeezed) == len(original) and squeezed.stat().st_size < len(original)
    assert sorted(p.name for p in run.rglob("*") if p.is_file()) == ["last.ckpt.bpz", "metrics.csv"]
    assert sq.unsqueeze_tree(run) == [ckpt]
    assert ckpt.read_bytes() == original and not squeezed.exists() and sq.squeezed(ckpt) == ckpt
    assert sq.unsqueeze_tree(run) == []  # a plain folder: nothing to do
    assert sq.plain_bytes(ckpt) == len(original)
    assert torch.equal(torch.load(ckpt, weights_only=True)["w"], torch.linspace(-1, 1, 5000))
