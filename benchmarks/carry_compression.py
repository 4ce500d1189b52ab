"""How much smaller a carried resume state gets under lossless compression: whether three large runs' states
would fit one device call's room beside the working tree travelling light, where two fit today.

    python benchmarks/carry_compression.py carry/paper/vit_lstm-state [more run folders ...] [--level 6]

Reads each carried run's ``last.safetensors`` (``scripts/gpu_carry.py``: fp32 network weights and Adam's two
moments, fp32 or bf16; carried squeezed as ``last.safetensors.bpz``, ``scripts/gpu_squeeze.py``, it is read back
first) and prints a Markdown table per tensor group: the bytes as carried (the moments also
rounded to bf16, as ``--carry-moments bf16`` carries them) and compressed with zlib, plain and after a byte
shuffle (each value's bytes split into planes, so the sign/exponent bytes, which repeat, sit together). A
float's low mantissa bytes are close to random, so the gain comes from the high bytes; it depends on the
trained values, hence a real carried state rather than a freshly initialised network.
"""

from __future__ import annotations

import argparse
import sys
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from scripts.gpu_squeeze import read_plain, squeeze, squeezed, to_planes  # noqa: E402

MIB = 2**20


def shuffled(values: np.ndarray) -> bytes:
    """The bytes of ``values`` as planes: every value's first byte, then every second byte, and so on."""
    return to_planes(values.tobytes(), values.dtype.itemsize)


def groups(path: Path, data: bytes | None = None) -> dict[str, np.ndarray]:
    """``weights`` (fp32), ``exp_avg`` and ``exp_avg_sq`` (as carried), and both moments in bf16 (``*_bf16``,
    as raw 16-bit patterns: numpy has no bf16), each one flat array; ``data``: the file's plain bytes, if read."""
    import torch
    from safetensors.torch import load

    tensors = load(read_plain(path) if data is None else data)
    out: dict[str, list] = {}
    for key, t in tensors.items():
        if key.startswith("/state_dict/") and t.is_floating_point():
            out.setdefault("weights", []).append(t.float().flatten().numpy())
        for moment in ("exp_avg", "exp_avg_sq"):
            if key.endswith(f"/{moment}"):
                out.setdefault(moment, []).append(t.flatten().view(torch.int16 if t.dtype == torch.bfloat16
                                                                   else torch.int32).numpy())
                out.setdefault(f"{moment}_bf16", []).append(t.flatten().to(torch.bfloat16).view(torch.int16).numpy())
    return {name: np.concatenate(parts) for name, parts in out.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="carried run folders (carry/PRESET/LABEL)")
    parser.add_argument("--level", type=int, default=6, help="zlib's level")
    args = parser.parse_args(argv)
    print("| run | tensors | carried | zlib | shuffled + zlib |")
    print("|---|---|---:|---:|---:|")
    for run in args.runs:
        path = squeezed(run / "last.safetensors")
        if not path.is_file():
            raise SystemExit(f"{path}: no such file; expected a run folder that scripts/gpu.py carry wrote")
        whole = read_plain(path)
        lean = {"moments as carried": [0, 0, 0], "bf16 moments": [0, 0, 0]}
        for name, values in groups(path, whole).items():
            sizes = [values.nbytes, len(zlib.compress(values.tobytes(), args.level)),
                     len(zlib.compress(shuffled(values), args.level))]
            print(f"| {run.name} | {name} ({values.dtype.itemsize * 8}-bit) | {sizes[0] / MIB:.1f} MiB | "
                  f"{sizes[1] / sizes[0]:.3f} | {sizes[2] / sizes[0]:.3f} |", flush=True)
            for state, parts in lean.items():
                if name == "weights" or name.endswith("_bf16") == (state == "bf16 moments"):
                    parts[:] = [a + b for a, b in zip(parts, sizes, strict=True)]
        for state, (raw, plain, shuffle) in lean.items():
            print(f"| {run.name} | **weights + {state}** | {raw / MIB:.1f} MiB | {plain / MIB:.1f} MiB | "
                  f"{shuffle / MIB:.1f} MiB |")
        print(f"| {run.name} | the whole file, as scripts/gpu_squeeze.py carries it (4-byte planes) | "
              f"{len(whole) / MIB:.1f} MiB | | {len(squeeze(whole, args.level)) / MIB:.1f} MiB |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
