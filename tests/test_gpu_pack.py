"""scripts/gpu.py's one packing path (scripts/gpu_pack.py) and its ``evaluate`` round trip.

Folders go out as a tar split into pieces of a size limit with a manifest (pieces, SHA-256, contents) and come
back whole; a missing or damaged piece, and a member that would land outside the folder ('..', absolute paths,
links), are refused before anything is written, also on a Python without tarfile's 'data' filter. A
``vitfly evaluate`` sweep flown by ``gpu.py evaluate`` packs its records, which ``gpu.py unpack`` merges into a
local sweep directory as ``vitfly evaluate --merge`` does.
"""

from __future__ import annotations

import io
import json
import os
import tarfile
from pathlib import Path

import pytest
from helpers import load_script


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def folders(tmp_path) -> Path:
    src = tmp_path / "src"
    for name, size in (("a/weights.bin", 150_000), ("a/nested/log.txt", 10_000), ("b/records.jsonl", 90_000),
                       ("c/big.bin", 400_000)):
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        (src / name).write_bytes(os.urandom(size))
    return src


def test_folders_travel_in_pieces_of_a_size_limit_with_their_manifest(tmp_path, folders):
    gpu_pack = load_script("gpu_pack")
    out, piece = tmp_path / "out", 64 * 2**10
    entries = [(name, folders / name) for name in ("a", "b", "c")]
    manifest = gpu_pack.pack(entries, out, "runs", tmp_path / "work", budget=300_000, piece_bytes=piece)

    assert [c["name"] for c in manifest["contents"]] == ["a", "b"] and manifest["left_out"] == ["c"]
    assert manifest["contents"][0] == {"name": "a", "bytes": 160_000, "files": 2}
    pieces = sorted(out.glob("runs.tar.*"))
    assert [p.name for p in pieces] == [p["file"] for p in manifest["pieces"]] and len(pieces) > 2
    assert all(p.stat().st_size <= piece for p in pieces) and sum(p["bytes"] for p in manifest["pieces"]) == \
        manifest["tar_bytes"]
    assert not (tmp_path / "work" / "runs.tar").exists()
    (out / "report.json").write_text(json.dumps({"what": "a test", "pack": manifest}))

    assert gpu_pack.unpack(out, "runs", tmp_path / "back", "report.json") == manifest
    back = tree(tmp_path / "back")
    assert back == {k: v for k, v in tree(folders).items() if not k.startswith("c/")}

    # a second pack into the same folder leaves no stale piece behind; nothing packed, no piece
    assert gpu_pack.pack([("c", folders / "c")], out, "runs", tmp_path / "work", budget=1000)["pieces"] == []
    assert not list(out.glob("runs.tar.*"))


def test_a_missing_or_damaged_piece_is_refused(tmp_path, folders):
    gpu_pack = load_script("gpu_pack")
    out = tmp_path / "out"
    manifest = gpu_pack.pack([("a", folders / "a")], out, "study", tmp_path / "work", piece_bytes=50_000)
    (out / "study.json").write_text(json.dumps({"pack": manifest}))
    last = sorted(out.glob("study.tar.*"))[-1]
    data = last.read_bytes()

    last.unlink()
    with pytest.raises(SystemExit, match="a piece did not come back"):
        gpu_pack.unpack(out, "study", tmp_path / "back1", "study.json")
    last.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    with pytest.raises(SystemExit, match="a piece is damaged"):
        gpu_pack.unpack(out, "study", tmp_path / "back2", "study.json")
    assert not tree(tmp_path / "back2")
    last.write_bytes(data)  # without a manifest (a report from before them), the pieces are taken as they are
    (out / "study.json").unlink()
    assert gpu_pack.unpack(out, "study", tmp_path / "back3", "study.json") is None
    assert tree(tmp_path / "back3") == {f"a/{k}": v for k, v in tree(folders / "a").items()}


