"""Train runs of a ``vitfly reproduce`` preset on a GPU machine lent in time-boxed slots, and carry them home:
the ``train``, ``train-one``, ``status``, ``carry`` and runs' ``unpack`` commands of ``scripts/gpu.py`` (the old command
line ``scripts/gpu_reproduce.py ARGS`` is ``scripts/gpu.py ARGS``).

There (the device machine, 16 cores and one GPU; at most 10 minutes a command; the working tree and the carry
64 MiB together, 8 files and 64 MiB brought back):

    python3 scripts/gpu.py train --preset paper --out DIR --expect-data-hash HASH \\
        --runs convnet-state vit_lstm-state ... [--resume-from carry/paper]

1. the preset's dataset, collected there with many workers (the collector is deterministic: the file is
   byte-identical to one collected anywhere else with the same settings; ``--expect-data-hash`` refuses to
   train on anything else, and so does every resumed run whose ``unfinished.json`` names another hash);
2. every run as its own process, all at once (small TBPTT batches leave a GPU mostly idle; where the machine has
   NVIDIA's MPS daemon, the runs share the card through a private one, ``scripts/gpu_mps.py``, unless ``--no-mps``),
   through the same code as ``vitfly reproduce``'s train stage (recipe, preset overrides, done.json); a run of
   ``--resume-from`` (a run folder that ``unpack`` left unfinished, or the lean copy ``carry`` kept of it in
   ``carry/<preset>/``, which travels with the working tree) goes on from its last epoch; a run that finishes with
   no epoch better than a best one it was carried without says so in its done.json. Every epoch ends in
   ``last.ckpt``; a run does not start an epoch that would end after the deadline (``--stop-after-epochs`` stops it
   after that many), and one still running then is killed and goes on from its last epoch next time. A run with a
   done.json is never trained again. ``--go-on`` makes a follow-on call on a machine still warm from the last one
   (the device time a lease leaves after a 10-minute command): each run goes on from its folder there (full state;
   the first call wrote its ``unfinished.json``) where that is further along than the ``--resume-from`` state;
3. the runs packed for the trip back as ``runs.tar.NNN`` (``scripts/gpu_pack.py``; at most ``--return-mib``,
   finished runs first):
   a finished run as metrics, split, cost, done.json and its best checkpoint without optimiser state (network
   weights in fp16, as the shipped weights); an unfinished one as its resume state (``scripts/gpu_slots.py``:
   ``last.ckpt`` with fp32 weights, Adam moments in fp32 or ``--moments bf16``, loop and random-generator
   state; the best checkpoint so far in fp16; ``unfinished.json``: epochs done, data hash, the slots so far);
   every checkpoint squeezed losslessly (``*.ckpt.bpz``, ``scripts/gpu_squeeze.py``: 0.74 of the bytes with
   bf16 moments, 0.82 with fp32), so three large runs' states come back where two did.
   DIR/gpu_reproduce.json says what happened to each run, whether they shared the card through MPS (``mps``),
   how busy they kept it (``card_load``: ``nvidia-smi`` every 5 s, ``scripts/gpu_load.py``) and holds the
   pieces' manifest; the command exits 0 when every run came back (finished, or unfinished with at least one
   more epoch) or was finished before.

Here (the machine that goes on with the preset):

    python3 scripts/gpu.py unpack --preset paper DIR
    python3 scripts/gpu.py status --preset paper
    python3 scripts/gpu.py carry --preset paper       # every run that trained here into carry/paper/; commit it

``unpack`` refuses runs trained on other data than the local dataset, then puts each under the preset's
``train/``: a finished one with done.json naming the local checkpoint (``vitfly reproduce`` skips it as done),
an unfinished one with its ``unfinished.json`` and never a done.json (``vitfly reproduce`` would resume it on
this machine); a run that came back without best.ckpt keeps the one here. A run that has a done.json here is
left alone. ``status`` lists every run of the preset (done, unfinished k/N epochs, not started) and the next
slot (``scripts/gpu_plan.py``): the unfinished runs it carries, lean (last.ckpt alone, bf16 moments where fp32
ones do not fit), within what the working tree leaves of 64 MiB, and the runs it starts, while what comes home
still fits the next carry; then the follow-on call for the warm machine and, where every run of the slot could
finish in the first call, the follow-on that starts the next runs instead; ``carry`` keeps every run that
trained here in ``carry/<preset>/`` (``scripts/gpu_carry.py``), ``restore`` puts them back.
A finished run returns without ``last.ckpt``: a later change of its settings trains it again from the start.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from scripts.gpu_load import CardLoad  # noqa: E402
from scripts.gpu_mps import SharedCard  # noqa: E402
from scripts.gpu_preset import flies_best, load_cfg, local_data_hash, parse_label, run_dir  # noqa: E402

SLOT_ENDED_RC = 3  # train-one's exit status when the slot ended before the run did
SLOT_EPOCHS = "slot_epochs.json"  # train-one's measured epoch lengths (s) this slot; not carried home
REPORT = "gpu_reproduce.json"  # what happened to each run, and the manifest of runs.tar.NNN


def log(msg: str) -> None:
    print(f"[gpu-reproduce {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def device_name() -> str:
    import torch

    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"


# -- there: one run (a child process of `train`) ----------------------------------------------------------------


def train_one(args: argparse.Namespace) -> int:
    """One run, exactly as ``vitfly reproduce``'s train stage trains it, ended early when the slot ends."""
    from scripts.gpu_slots import SlotEnded, SlotStop
    from vitfly.atomic import write_text
    from vitfly.training.fit import BestCheckpointMissing
    from vitfly.workflows.pipeline import stage_train, train_settings
    from vitfly.workflows.reproduce import _add_cost, _fit_seconds
    from vitfly.workflows.reproduce_config import train_callbacks, train_stage

    cfg = load_cfg(args)
    run = parse_label(args.train_one)
    stage, callbacks = train_callbacks(train_stage(cfg, run.model, run.use_state, seed=run.seed), cfg,
                                       "reproduce config")
    slot = SlotStop(args.stop_at, args.stop_after_epochs, args.epoch_s)
    train_dir = cfg.train_dir(*run)
    fit_before_s = _fit_seconds(train_dir)
    t0 = time.perf_counter()
    try:
        try:
            stage_train(stage, cfg.data, train_dir, args.threads, progress=False, callbacks=[*callbacks, slot])
        except SlotEnded as stop:  # stage_train writes no done.json: the run is unfinished
            print(f"[train] {args.train_one}: slot ended after {slot.trained} epochs here: {stop}", flush=True)
            _add_cost(train_dir, time.perf_counter() - t0, fit_before_s)
            return SLOT_ENDED_RC
        except BestCheckpointMissing as missing:  # carried lean: its best epoch is at home, none here beat it
            write_text(train_dir / "done.json", json.dumps({"checkpoint": str(missing.path),
                                                            "train": train_settings(stage, cfg.data)}) + "\n")
            print(f"[train] {args.train_one}: finished; its best epoch is the one at home", flush=True)
        _add_cost(train_dir, time.perf_counter() - t0, fit_before_s)
        return 0
    finally:  # the epochs this slot measured, for the next slot's plan (stage_run reads them)
        if train_dir.exists():
            write_text(train_dir / SLOT_EPOCHS, json.dumps([round(s, 1) for s in slot.measured]) + "\n")


