"""A preset's runs kept in the repository, ``carry/<preset>/<label>/``: ``scripts/gpu.py carry`` writes them here,
``restore`` puts them back into the preset's ``train/``, and ``train --resume-from carry/<preset>`` resumes them
on the GPU machine.

Nothing a session leaves outside git outlives it: the next session starts from a new checkout, without runs/
or data/ (both ignored), and on 2026-11-28 a ViT+LSTM state from an H100 slot and a LSTMnet run 65 epochs into a
CPU training were lost so. A run therefore goes on only from what was committed, and the carry is what gets
committed: every run of the preset that has trained here, as plain files (no pickle;
``vitfly.training.checkpoint_files``), small enough for the device tool, which sends the working tree, carry/
included, within 64 MiB a call:

- an unfinished run (stopped by a GPU slot, or started here by ``vitfly reproduce``): ``last.*``, its last
  epoch's resume state, lean (fp32 weights, Adam's moments in fp32 where they fit and in bf16 where they do not:
  an inexact resume), its tensors squeezed losslessly (``last.safetensors.bpz``, ``scripts/gpu_squeeze.py``:
  0.82 of the bytes with fp32 moments, 0.74 with bf16), ``best.*`` where the preset flies the best epoch
  (its network weights as stored: fp16 as a slot returns them, fp32 where it trained here, so a run finished in
  a new checkout flies the weights an uninterrupted run would), ``unfinished.json`` (epochs, data hash, slots)
  and the run's metrics, split, cost, hparams and data record;
- a finished run: ``best.*``, the checkpoint it flies, with the very weights it flew (fp16 as a slot returns
  them, fp32 where it trained here), ``done.json`` and the same run files.

The data never travels: every machine collects it again (deterministic, ``physics: native``), and each run's
data hash is checked against it before anything resumes or is taken as done.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

from scripts.gpu_slots import MARKER, compact_moments, copy_run, epochs_done, mib, relocate, tree_bytes
from scripts.gpu_squeeze import squeeze_file, squeezed, unsqueeze_tree

ROOT = Path(__file__).resolve().parent.parent
CARRY_DIR = "carry"  # carry/<preset>/<label>/: tracked, so it lands with a commit and travels with every call
LAST, BEST = "last", "best"  # the checkpoints' names in a carried folder (NAME.safetensors + NAME.json)
STOWED = "stowed.json"  # a finished run's weights left the tree: the commit and paths that hold them


def git(folder: Path, *args: str) -> str | None:
    """``git -C folder ARGS``'s output, or None where it fails (not a repository, path not tracked)."""
    done = subprocess.run(["git", "-C", str(folder), *args], capture_output=True, text=True)
    return done.stdout.strip() if done.returncode == 0 else None


def stow(folder: Path) -> str | None:
    """A finished run's carried weights (best.*) out of the tree, once a commit holds them as they are: they stay
    in git's history, ``STOWED`` names where, and ``restore`` reads them back from there. Returns the commit, or
    None (not committed yet, or changed since)."""
    from vitfly.training import checkpoint_files

    files = [p for p in checkpoint_files.paths(folder, BEST) if p.exists()]
    top = git(folder, "rev-parse", "--show-toplevel")
    if not files or top is None or git(folder, "status", "--porcelain", "--", *map(str, files)) != "":
        return None
    rel = [str(p.resolve().relative_to(Path(top).resolve())) for p in files]
    commit = git(folder, "log", "-1", "--format=%H", "--", *map(str, files))
    if not commit or any(git(folder, "cat-file", "-e", f"{commit}:{r}") is None for r in rel):
        return None
    stowed = {"commit": commit, "files": {p.name: r for p, r in zip(files, rel, strict=True)}}
    (folder / STOWED).write_text(json.dumps(stowed) + "\n")
    for p in files:
        p.unlink()
    return commit


def unstow(carried: Path, dst: Path) -> None:
    """The weights ``stow`` took out of the carried folder ``carried``, read back from its repository's history
    into ``dst`` (one line if they cannot be)."""
    record = json.loads((carried / STOWED).read_text())
    for name, rel in record["files"].items():
        data = subprocess.run(["git", "-C", str(carried), "show", f"{record['commit']}:{rel}"], capture_output=True)
        if data.returncode != 0:
            raise SystemExit(f"{carried / STOWED}: {rel} is not in commit {record['commit'][:12]} "
                             f"({data.stderr.decode().strip()[:200]}); restore from a clone that has its history")
        (dst / name).write_bytes(data.stdout)
    (dst / STOWED).unlink()


