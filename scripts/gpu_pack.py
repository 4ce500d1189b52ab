"""What comes back from the GPU machine: folders packed into pieces the device tool returns, and unpacked here.

The device tool brings back at most 8 files of 16 MiB from ``$OUT``. Every ``scripts/gpu.py`` subcommand that
runs there packs what it returns the same way: the folders named ``(arcname, path)`` go into one tar, while they
fit a byte budget, and the tar is split into ``NAME.tar.NNN`` pieces of at most 15 MiB. :func:`pack` returns the
manifest (pieces with their bytes and SHA-256, the tar's SHA-256, each packed folder's files and bytes, what was
left out); the subcommand writes it into its report JSON under ``"pack"``, so pieces and report take no more
files than before. Here :func:`unpack` joins the pieces, checks them against the manifest when the report has
one (a missing or damaged piece is one clear error), and extracts the tar with :func:`safe_extract`: every
member checked first (no absolute or ``..`` paths, no links or devices), on every Python, also Debian bookworm's
3.11.2, whose tarfile has no ``data`` filter.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tarfile
from pathlib import Path

PIECE_BYTES = 15 * 2**20  # the device tool returns files of at most 16 MiB
HEADER_BYTES = 4096  # tar headers and padding per folder, generously
FORMAT = 1


def tree_bytes(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(2**20), b""):
            h.update(block)
    return h.hexdigest()


def pieces_of(folder: Path, name: str) -> list[Path]:
    return sorted(folder.glob(f"{name}.tar.[0-9][0-9][0-9]"))


def write_pieces(path: Path, out: Path, piece_bytes: int = PIECE_BYTES) -> list[dict]:
    """``path`` split into ``out/<name>.NNN`` files of at most ``piece_bytes`` (``cat`` joins them)."""
    pieces = []
    with open(path, "rb") as f:
        for i, block in enumerate(iter(lambda: f.read(piece_bytes), b"")):
            piece = out / f"{path.name}.{i:03d}"
            piece.write_bytes(block)
            pieces.append({"file": piece.name, "bytes": len(block), "sha256": hashlib.sha256(block).hexdigest()})
    return pieces


def pack(entries: list[tuple[str, Path]], out: Path, name: str, work: Path, budget: int | None = None,
         piece_bytes: int = PIECE_BYTES) -> dict:
    """The folders (or files) of ``entries``, in order, as ``out/NAME.tar.NNN`` while they fit ``budget`` bytes
    (None: all); returns the manifest. Stale pieces of ``NAME`` in ``out`` are removed first (unpack joins every
    piece it finds); with nothing packed, no piece is written."""
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    for stale in pieces_of(out, name):
        stale.unlink()
    contents, left, total = [], [], 0
    tar_path = work / f"{name}.tar"
    with tarfile.open(tar_path, "w") as tar:
        for arcname, path in entries:
            check_name(arcname, f"pack {name}")
            size = tree_bytes(path) + HEADER_BYTES
            if budget is not None and total + size > budget:
                left.append(arcname)
                continue
            tar.add(path, arcname=arcname)
            files = sum(1 for p in path.rglob("*") if p.is_file()) if path.is_dir() else 1
            contents.append({"name": arcname, "bytes": size - HEADER_BYTES, "files": files})
            total += size
    manifest = {"format": FORMAT, "name": name, "contents": contents, "left_out": left, "pieces": []}
    if contents:
        manifest.update(tar_bytes=tar_path.stat().st_size, tar_sha256=sha256(tar_path),
                        pieces=write_pieces(tar_path, out, piece_bytes))
    tar_path.unlink()
    return manifest


def read_manifest(src: Path, report: str, name: str) -> dict | None:
    """The manifest that ``src/report`` holds under ``"pack"`` for pieces ``name`` (None: none there)."""
    path = src / report
    if not path.exists():
        return None
    try:
        manifest = json.loads(path.read_text()).get("pack")
    except ValueError as err:
        raise SystemExit(f"{path}: not readable JSON ({err})") from None
    return manifest if isinstance(manifest, dict) and manifest.get("name") == name else None


def join_pieces(src: Path, name: str, tar_path: Path, manifest: dict | None = None) -> None:
    """``src/NAME.tar.NNN`` joined into ``tar_path``; checked against ``manifest`` when there is one."""
    pieces = pieces_of(src, name)
    if not pieces:
        raise SystemExit(f"{src}: no {name}.tar.NNN pieces")
    if manifest is not None:
        expected = [p["file"] for p in manifest["pieces"]]
        if [p.name for p in pieces] != expected:
            raise SystemExit(f"{src}: pieces {[p.name for p in pieces]}, the manifest lists {expected}; "
                             "a piece did not come back")
    with open(tar_path, "wb") as f:
        for piece in pieces:
            f.write(piece.read_bytes())
    if manifest is not None and sha256(tar_path) != manifest["tar_sha256"]:
        raise SystemExit(f"{src}: the joined {name}.tar differs from the one packed (SHA-256); a piece is damaged")


def unpack(src: Path, name: str, dest: Path, report: str | None = None) -> dict | None:
    """The pieces ``src/NAME.tar.NNN`` joined, checked against the manifest in ``src/report`` (if it has one)
    and extracted safely into ``dest``; returns the manifest."""
    manifest = read_manifest(src, report, name) if report else None
    dest.mkdir(parents=True, exist_ok=True)
    tar_path = dest / f".{name}.tar"
    try:
        join_pieces(src, name, tar_path, manifest)
        safe_extract(tar_path, dest)
    finally:
        tar_path.unlink(missing_ok=True)
    return manifest


def check_name(name: str, where: str) -> None:
    parts = Path(name).parts
    if name.startswith(("/", "\\")) or Path(name).is_absolute() or ".." in parts:
        raise SystemExit(f"{where}: member {name!r} points outside the folder it unpacks into")


def check_member(member: tarfile.TarInfo, tar_path: Path) -> None:
    """Refuse what the 'data' filter refuses and more: absolute or '..' paths, links, devices, fifos."""
    check_name(member.name, str(tar_path))
    if not (member.isfile() or member.isdir()):
        raise SystemExit(f"{tar_path}: member {member.name!r} is a link or special file; expected files and folders")


def safe_extract(tar_path: Path, dest: Path) -> None:
    """Unpack ``tar_path`` into ``dest`` and nowhere else, on every Python >= 3.10: every member checked here
    first, then tarfile's 'data' filter where it exists (3.10.12, 3.11.4, 3.12; not Debian bookworm's 3.11.2)."""
    with tarfile.open(tar_path) as tar:
        members = tar.getmembers()
        for member in members:
            check_member(member, tar_path)
        if hasattr(tarfile, "data_filter"):
            tar.extractall(dest, members=members, filter="data")
            return
        for member in members:
            member.mode &= 0o755  # what the filter would do: no set-uid, set-gid or world-writable bits
        tar.extractall(dest, members=members)


def fresh_dir(path: Path) -> Path:
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    return path