# -- there: packing for the trip back ---------------------------------------------------------------------------


def slim_checkpoint(src: Path, dst: Path) -> dict:
    """``slim(src)`` saved as ``dst``; returns its epoch and step."""
    import torch

    from scripts.gpu_slots import slim

    obj = slim(src)
    torch.save(obj, dst)
    return {"epoch": int(obj.get("epoch", -1)), "global_step": int(obj.get("global_step", -1))}


def stage_finished(d: Path, dst: Path, slots: list[dict], data_hash: str, best_epoch: int | None = None) -> dict:
    """A finished run as it travels: slim best checkpoint and done.json naming it (made absolute by unpack). A run
    carried without its best.ckpt whose best epoch (``best_epoch``) came before this slot travels without one:
    unpack keeps the one at home."""
    import torch

    from scripts.gpu_slots import copy_run_files

    (dst / "checkpoints").mkdir(parents=True)
    done = json.loads((d / "done.json").read_text())
    if Path(done["checkpoint"]).exists():
        best_epoch = slim_checkpoint(Path(done["checkpoint"]), dst / "checkpoints" / "best.ckpt")["epoch"] + 1
    last = torch.load(d / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True, mmap=True)
    done["checkpoint"] = "checkpoints/best.ckpt"
    done["trained_on"] = {"device": " + ".join(dict.fromkeys(s["device"] for s in slots)), "weights": "fp16",
                          "best_epoch": best_epoch, "epochs": int(last.get("epoch", -1)) + 1,
                          "steps": int(last.get("global_step", -1)), "dataset_hash": data_hash, "slots": slots}
    (dst / "done.json").write_text(json.dumps(done) + "\n")
    copy_run_files(d, dst, None)
    squeeze_checkpoints(dst)
    return done["trained_on"]