def preset_carry(carry_dir: str, preset: str) -> Path:
    """``carry_dir/<preset>``, in the repository unless ``carry_dir`` is absolute."""
    return ROOT / carry_dir / preset


def other_carries(carry_dir: Path) -> list[Path]:
    """The other presets' carries beside ``carry_dir`` (``carry/<preset>``): no run of theirs goes to this
    preset's slot, so they stay here when it travels light."""
    parent = carry_dir.parent
    if parent == ROOT or not parent.is_dir():
        return []
    return sorted(p for p in parent.iterdir() if p.is_dir() and p.resolve() != carry_dir.resolve())


def lean_last(run: Path, moments: str) -> dict:
    """A run's last.ckpt with Adam's moments in ``moments`` (fp32: as they are)."""
    import torch

    return compact_moments(torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True),
                           moments)


def flown_checkpoint(cfg, r) -> Path | None:
    """The checkpoint a finished run flies (done.json's), or an unfinished run's best so far where the preset
    flies the best epoch (None: nothing to keep)."""
    from scripts.gpu_preset import flies_best

    done = r.folder / "done.json"
    if done.exists():
        path = Path(json.loads(done.read_text())["checkpoint"])
        # relative: to the run folder as carried runs write it, or to the working directory as `vitfly reproduce`
        # with a relative output directory writes it (an absolute path stays itself)
        return next((p for p in (r.folder / path, path) if p.exists()), r.folder / path)
    best = r.folder / "checkpoints" / "best.ckpt"
    return best if flies_best(cfg, r.run) and best.exists() else None


def cpu_marker(cfg, r) -> dict:
    """The resume marker of a run started here (``vitfly reproduce``), which has none yet."""
    from scripts.gpu_plan import max_epochs

    run = r.folder
    record = json.loads((run / "data.json").read_text()) if (run / "data.json").exists() else {}
    # its one slot: every epoch so far, on this CPU, timed by the checkpoint's Timer
    return caught_up({"label": r.label, "preset": cfg.preset, "dataset_hash": record.get("dataset_hash"),
                      "max_epochs": max_epochs(cfg, r.run), "slots": []}, run)


def caught_up(marker: dict, run: Path) -> dict:
    """``marker`` with the epochs of the run's ``last.ckpt``, and those that ``vitfly reproduce`` trained here since
    the marker's last slot as one more CPU slot.

    Its ``wall_s`` is the fitting time that ``last.ckpt``'s ``Timer`` gained since the last slot's ``fit_s``;
    a slot without ``fit_s`` (older markers) ended at the sum of the slots' ``wall_s``, exact for CPU slots (their
    ``wall_s`` is the Timer's) and a little early for GPU ones (start-up included), so never too much here.
    """
    from vitfly.workflows.reproduce import _fit_seconds

    slots = marker.get("slots", [])
    since = slots[-1]["epochs"][1] if slots else 0
    n = epochs_done(run)
    if n <= since:
        return {**marker, "epochs": n}
    fit_s = _fit_seconds(run)
    before = slots[-1].get("fit_s", sum(s["wall_s"] for s in slots)) if slots else 0.0
    slot = {"device": "cpu", "epochs": [since, n], "wall_s": round(max(0.0, fit_s - before), 1),
            "fit_s": round(fit_s, 1)}
    return {**marker, "epochs": n, "slots": [*slots, slot]}