@pytest.mark.parametrize("filter_present", [True, False], ids=["data_filter", "python_3.11.2"])
def test_unpacking_refuses_members_outside_its_folder(tmp_path, monkeypatch, filter_present):
    gpu_pack = load_script("gpu_pack")
    if not filter_present:  # TarFile.extractall(filter=...) arrived in 3.10.12 / 3.11.4
        monkeypatch.delattr(tarfile, "data_filter", raising=False)
    with pytest.raises(SystemExit, match="points outside"):  # refused on the way out too
        gpu_pack.pack([("../up", tmp_path)], tmp_path / "never", "runs", tmp_path / "work")

    for i, (name, kind, target) in enumerate([("../escaped.json", tarfile.REGTYPE, ""),
                                              ("/tmp/absolute.json", tarfile.REGTYPE, ""),
                                              ("run/../../escaped.json", tarfile.REGTYPE, ""),
                                              ("run/link", tarfile.SYMTYPE, "/etc/passwd")]):
        src = tmp_path / f"src{i}"
        src.mkdir()
        with tarfile.open(tmp_path / "runs.tar", "w") as tar:
            ok = tarfile.TarInfo("run/ok.json")
            ok.size = 2
            tar.addfile(ok, io.BytesIO(b"{}"))
            info = tarfile.TarInfo(name)
            info.type, info.linkname, info.size = kind, target, 2 if kind == tarfile.REGTYPE else 0
            tar.addfile(info, io.BytesIO(b"{}") if kind == tarfile.REGTYPE else None)
        gpu_pack.write_pieces(tmp_path / "runs.tar", src, piece_bytes=512)
        dest = tmp_path / f"dest{i}"
        with pytest.raises(SystemExit, match="member"):
            gpu_pack.unpack(src, "runs", dest)
        assert not tree(dest)  # refused before anything is written
    assert not (tmp_path / "escaped.json").exists()


def test_unpack_takes_what_a_folder_holds(tmp_path, folders, capsys):
    gpu = load_script("gpu")
    gpu_pack = load_script("gpu_pack")
    with pytest.raises(SystemExit, match="found none"):
        gpu.main(["unpack", str(tmp_path)])
    out = tmp_path / "out"
    study = {"pack": gpu_pack.pack([("end", folders / "a"), ("logs", folders / "b")], out, "study", tmp_path / "w")}
    (out / "study.json").write_text(json.dumps(study))
    with pytest.raises(SystemExit, match="--into"):
        gpu.main(["unpack", str(out)])
    assert gpu.main(["unpack", str(out), "--into", str(tmp_path / "study")]) == 0
    assert "end/, logs/ unpacked" in capsys.readouterr().out
    assert tree(tmp_path / "study" / "logs") == tree(folders / "b")
    gpu_pack.pack([("x", folders / "c")], out, "runs", tmp_path / "w")
    with pytest.raises(SystemExit, match="found runs and study"):
        gpu.main(["unpack", str(out), "--into", str(tmp_path / "study")])


def test_evaluate_packs_records_that_merge_into_a_local_sweep(tmp_path, monkeypatch, capsys):
    gpu = load_script("gpu")
    for key in ("MPLBACKEND", "WANDB_MODE", "PYTHONUNBUFFERED"):  # what gpu.py sets for a job there
        monkeypatch.setenv(key, os.environ.get(key, ""))
    out, home = tmp_path / "out", tmp_path / "home" / "spheres"
    fly = ["--policy", "expert", "--env", "spheres", "--speeds", "3", "--trials", "1", "--workers", "1",
           "--num-envs", "1", "--physics", "native", "--no-gif", "--no-plots"]
    with pytest.raises(SystemExit, match="--out is set by scripts/gpu.py"):
        gpu.main(["evaluate", "--out", str(out), "--", *fly, "--out", "elsewhere"])
    assert gpu.main(["evaluate", "--out", str(out), "--work", str(tmp_path / "work"), "--", *fly]) == 0
    report = json.loads((out / "gpu_evaluate.json").read_text())
    assert report["trials"] == 1 and report["rc"] == 0 and "--device" in report["command"]
    assert [c["name"] for c in report["pack"]["contents"]] == ["eval", "evaluate.log"]
    assert sorted(p.name for p in out.iterdir()) == ["eval.tar.000", "gpu_evaluate.json"]

    capsys.readouterr()
    assert gpu.main(["unpack", str(out), "--into", str(home), "--no-plots"]) == 0
    assert "merged 1 new trials" in capsys.readouterr().out
    assert len((home / "trials.jsonl").read_text().splitlines()) == 1 and (home / "summary.md").exists()
    assert not list(home.parent.glob(".*gpu_unpack"))  # the scratch folder is gone
    assert gpu.main(["unpack", str(out), "--into", str(home), "--no-plots"]) == 0  # again: nothing new
    assert "merged 0 new trials" in capsys.readouterr().out
    assert len((home / "trials.jsonl").read_text().splitlines()) == 1