def stage_unfinished(d: Path, dst: Path, marker: dict, moments: str) -> None:
    """An unfinished run as it travels: its resume state (``scripts/gpu_slots.py``) and ``unfinished.json``."""
    import torch

    from scripts.gpu_slots import MARKER, compact_moments, copy_run_files, save_atomic

    (dst / "checkpoints").mkdir(parents=True)
    last = torch.load(d / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    save_atomic(compact_moments(last, moments), dst / "checkpoints" / "last.ckpt")
    if (d / "checkpoints" / "best.ckpt").exists():
        best = slim_checkpoint(d / "checkpoints" / "best.ckpt", dst / "checkpoints" / "best.ckpt")
        marker["best_epoch"] = best["epoch"] + 1
    (dst / MARKER).write_text(json.dumps(marker) + "\n")
    copy_run_files(d, dst, marker["epochs"])
    squeeze_checkpoints(dst)


def squeeze_checkpoints(dst: Path) -> None:
    """A staged run's checkpoints squeezed for the trip back (``scripts/gpu_squeeze.py``: lossless, 0.74-0.83 of
    the bytes); ``unpack`` reads them back first."""
    from scripts.gpu_squeeze import squeeze_file

    for ckpt in sorted((dst / "checkpoints").glob("*.ckpt")):
        squeeze_file(ckpt)


def lighten_to_fit(staged: list[tuple[str, Path]], report: dict, budget: int) -> None:
    """While the staged folders exceed the trip back, unfinished runs with fp32 Adam moments (the largest first,
    so that fewest runs lose exactness) are re-staged with bf16 moments: a resume that is no longer exact,
    rather than a slot's work lost."""
    import torch

    from scripts.gpu_pack import HEADER_BYTES
    from scripts.gpu_slots import MARKER, compact_moments, save_atomic, tree_bytes
    from scripts.gpu_squeeze import SUFFIX, read_plain, squeeze_file

    for label, folder in sorted(staged, key=lambda s: -tree_bytes(s[1])):
        if sum(tree_bytes(f) + HEADER_BYTES for _, f in staged) <= budget:
            return
        marker = json.loads((folder / MARKER).read_text()) if (folder / MARKER).exists() else None
        if marker is None or marker["moments"] == "bf16":  # finished, or already light
            continue
        squeezed_last = folder / "checkpoints" / f"last.ckpt{SUFFIX}"
        state = torch.load(io.BytesIO(read_plain(squeezed_last)), map_location="cpu", weights_only=True)
        last = squeezed_last.with_name("last.ckpt")
        save_atomic(compact_moments(state, "bf16"), last)
        squeeze_file(last)  # replaces the fp32 one
        (folder / MARKER).write_text(json.dumps({**marker, "moments": "bf16"}) + "\n")
        report["runs"][label].update(moments="bf16", note="Adam moments sent in bf16 to fit the trip back "
                                     "(the resume is no longer exact)")
        log(f"{label}: Adam moments in bf16 to fit the trip back ({tree_bytes(folder) / 2**20:.1f} MiB now)")


def pack(staged: list[tuple[str, Path]], out: Path, work: Path, budget: int) -> dict:
    """The staged run folders, in order, into ``out/runs.tar.NNN`` while they fit ``budget`` bytes; returns the
    manifest (``scripts/gpu_pack.py``: what was packed, what was left out, the pieces)."""
    from scripts.gpu_pack import pack as pack_pieces

    return pack_pieces(staged, out, "runs", work, budget)


# -- there: the slot --------------------------------------------------------------------------------------------


def resume_sources(paths: list[str], preset: str) -> dict[str, tuple[Path, dict]]:
    """label -> (run folder, its unfinished.json) for each ``--resume-from`` folder: a run folder, or a folder
    of run folders (those with a done.json are finished: they are not resumed). A run found in several goes on
    from the state with the most epochs (on a tie, the folder named last): a follow-on call's own run folder
    beside the carry it started from."""
    from scripts.gpu_slots import MARKER, read_marker

    found: dict[str, tuple[Path, dict]] = {}
    for p in map(Path, paths):
        if not p.is_dir():
            raise SystemExit(f"--resume-from {p}: no such folder")
        folders = [p] if (p / MARKER).exists() or (p / "done.json").exists() else sorted(q for q in p.iterdir()
                                                                                       if (q / MARKER).exists())
        if not folders:
            raise SystemExit(f"--resume-from {p}: no {MARKER}; expected a run folder that unpack left unfinished")
        for folder in folders:
            if (folder / "done.json").exists():
                log(f"{folder}: finished (done.json); not resumed")
                continue
            marker = read_marker(folder)
            if marker["preset"] != preset:
                raise SystemExit(f"{folder / MARKER}: preset {marker['preset']!r}, not --preset {preset!r}")
            parse_label(marker["label"])
            label = marker["label"]
            if label in found and found[label][1]["epochs"] > marker["epochs"]:
                log(f"{folder}: {label} at {marker['epochs']} epochs; goes on from {found[label][0]} "
                    f"({found[label][1]['epochs']} epochs)")
                continue
            found[label] = (folder, marker)
    return found


def place_resumed(cfg, resumed: dict[str, tuple[Path, dict]]) -> None:
    """Each resumed run into the preset's train dir here (a carried one made a run folder again), its callbacks
    pointed there, its metrics set aside."""
    from scripts.gpu_carry import is_carried, materialize
    from scripts.gpu_slots import copy_run, epochs_done, relocate_file, set_metrics_aside

    for label, (src, marker) in resumed.items():
        dst = run_dir(cfg, label)
        copy_run(src, dst)
        if is_carried(dst):
            materialize(dst)
        else:
            relocate_file(dst / "checkpoints" / "last.ckpt")
        set_metrics_aside(dst)
        marker["epochs"] = epochs_done(dst)  # the checkpoint's, should a resume at home have gone on since


def collect_data(cfg, args, report: dict) -> str | None:
    """The preset's dataset, fingerprinted; None (and the report says why) if its hash is not the expected one."""
    from vitfly.datamodules.provenance import dataset_fingerprint
    from vitfly.workflows.pipeline import stage_collect

    t0 = time.monotonic()
    stage_collect(cfg.collect_config, {**cfg.collect, "workers": args.collect_workers}, cfg.data, progress=False)
    report["data"] = {**dataset_fingerprint(cfg.data), "collect_s": round(time.monotonic() - t0, 1)}
    log(f"data {cfg.data}: {report['data']}")
    data_hash = report["data"]["dataset_hash"]
    if args.expect_data_hash and data_hash != args.expect_data_hash:
        report["error"] = f"dataset_hash {data_hash} != expected {args.expect_data_hash}"
        return None
    return data_hash


def wrong_data(resumed: dict[str, tuple[Path, dict]], data_hash: str) -> str | None:
    for label, (folder, marker) in resumed.items():
        if marker["dataset_hash"] != data_hash:
            return (f"{folder}: {label} was trained on dataset_hash {marker['dataset_hash']}, "
                    f"not this slot's {data_hash}; not resumed")
    return None


def start_runs(args, labels: list[str], resumed: dict, stop_at: float, work: Path) -> dict:
    procs = {}
    for label in labels:
        cmd = [sys.executable, str(ROOT / "scripts" / "gpu.py"), "train-one", "--config", args.config,
               "--preset", args.preset, "--threads", str(args.threads), "--stop-at", str(stop_at), label]
        cmd += ["--run-dir", args.run_dir] if args.run_dir else []
        cmd += ["--data", args.data] if args.data else []
        cmd += ["--stop-after-epochs", str(args.stop_after_epochs)] if args.stop_after_epochs is not None else []
        marker = resumed[label][1] if label in resumed else {}
        hint = marker.get("first_epoch_s") or marker.get("epoch_s")  # the slot's first epoch compiles again
        cmd += ["--epoch-s", str(hint)] if hint else []
        with open(work / f"{label}.log", "w") as logfile:  # the child writes through its own copy
            procs[label] = (subprocess.Popen(cmd, stdout=logfile, stderr=subprocess.STDOUT, cwd=ROOT,
                                             start_new_session=True), time.monotonic())
    return procs


def wait_runs(procs: dict, deadline: float) -> dict[str, tuple[int | None, float]]:
    """label -> (exit status, or None if killed at ``deadline``; wall seconds)."""
    ended: dict[str, tuple[int | None, float]] = {}
    while True:
        for label, (p, t0) in procs.items():
            if label not in ended and p.poll() is not None:
                ended[label] = (p.returncode, time.monotonic() - t0)
        if len(ended) == len(procs) or time.monotonic() >= deadline:
            break
        time.sleep(0.2)
    for label, (p, t0) in procs.items():
        if label not in ended:  # mid-epoch: its last.ckpt (written atomically) holds the epoch before
            os.killpg(p.pid, 9)
            p.wait()
            ended[label] = (None, time.monotonic() - t0)
    return ended


def stage_run(cfg, label: str, ended: tuple, resumed: dict, data_hash: str, args,
              work: Path) -> tuple[dict, Path | None]:
    """What one run did this slot (the report's entry), and its folder staged for the trip back (or None)."""
    from scripts.gpu_slots import MARKER, epochs_done, steady_epoch_s
    from vitfly.atomic import write_text
    from vitfly.workflows.reproduce import _fit_seconds
    from vitfly.workflows.reproduce_config import train_stage

    d = run_dir(cfg, label)
    rc, wall_s = ended
    marker = resumed[label][1] if label in resumed else {"label": label, "preset": args.preset, "slots": []}
    before, after = (marker.get("epochs", 0), epochs_done(d))
    # fit_s: the Timer's fitting seconds at the slot's end, where a CPU session that goes on from it counts from
    slot = {"device": device_name(), "epochs": [before, after], "wall_s": round(wall_s, 1),
            "fit_s": round(_fit_seconds(d), 1)}
    if label in resumed:  # an exact resume (fp32) or not (bf16)
        slot["moments_in"] = marker.get("carried_moments", marker.get("moments", "fp32"))
    entry = {"rc": rc, "epochs": [before, after], "wall_s": slot["wall_s"]}
    dst = work / "stage" / label
    if (d / "done.json").exists():
        entry["state"] = "finished"
        stage_finished(d, dst, [*marker["slots"], slot], data_hash, marker.get("best_epoch"))
        return entry, dst
    if after <= before:
        entry.update(state="no progress", note="no epoch finished this slot; nothing returned")
        return entry, None
    measured = json.loads((d / SLOT_EPOCHS).read_text()) if (d / SLOT_EPOCHS).exists() else []
    epoch_s = wall_s / (after - before)  # start-up included: errs long, so the next slot stops in time
    steady = {"epoch_s": round(steady_epoch_s(measured), 1), "first_epoch_s": round(measured[0], 1)} if measured \
        else {"epoch_s": round(epoch_s, 1)}
    run = parse_label(label)
    max_epochs = train_stage(cfg, run.model, run.use_state, seed=run.seed).max_epochs
    marker = {**{k: v for k, v in marker.items() if k != "carried_moments"}, "epochs": after, "max_epochs": max_epochs,
              "dataset_hash": data_hash, "moments": args.moments, **steady, "slots": [*marker["slots"], slot]}
    entry.update(state="unfinished", max_epochs=marker["max_epochs"])
    stage_unfinished(d, dst, marker, args.moments)
    # the run folder here says so too: a follow-on call on this machine (--go-on) resumes it from its full state
    write_text(d / MARKER, json.dumps({**marker, "moments": "fp32"}, indent=1) + "\n")
    return entry, dst


def runs_to_train(cfg, labels: list[str], report: dict) -> list[str]:
    """The labels without a done.json here (a finished run is never trained again)."""
    todo = []
    for label in labels:
        if (run_dir(cfg, label) / "done.json").exists():
            report["runs"][label] = {"state": "done before", "note": "finished (done.json): not retrained"}
            log(f"{label}: finished before (done.json); not retrained, not returned")
        else:
            todo.append(label)
    return todo


def return_runs(cfg, args, todo: list[str], ended: dict, resumed: dict, data_hash: str, report: dict,
                start: float) -> int:
    """Stage what each run did, pack what fits for the trip back, write the report; 0 if every run came back."""
    out, work = Path(args.out), Path(args.work)
    staged = []
    for label in todo:
        entry, folder = stage_run(cfg, label, ended[label], resumed, data_hash, args, work)
        report["runs"][label] = entry
        staged += [(label, folder)] if folder else []
        log(f"{label}: {entry}; log tail: "
            + " | ".join((work / f"{label}.log").read_text().strip().splitlines()[-2:]))
    staged.sort(key=lambda s: report["runs"][s[0]]["state"] != "finished")  # finished runs first
    lighten_to_fit(staged, report, int(args.return_mib * 2**20))
    report["pack"] = pack(staged, out, work, int(args.return_mib * 2**20))
    packed = [c["name"] for c in report["pack"]["contents"]]
    for label in packed:
        report["runs"][label]["packed"] = True
    for label in report["pack"]["left_out"]:
        report["runs"][label]["note"] = f"not returned: the trip back holds {args.return_mib} MiB"
    report["elapsed_s"] = round(time.monotonic() - start, 1)
    (out / REPORT).write_text(json.dumps(report, indent=1) + "\n")
    log(f"packed {len(packed)}/{len(todo)} runs in {report['elapsed_s']} s")
    return 0 if len(packed) == len(todo) else 1


def train(args: argparse.Namespace) -> int:
    start = time.monotonic()
    out, work = Path(args.out), Path(args.work)
    out.mkdir(parents=True, exist_ok=True)
    for stale in [*out.glob("runs.tar.[0-9][0-9][0-9]"), out / REPORT]:
        stale.unlink(missing_ok=True)  # unpack joins every piece it finds
    shutil.rmtree(work / "stage", ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    cfg = load_cfg(args)
    sources = list(args.resume_from)
    here = cfg.out_dir / "train"  # an earlier call's runs, on a machine still warm from it
    if args.go_on and here.is_dir():
        sources.append(str(here))  # named last: it wins a tie with the carry
    elif args.go_on:
        log(f"--go-on: no earlier call's runs in {here} (a fresh machine); resumes from --resume-from alone")
    resumed = resume_sources(sources, args.preset)
    for label in [k for k in resumed if parse_label(k).model in cfg.train.cpu_models and k not in args.runs]:
        log(f"{label}: trains on a CPU (train.cpu_models); not resumed here (name it in --runs to)")
        del resumed[label]
    labels = list(dict.fromkeys([*args.runs, *resumed]))
    if not labels:
        raise SystemExit("train: nothing to train; name runs with --runs or resume states with --resume-from")
    from vitfly.workflows.reproduce_config import runs

    known = {r.dir_name for r in runs(cfg)}
    for label in labels:
        parse_label(label)
        if label not in known:
            raise SystemExit(f"train: {label} is not a run of the {args.preset} preset (train.models, "
                             f"train.nostate_models, train.draws); its runs: {', '.join(sorted(known))}")
    report: dict = {"preset": args.preset, "runs": {}, "resumed": {k: str(v[0]) for k, v in resumed.items()}}
    data_hash = collect_data(cfg, args, report)
    error = report.get("error") or (data_hash and wrong_data(resumed, data_hash))
    if error:
        report["error"] = error
        (out / REPORT).write_text(json.dumps(report, indent=1) + "\n")
        log(error + ": nothing trained")
        return 1
    resumed = {k: v for k, v in resumed.items() if not (run_dir(cfg, k) / "done.json").exists()}
    place_resumed(cfg, resumed)
    todo = runs_to_train(cfg, labels, report)
    deadline = start + args.deadline_s - args.reserve_s
    with SharedCard(len(todo), wanted=not args.no_mps, memo=work / "mps_check.json") as card:
        report["mps"] = card.info
        log(f"mps: {card.info}")
        with CardLoad(work / "card_load.csv") as load:  # how busy the runs kept the card, for the next plan
            procs = start_runs(args, todo, resumed, time.time() + deadline - time.monotonic(), work)
            ended = wait_runs(procs, deadline)
    report["card_load"] = load.summary()
    log(f"card load: { {k: v for k, v in report['card_load'].items() if k != 'utilization_samples'} }")
    return return_runs(cfg, args, todo, ended, resumed, data_hash, report, start)


# -- here: unpacking and planning -------------------------------------------------------------------------------


def extract_returned(src: Path, tmp: Path) -> None:
    """The returned runs, joined from their pieces, checked against the report's manifest and unpacked (safely)
    into the scratch folder ``tmp``."""
    from scripts.gpu_pack import fresh_dir, unpack
    from scripts.gpu_squeeze import unsqueeze_tree

    unpack(src, "runs", fresh_dir(tmp), REPORT)
    unsqueeze_tree(tmp)  # the checkpoints travel squeezed (a report from before they did: nothing to do)


def keep_best_at_home(run: Path, dst: Path) -> None:
    """A run carried lean (``scripts/gpu.py carry``) comes back without best.ckpt when no epoch of the slot beat
    the best one here: that one moves into the returned folder (a preset that flies the last epoch has none)."""
    best, home = run / "checkpoints" / "best.ckpt", dst / "checkpoints" / "best.ckpt"
    if not best.exists() and home.exists():
        shutil.move(str(home), best)


def place_finished(run: Path, dst: Path) -> None:
    keep_best_at_home(run, dst)
    if dst.exists():  # an unfinished attempt (here or from a slot): the finished run replaces it
        print(f"{dst}: unfinished here; replaced by the returned finished run")
        shutil.rmtree(dst)
    shutil.move(str(run), dst)
    done = json.loads((dst / "done.json").read_text())
    done["checkpoint"] = str((dst / done["checkpoint"]).resolve())
    (dst / "done.json").write_text(json.dumps(done) + "\n")
    print(f"{dst}: done; {done['trained_on']['epochs']} epochs on {done['trained_on']['device']}")


def place_unfinished(run: Path, dst: Path) -> None:
    from scripts.gpu_slots import MARKER, epochs_done, relocate_file

    marker = json.loads((run / MARKER).read_text())
    here = epochs_done(dst)
    if here >= marker["epochs"]:
        print(f"{dst}: already {here} epochs here; the returned state ({marker['epochs']} epochs) left out")
        return
    keep_best_at_home(run, dst)
    if dst.exists():
        shutil.rmtree(dst)
    shutil.move(str(run), dst)
    relocate_file(dst / "checkpoints" / "last.ckpt")  # a resume here (vitfly reproduce) or in the next slot
    print(f"{dst}: unfinished, {progress(marker)}")


def slots_left(marker: dict) -> str:
    """``; about N more slots`` of a default slot's training time at the last slot's epoch times."""
    from scripts.gpu_plan import STARTUP_S, epochs_per_slot

    left = marker.get("max_epochs", 0) - marker["epochs"]
    per_slot = epochs_per_slot(marker, DEADLINE_S - RESERVE_S - STARTUP_S)
    if per_slot is None or left <= 0:
        return ""
    per_slot = max(1, per_slot)
    slots = -(-left // per_slot)
    return f"; about {slots} more slot{'s' * (slots != 1)} of {per_slot} epochs"


def progress(marker: dict) -> str:
    minutes = sum(s["wall_s"] for s in marker["slots"]) / 60
    devices = " + ".join(dict.fromkeys(s["device"] for s in marker["slots"]))
    return f"{marker['epochs']}/{marker.get('max_epochs', '?')} epochs, {minutes:.1f} min on {devices}"


def checked_runs(tmp: Path, src: Path, cfg, local: str) -> list[Path]:
    """The returned run folders, every one checked (label, data hash against ``local``, no live training here)
    before any is placed."""
    from scripts.gpu_slots import returned_hash
    from vitfly.training.run_lock import training_now, who_holds

    runs = sorted(p for p in tmp.iterdir() if p.is_dir())
    for run in runs:
        label = parse_label(run.name)
        holder = training_now(run_dir(cfg, run.name))
        if holder is not None:  # placing would pull the folder from under that process
            raise SystemExit(f"{src}: {run.name} is training here now ({who_holds(holder)}); stop it (it resumes "
                             "from its last checkpoint) or let it end, then unpack again; nothing unpacked")
        if returned_hash(run) != local:
            raise SystemExit(f"{src}: {run.name} was trained on dataset_hash {returned_hash(run)}; the local "
                             f"{cfg.data} has {local}; nothing unpacked")
        home = run_dir(cfg, run.name) / "checkpoints" / "best.ckpt"
        if flies_best(cfg, label) and not (run / "checkpoints" / "best.ckpt").exists() and not home.exists():
            raise SystemExit(f"{src}: {run.name} came back without best.ckpt (its best epoch is the one at home, "
                             f"carried lean), but {home} is missing; nothing unpacked")
    return runs


def unpack(args: argparse.Namespace) -> int:
    cfg = load_cfg(args)
    src = Path(args.dir)
    local = local_data_hash(cfg)
    tmp = cfg.out_dir / "train" / ".gpu_unpack"
    try:
        extract_returned(src, tmp)
        for run in checked_runs(tmp, src, cfg, local):
            dst = run_dir(cfg, run.name)
            if (dst / "done.json").exists():
                print(f"{dst}: has a done.json; left alone")
            elif (run / "done.json").exists():
                place_finished(run, dst)
            else:
                place_unfinished(run, dst)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


def run_states(cfg) -> list:
    """Every run of the preset as it stands here (``scripts.gpu_plan.RunState``), in the preset's order."""
    from scripts.gpu_carry import caught_up
    from scripts.gpu_plan import RunState
    from scripts.gpu_slots import MARKER, epochs_done, tree_bytes
    from vitfly.training.run_lock import training_now, who_holds
    from vitfly.workflows.reproduce_config import runs, train_stage

    rows = []
    for run in runs(cfg):
        d = cfg.train_dir(*run)
        n = train_stage(cfg, run.model, run.use_state, seed=run.seed).max_epochs
        holder = training_now(d)  # a process here holds the run's lock (vitfly.training.run_lock)
        now = "" if holder is None else f", training here now ({who_holds(holder)})"
        if (d / "done.json").exists():
            on = json.loads((d / "done.json").read_text()).get("trained_on")
            rows.append(RunState(run, "done", "done" + (f" ({on['epochs']} epochs on {on['device']})" if on else ""),
                                 d))
        elif (d / MARKER).exists():
            # a restored run that vitfly reproduce took further here: those epochs as one more CPU slot
            marker = caught_up({**json.loads((d / MARKER).read_text()), "max_epochs": n}, d)
            rows.append(RunState(run, "unfinished", f"unfinished: {progress(marker)}{slots_left(marker)}{now}", d,
                                 tree_bytes(d), marker, here_now=holder is not None))
        elif epochs_done(d):
            rows.append(RunState(run, "started here",
                                 f"started here: {epochs_done(d)}/{n} epochs (vitfly reproduce resumes it){now}", d))
        elif holder is not None:  # in its first epoch here: no slot may start it too
            rows.append(RunState(run, "started here", f"started here: no epoch ended yet{now}", d))
        else:  # a folder without an epoch: one stopped before its first epoch's end
            rows.append(RunState(run, "not started", "not started" + (" (its folder exists: no epoch ended yet)"
                                                                      if d.is_dir() else "")))
    return rows


def status(args: argparse.Namespace) -> int:
    """Every run of the preset and the next slot; with ``carry`` (``args.write_carry``), every run that trained here
    written into ``carry/<preset>/`` too (``scripts/gpu_carry.py``), the slot's with the moments it plans."""
    from scripts.gpu_carry import other_carries, preset_carry, write_carry
    from scripts.gpu_plan import next_slot, slot_after
    from scripts.gpu_slots import CARRY_BYTES, mib, travelling_bytes, tree_bytes, wheels_reserve
    from scripts.gpu_travel import is_light, light_bytes

    cfg = load_cfg(args)
    rows = run_states(cfg)
    carry_dir = preset_carry(args.carry_dir, cfg.preset)
    # a new checkout before `restore`: its kept runs look new here, and a slot would train them again from scratch
    kept = {r.label for r in rows if r.state == "not started" and (carry_dir / r.label).is_dir()}
    here = carry_dir.relative_to(ROOT) if carry_dir.is_relative_to(ROOT) else carry_dir
    unrestored = f"{here} keeps {len(kept)} run{'s' * (len(kept) != 1)}"
    width = max(len(r.label) for r in rows)
    for r in rows:
        text = f"kept in {here / r.label}, not restored here" if r.label in kept else r.text
        print(f"{r.label:<{width}}  {text}" + (f" ({mib(r.size)} here)" if r.size else ""))
    if kept and not getattr(args, "write_carry", False):  # `carry` leaves kept runs as they are: no harm to write
        raise SystemExit(f"status: {unrestored} that {cfg.out}/train lacks, "
                         f"so no slot can be planned; first: python3 scripts/gpu.py restore --preset {cfg.preset}")
    # as the call travels: light (scripts/gpu_travel.py), the shipped weights, the docs, the other presets' carries
    # and the carried runs of no slot left here; the room is what the code and .whl/ leave of the call's 64 MiB
    light = is_light(ROOT)
    others = [p for p in other_carries(carry_dir) if p.resolve().is_relative_to(ROOT)]
    tree = travelling_bytes(ROOT, leave_out=[carry_dir, *others]) - (0 if light else light_bytes(ROOT))
    if light:
        print("  travelling light now (weights/ and docs/ out of git's index, commits refused): once the device "
              "call is done, python3 scripts/gpu.py travel full")
    reserve = wheels_reserve(ROOT)  # every call carries the wheels: their room is planned before they are fetched
    if reserve:
        tree += reserve
        print(f"  no .whl/ here yet: {mib(reserve)} kept for it (python3 scripts/gpu.py wheels)")
    room = CARRY_BYTES - tree
    # a run training here now goes on here: a slot takes what nothing here trains (stop it to send it to the card)
    planned = [r for r in rows if (r.run.model not in cfg.train.cpu_models or r.state == "not started")
               and not r.here_now]
    busy = [r.label for r in rows if r.here_now and r.run.model not in cfg.train.cpu_models]
    if busy:
        print(f"  training here now, so in no slot: {', '.join(busy)} (stop them first to send them to the card)")
    slot = next_slot(cfg, planned, room, args.carry_moments, args.deadline_s, args.reserve_s)
    print(f"next slot carries {len(slot.carry)} unfinished runs, {mib(sum(slot.sizes.values()))} of the "
          f"{mib(room)} a call leaves beside the working tree travelling light and .whl/ ({mib(tree)})"
          + (f"; {', '.join(slot.no_room)} wait for a later slot (no room)" if slot.no_room else ""))
    for r in slot.carry:
        print(f"  carries: {r.label:<{width}}  last.* with {slot.moments[r.label]} moments")
    if slot.start:
        print(f"  starts: {', '.join(r.label for r in slot.start)}"
              + (f" ({slot.alone})" if slot.alone else f"; resume states expected home: at most "
                 f"{mib(slot.back_bytes)} of the next call's {mib(room)}"))
    for label, why in slot.wait.items():
        print(f"  waits: {label:<{width}}  {why}")
    if slot.on_cpu:
        models = " ".join(dict.fromkeys(r.run.model for r in slot.on_cpu))
        two = len(slot.on_cpu) > 1  # one-trajectory steps use one core well: two processes train two runs at once
        print(f"  on a CPU (train.cpu_models): {', '.join(r.label for r in slot.on_cpu)}: vitfly reproduce "
              f"--config {args.config} --preset {cfg.preset} --models {models} --stages train"
              + (" --threads 1, twice side by side (each takes a run the other is not on)" if two else ""))
    if all(r.state == "done" for r in rows):
        print(f"  every run is done: vitfly reproduce --config {args.config} --preset {cfg.preset} flies them")
    # a carry in this checkout is committed with the session's other commits: what they weigh, once
    committed_here = carry_dir.resolve().is_relative_to(ROOT)
    weighed = None
    if getattr(args, "write_carry", False):
        write_carry(cfg, rows, slot, carry_dir, room)
        if committed_here:
            from scripts.gpu_history import report

            weighed = report(ROOT)
    if kept:
        print(f"  no slot planned: {unrestored} not restored here "
              f"(python3 scripts/gpu.py restore --preset {cfg.preset})")
        return 0
    if not (slot.carry or slot.start):
        return 0
    if slot.carry and not getattr(args, "write_carry", False):
        print(f"  first, here: python3 scripts/gpu.py carry --preset {cfg.preset} (into {here}/; the call sends it "
              "uncommitted: commit the carry once, when the slot is home)")
    data_hash = local_data_hash(cfg) if Path(cfg.data).exists() else "HASH"
    deadline = [f"--deadline-s {args.deadline_s:g}"] if args.deadline_s != DEADLINE_S else []
    flags = [f"--reserve-s {args.reserve_s:g}"] if args.reserve_s != RESERVE_S else []
    flags += [f"--moments {args.moments}"] if args.moments != "fp32" else []
    # every carried run but the slot's stays here: no room taken, and `train --resume-from` does not resume it
    travelling = {r.label for r in slot.carry}
    carried_here = [r for r in rows if (carry_dir / r.label).exists() or (r.folder is not None and (
        r.state == "done" or r.run.model in cfg.train.cpu_models))]  # in carry/, or once `carry` has run
    stay = [(carry_dir / r.label).relative_to(ROOT).as_posix() for r in carried_here
            if r.label not in travelling and (carry_dir / r.label).resolve().is_relative_to(ROOT)]
    stay += [p.resolve().relative_to(ROOT).as_posix() for p in others]
    print("  then, right before the call (weights/, docs/ and the carried runs of no slot stay here; right after "
          "it: python3 scripts/gpu.py travel full):\n    python3 scripts/gpu.py travel light"
          + (f" --leave {' '.join(stay)}" if stay else ""))
    base = f"python3 scripts/gpu.py train --preset {cfg.preset} --out $OUT --expect-data-hash {data_hash}"
    command = (base + (f" --resume-from {here}" if slot.carry else "")
               + (f" --runs {' '.join(r.label for r in slot.start)}" if slot.start else "")
               + "".join(" " + f for f in flags))
    print(f"  carry: {json.dumps(['.whl'])} ({here}/ travels with the working tree)\n  command: {command}"
          + "".join(" " + f for f in deadline))
    print("  then at once, while the machine is warm (30 s), a follow-on call for what the lease has left "
          "(timeout_s T: its budget_left_s less 30 s), resuming the runs where the first call left them there:"
          f"\n    {command} --go-on --deadline-s $((T - 10 - SECONDS))")
    if committed_here:  # and the slot's carry, home again, joins them
        from scripts.gpu_history import slot_outlook

        slot_outlook(ROOT, sum(tree_bytes(carry_dir / r.label) for r in slot.carry if (carry_dir / r.label).exists()),
                     slot.back_bytes, weighed)
    after = slot_after(cfg, planned, slot, room, args.carry_moments, args.deadline_s, args.reserve_s)
    if after is not None:  # a finished run is not trained again: the follow-on would have nothing to do
        print("  or, if the first call's report says every run finished, a follow-on that starts the next:\n    "
              f"{base} --runs {' '.join(r.label for r in after.start)}" + "".join(" " + f for f in flags)
              + " --go-on --deadline-s $((T - 10 - SECONDS))")
    return 0


def add_commands(sub) -> dict:
    """``train``, ``train-one`` and ``status`` on ``scripts/gpu.py``'s subparsers; returns name -> handler
    (``unpack`` takes the preset flags too: its runs are the pieces ``runs.tar.NNN``)."""
    for name in ("train", "train-one", "status", "carry", "restore"):
        preset_flags(sub.add_parser(name, help=COMMAND_HELP[name]), required=True)
    t = sub.choices["train"]
    t.add_argument("--out", required=True, help="what comes back: runs.tar.NNN and gpu_reproduce.json")
    t.add_argument("--work", default="/tmp/vitfly-gpu-reproduce", help="logs and packing")
    t.add_argument("--runs", nargs="*", default=[], help="MODEL-state / MODEL-nostate labels")
    t.add_argument("--resume-from", nargs="*", default=[], metavar="DIR",
                   help="unfinished run folders (as unpack leaves them, carried here), or folders of them")
    t.add_argument("--go-on", action="store_true",
                   help="a follow-on call on a machine still warm from the last: resume its runs from their run "
                        "folders there too, where they trained further than --resume-from's states")
    t.add_argument("--expect-data-hash", help="the dataset_hash the collected file must have")
    t.add_argument("--collect-workers", type=int, default=14)
    t.add_argument("--threads", type=int, default=2, help="torch threads per run")
    t.add_argument("--stop-after-epochs", type=int, help="epochs each run trains in this slot at most")
    t.add_argument("--no-mps", action="store_true",
                   help="runs take turns on the card even where NVIDIA's MPS daemon could let them share it")
    for p in (t, sub.choices["status"], sub.choices["carry"]):  # status plans the slot train runs with them
        p.add_argument("--deadline-s", type=float, default=DEADLINE_S, help="the whole command, from its start")
        p.add_argument("--reserve-s", type=float, default=RESERVE_S, help="left after training for packing")
        p.add_argument("--moments", choices=["fp32", "bf16"], default="fp32",
                       help="Adam moments of the unfinished runs sent home (bf16: half their bytes, an inexact resume)")
    for p in (sub.choices["status"], sub.choices["carry"]):
        p.add_argument("--carry-moments", choices=["auto", "fp32", "bf16"], default="auto",
                       help="Adam moments of the carried runs (auto: fp32 where they fit beside the working tree)")
    for p in (sub.choices["status"], sub.choices["carry"], sub.choices["restore"]):
        p.add_argument("--carry-dir", default=CARRY_DIR,
                       help="the runs kept in the repository, one folder per preset (an absolute path: elsewhere)")
    sub.choices["carry"].set_defaults(write_carry=True)
    t.add_argument("--return-mib", type=float, default=60.0,
                   help="what the pieces may hold (the device tool returns 64 MiB in all, the report and logs too)")
    one = sub.choices["train-one"]
    one.add_argument("--threads", type=int, default=2)
    one.add_argument("--stop-at", type=float, help="Unix time by which the last epoch must have ended")
    one.add_argument("--stop-after-epochs", type=int)
    one.add_argument("--epoch-s", type=float, help="expected epoch length until one is measured")
    one.add_argument("train_one", metavar="LABEL")
    return {"train": train, "train-one": train_one, "status": status, "carry": status, "restore": restore}


def restore(args: argparse.Namespace) -> int:
    """``scripts/gpu_carry.py``'s restore, imported when it runs (it imports Lightning; the parser does not)."""
    from scripts.gpu_carry import restore as restore_carry

    return restore_carry(args)


DEADLINE_S, RESERVE_S = 560.0, 40.0  # a command may run 600 s
COMMAND_HELP = {"train": "there: collect a preset's data, train named runs until the deadline, pack them",
                "train-one": "there: one run (a child process of train)",
                "status": "here: every run of a preset, and the next slot: what it carries and starts",
                "carry": "here: status, and every run that trained here into carry/PRESET/ (commit it)",
                "restore": "here: carry/PRESET/ back into the preset's train/ (a new checkout goes on from it)"}
CARRY_DIR = "carry"  # carry/<preset>/: the runs kept in the repository (scripts/gpu_carry.py)


def preset_flags(p: argparse.ArgumentParser, required: bool) -> None:
    p.add_argument("--config", default="configs/reproduce.yaml")
    p.add_argument("--preset", required=required)
    p.add_argument("--run-dir", help="the preset's run directory (vitfly reproduce --out)")
    p.add_argument("--data", help="the preset's dataset (vitfly reproduce --data)")


def main(argv: list[str] | None = None) -> int:
    """The old command line: ``scripts/gpu_reproduce.py ARGS`` is ``scripts/gpu.py ARGS``.
    Handed over as a process: ``gpu.py`` imports this module, which so never imports it back."""
    args = sys.argv[1:] if argv is None else argv
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "gpu.py"), *args]).returncode


if __name__ == "__main__":
    sys.exit(main())