def park(cfg, r, dst: Path, moments: str) -> int:
    """Run ``r`` (``scripts.gpu_plan.RunState``) as its carried folder ``dst``; returns its bytes."""
    from scripts.gpu_slots import copy_run_files, slim
    from vitfly.training import checkpoint_files

    run = r.folder
    dst.mkdir(parents=True)
    flown = flown_checkpoint(cfg, r)
    if flown is not None:
        # every run keeps its best weights as stored (fp16 from a slot, fp32 where it trained here): rounded, one
        # trial in eight to one in four flies otherwise, so a finished run's published outcomes would not come
        # back, and an unfinished one whose best epoch stays best would finish with other weights than it trained
        checkpoint_files.write(slim(flown, half=False), dst, BEST)
    if r.state == "done":
        done = json.loads((run / "done.json").read_text())
        (dst / "done.json").write_text(json.dumps({**done, "checkpoint": BEST}) + "\n")
    else:
        marker = r.marker if r.state == "unfinished" else cpu_marker(cfg, r)  # run_states caught it up
        checkpoint_files.write(lean_last(run, moments), dst, LAST)
        squeeze_file(checkpoint_files.paths(dst, LAST)[0])
        (dst / MARKER).write_text(json.dumps({**marker, "carried_moments": moments}) + "\n")
    # a run training here now may have logged an epoch its last.ckpt does not hold yet: its rows stay behind
    copy_run_files(run, dst, None if r.state == "done" else marker["epochs"])
    return tree_bytes(dst)


def carried_epochs(folder: Path) -> float:
    """How far a carried run is: its epochs, infinite when done (nothing here replaces a finished run)."""
    if (folder / "done.json").exists():
        return float("inf")
    return json.loads((folder / MARKER).read_text())["epochs"]


def check_carry(carry_dir: Path) -> dict[str, Path]:
    """label -> folder of what ``carry_dir`` holds; refused (one line) for anything but carried run folders."""
    if not carry_dir.exists():
        return {}
    for unfinished in carry_dir.glob(".*.writing"):  # a carry interrupted while writing this folder
        shutil.rmtree(unfinished)
    strangers = [p.name for p in carry_dir.iterdir()
                 if not ((p / MARKER).exists() or (p / "done.json").exists())]
    if strangers:
        raise SystemExit(f"{carry_dir}: holds {', '.join(sorted(strangers)[:3])}, not carried runs; "
                         "nothing written (name another --carry-dir)")
    return {p.name: p for p in carry_dir.iterdir()}


def write_carry(cfg, rows: list, slot, carry_dir: Path, room: int) -> None:
    """Every run of ``rows`` that trained here into ``carry_dir``: the slot's carried runs with the moments its
    plan chose, the others (they stay here when the call travels light: ``scripts/gpu_travel.py``) with fp32
    moments. A carried run that is not here (a new checkout not restored), further along than here, or restored
    and not trained since stays as it is (unless the slot needs it lighter: then it says so); each folder is
    written beside its old one and then replaces it. Says (one line) when the slot's runs
    take more than ``room``, what a call leaves the carry."""
    carried = check_carry(carry_dir)
    written = travelling = 0
    for r in rows:
        old = carried.get(r.label)
        if old is not None and (old / "done.json").exists():  # finished: it never changes again
            commit = stow(old) if not (old / STOWED).exists() else None
            written += tree_bytes(old)
            print(f"  kept: {r.label} (done" + (f"; its weights now in git's history, commit {commit[:12]}: "
                                                 "commit the carry again)" if commit else ")"))
            continue
        here = float("inf") if r.state == "done" else epochs_done(r.folder) if r.folder else 0
        if old is not None and (r.folder is None or carried_epochs(old) > here):
            written += tree_bytes(old)
            print(f"  kept as it was: {r.label} (further along in {carry_dir.name}/ than here; restore it to go on)")
            continue
        if r.folder is None:
            continue
        if not here:  # in its first epoch here (vitfly reproduce holds it): no checkpoint yet
            print(f"  not yet: {r.label} (no epoch has ended here, nothing to carry)")
            continue
        moments = slot.moments.get(r.label, "fp32")
        if old is not None and r.state != "done" and carried_epochs(old) == here:
            # restored and not trained since: written again it would cost a commit the old bytes and the new
            had = json.loads((old / MARKER).read_text()).get("carried_moments", "fp32")
            if moments == had or moments == "fp32":  # fp32 would hold bf16's rounded values no better
                size = tree_bytes(old)
                written += size
                travelling += size if r.label in slot.moments else 0
                print(f"  kept as it was: {r.label} (has not trained since it was carried, {had} moments)")
                continue
            print(f"  {r.label}: has not trained since it was carried with {had} moments, written again with "
                  f"{moments} for the slot's room (an inexact resume): commit it only once the slot has trained "
                  f"it; git checkout -- {carry_dir / r.label} puts the carried one back")
        tmp = carry_dir / f".{r.label}.writing"
        shutil.rmtree(tmp, ignore_errors=True)
        size = park(cfg, r, tmp, moments)
        written += size
        travelling += size if r.label in slot.moments else 0
        if old is not None:
            shutil.rmtree(old)
        tmp.rename(carry_dir / r.label)
        what = "done, the flown weights" if r.state == "done" else f"unfinished, {moments} moments"
        print(f"  kept: {r.label} ({what}): {mib(tree_bytes(carry_dir / r.label))}")
    if not written:
        print(f"  nothing has trained here: {carry_dir}/ holds nothing")
        return
    print(f"  {carry_dir}/ holds {mib(written)}, {mib(travelling)} of it for the slot; commit it: the next session "
          "and the next slot go on from it")
    if travelling > room:
        print(f"  the slot's runs ({mib(travelling)}) are over the {mib(room)} a device call leaves them: a call "
              "would be refused")


def materialize(folder: Path) -> None:
    """A carried folder made a run folder in place: ``last.*`` and ``best.*`` as ``checkpoints/*.ckpt`` (the
    callbacks pointed there), what Lightning and ``vitfly reproduce`` read."""
    import torch

    from vitfly.training import checkpoint_files

    unsqueeze_tree(folder)
    ckpt_dir = folder / "checkpoints"
    ckpt_dir.mkdir(exist_ok=True)
    for name in (LAST, BEST):
        if checkpoint_files.exists(folder, name):
            obj = checkpoint_files.read(folder, name)
            torch.save(relocate(obj, ckpt_dir) if name == LAST else obj, ckpt_dir / f"{name}.ckpt")
            for path in checkpoint_files.paths(folder, name):
                path.unlink()
    done = folder / "done.json"
    if done.exists():
        record = json.loads(done.read_text())
        record["checkpoint"] = str((ckpt_dir / f"{BEST}.ckpt").resolve())
        done.write_text(json.dumps(record) + "\n")


def is_carried(folder: Path) -> bool:
    """Whether ``folder`` holds a carried checkpoint (plain or squeezed), which ``materialize`` turns into
    ``checkpoints/*.ckpt``."""
    from vitfly.training import checkpoint_files

    return any(all(squeezed(p).exists() for p in checkpoint_files.paths(folder, name)) for name in (LAST, BEST))


def carried_hash(folder: Path) -> str | None:
    """The dataset hash a carried run was trained on: its data record, else its marker's or done.json's."""
    from scripts.gpu_slots import returned_hash

    record = folder / "data.json"
    return json.loads(record.read_text()).get("dataset_hash") if record.exists() else returned_hash(folder)


def restore(args) -> int:
    """``carry/<preset>/`` back into the preset's ``train/``: each run that is not done here and not further along
    here; its data hash checked against the local dataset first (one line naming both, nothing restored)."""
    from scripts.gpu_preset import load_cfg, local_data_hash, run_dir

    cfg = load_cfg(args)
    src = preset_carry(args.carry_dir, cfg.preset)
    if not src.is_dir():
        print(f"{src}: no carried runs")
        return 0
    local = local_data_hash(cfg)
    folders = sorted(p for p in src.iterdir() if p.is_dir())
    for folder in folders:
        if carried_hash(folder) != local:
            raise SystemExit(f"{folder}: trained on dataset_hash {carried_hash(folder)}; the local {cfg.data} has "
                             f"{local}; nothing restored (collect the preset's data as it was: physics, count)")
    for folder in folders:
        dst = run_dir(cfg, folder.name)
        carried = json.loads((folder / MARKER).read_text())["epochs"] if (folder / MARKER).exists() else None
        if (dst / "done.json").exists():
            print(f"{dst}: done here; left alone")
        elif carried is not None and epochs_done(dst) >= carried:
            print(f"{dst}: {epochs_done(dst)} epochs here, {carried} carried; left alone")
        else:
            copy_run(folder, dst)
            if (dst / STOWED).exists():
                unstow(folder, dst)
            materialize(dst)
            print(f"{dst}: " + ("done" if carried is None else f"unfinished, {carried} epochs; vitfly reproduce "
                                "or the next slot goes on from it"))
    return 0

