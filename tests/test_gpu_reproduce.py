"""scripts/gpu_reproduce.py: runs of a reproduce preset trained in GPU slots, carried home, resumed, taken as done.

Here every end runs on the CPU with the tiny preset. A run finished in one slot comes home as done (fp16
network, no optimiser state). A run stopped after 1 of 2 epochs comes home unfinished with its optimiser state,
is resumed from a fresh directory in a second slot and ends with the weights and Adam moments of an
uninterrupted 2-epoch run, bit for bit; with bf16 moments it ends close to them. Resume states and returned
runs on other data are refused; finished runs are never trained again; ``status`` lists the runs and what the
next slot carries; runs outlive the session in carry/ and go on from there in a new checkout; unpacking refuses
unsafe archives on Pythons without tarfile's 'data' filter.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from types import SimpleNamespace

import h5py
import pytest
import torch
import yaml
from helpers import load_script
from test_run_lock import Holder

from vitfly.datamodules.provenance import dataset_fingerprint
from vitfly.errors import VitflyError
from vitfly.workflows.pipeline import TrainStage, check_trained_data, stage_collect, stage_train
from vitfly.workflows.reproduce_config import load_reproduce_config, train_callbacks, train_stage
from vitfly.workflows.reproduce_report import _training_table
from vitfly.zoo import load_network

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """The tiny preset's dataset, collected once for every test here."""
    path = tmp_path_factory.mktemp("data") / "tiny.h5"
    cfg = load_reproduce_config(REPO / "configs" / "reproduce.yaml", "tiny", {"data": str(path)})
    stage_collect(cfg.collect_config, cfg.collect, path, progress=False)
    return path


@pytest.fixture(scope="module")
def two_epochs(tmp_path_factory) -> Path:
    """configs/reproduce.yaml with the tiny preset trained for 2 epochs instead of 1."""
    config = yaml.safe_load((REPO / "configs" / "reproduce.yaml").read_text())
    config["presets"]["tiny"]["train"]["overrides"]["max_epochs"] = 2
    path = tmp_path_factory.mktemp("config") / "reproduce.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_runs_trained_elsewhere_come_back_as_done(tmp_path, data, capsys):
    gpu = load_script("gpu")  # the one entry point (gpu_reproduce.py hands over to it)
    run_dir, out = tmp_path / "run", tmp_path / "back"
    where = ["--preset", "tiny", "--run-dir", str(run_dir), "--data", str(data)]
    train = ["train", *where, "--out", str(out), "--work", str(tmp_path / "work"), "--collect-workers", "1",
             "--threads", "1", "--runs", "convnet-nostate"]

    assert gpu.main([*train, "--expect-data-hash", "0000000000000000"]) == 1
    assert "nothing trained" in capsys.readouterr().out
    assert "!= expected 0000000000000000" in json.loads((out / "gpu_reproduce.json").read_text())["error"]
    assert not (run_dir / "train").exists()

    data_hash = dataset_fingerprint(data)["dataset_hash"]
    assert gpu.main([*train, "--expect-data-hash", data_hash]) == 0
    report = json.loads((out / "gpu_reproduce.json").read_text())
    assert report["runs"]["convnet-nostate"]["state"] == "finished"
    assert report["runs"]["convnet-nostate"]["packed"] and report["runs"]["convnet-nostate"]["epochs"] == [0, 1]
    assert report["data"]["dataset_hash"] == data_hash
    assert report["mps"] == {"mps": False, "note": "one run: nothing to share the card with"}

    trained = run_dir / "train" / "convnet-nostate"
    original = load_network(trained / "checkpoints" / "best.ckpt")
    shutil.rmtree(trained)
    holder = Holder(trained)  # a training here on the same run: unpacking would pull its folder away
    try:
        with pytest.raises(SystemExit, match=rf"convnet-nostate is training here now \(pid {holder.proc.pid} on "
                           r".*, since .*\); stop it .* nothing unpacked"):
            gpu.main(["unpack", *where, str(out)])
    finally:
        holder.release()
    assert list(trained.iterdir()) == []  # nothing placed (the holder's folder is left, empty)
    assert gpu.main(["unpack", *where, str(out)]) == 0
    marker = json.loads((trained / "done.json").read_text())
    assert Path(marker["checkpoint"]) == (trained / "checkpoints" / "best.ckpt").resolve()
    assert marker["trained_on"]["epochs"] == 1 and marker["trained_on"]["steps"] == 2  # tiny: 1 epoch, 2 batches
    assert marker["trained_on"]["dataset_hash"] == data_hash
    assert not (trained / "checkpoints" / "last.ckpt").exists()
    saved = torch.load(marker["checkpoint"], map_location="cpu", weights_only=True)
    assert "optimizer_states" not in saved

    back = load_network(marker["checkpoint"])  # the weights, rounded to fp16 and nothing else
    for (name, a), b in zip(original.state_dict().items(), back.state_dict().values(), strict=True):
        expected = a.half().float() if a.is_floating_point() else a
        assert torch.equal(expected, b), name

    cfg = load_reproduce_config(REPO / "configs" / "reproduce.yaml", "tiny", {"out": str(run_dir), "data": str(data)})
    stage, callbacks = train_callbacks(train_stage(cfg, "convnet", False), cfg, "test")
    assert stage_train(stage, data, trained, 1, progress=False, callbacks=callbacks) == Path(marker["checkpoint"])
    assert not (trained / "checkpoints" / "last.ckpt").exists()  # taken as done, not trained again
    assert "| convnet-nostate | 1 | 2 |" in _training_table(cfg)

    capsys.readouterr()
    assert gpu.main(["unpack", *where, str(out)]) == 0 and "left alone" in capsys.readouterr().out


def other_data(data: Path, tmp_path: Path) -> Path:
    """``data`` with one attribute more: the same flights, another dataset hash."""
    other = tmp_path / "other.h5"
    shutil.copy(data, other)
    with h5py.File(other, "r+") as f:
        f.attrs["note"] = "another dataset"
    return other


def trained_state(path: Path) -> tuple[dict, dict]:
    """(weights, Adam state) of a Lightning checkpoint."""
    saved = torch.load(path, map_location="cpu", weights_only=True)
    return saved["state_dict"], saved["optimizer_states"][0]["state"]


def assert_same_training(a: Path, b: Path) -> None:
    (weights_a, adam_a), (weights_b, adam_b) = trained_state(a), trained_state(b)
    assert weights_a.keys() == weights_b.keys() and adam_a.keys() == adam_b.keys()
    for name, value in weights_a.items():
        assert torch.equal(value, weights_b[name]), name
    for i, state in adam_a.items():
        for key, value in state.items():
            assert value.dtype == adam_b[i][key].dtype and torch.equal(value, adam_b[i][key]), (i, key)


def test_status_asks_for_two_cpu_processes_where_two_cpu_runs_wait(tmp_path, capsys, code_tree):
    """The paper preset's CPU runs train one trajectory a step, which one core does about as fast as two (measured
    in docs/reproduce.md): with two or more of them not started, status's CPU line says to run the command twice
    with one thread each; with one left, once, as it is."""
    gpu = load_script("gpu")
    none = ["--carry-dir", str(tmp_path / "no_carry")]  # not the repository's carry/paper, which restore would need
    assert gpu.main(["status", "--preset", "paper", "--run-dir", str(tmp_path / "empty"), *none]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if "on a CPU (train.cpu_models)" in x)
    assert line.endswith("--stages train --threads 1, twice side by side (each takes a run the other is not on)")
    config = yaml.safe_load((REPO / "configs" / "reproduce.yaml").read_text())
    config["presets"]["paper"]["train"].update(models=["lstmnet", "vit"], nostate_models=[], draws={},
                                               cpu_models=["lstmnet"], slot_order=["vit"])
    one = tmp_path / "one.yaml"
    one.write_text(yaml.safe_dump(config))
    assert gpu.main(["status", "--config", str(one), "--preset", "paper", "--run-dir", str(tmp_path / "empty"),
                     *none]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if "on a CPU (train.cpu_models)" in x)
    assert line.endswith("--models lstmnet --stages train")


def test_status_refuses_to_plan_before_the_kept_runs_are_restored(tmp_path, capsys):
    """In a new checkout carry/<preset> holds the kept runs and the run directory nothing: planned so, every kept
    run would look new and a slot would train it again from scratch. status names them and asks for restore;
    carry (which leaves kept runs as they are) writes, and plans no slot."""
    gpu = load_script("gpu")
    kept = tmp_path / "carry" / "paper" / "convnet-state"
    shutil.copytree(REPO / "carry" / "paper" / "convnet-state", kept)  # a finished run, as committed
    before = {p.name: p.read_bytes() for p in kept.iterdir()}
    common = ["--preset", "paper", "--run-dir", str(tmp_path / "empty"), "--carry-dir", str(tmp_path / "carry")]
    with pytest.raises(SystemExit, match=r"keeps 1 run that .*/train lacks, so no slot can be planned; first: "
                                         r"python3 scripts/gpu\.py restore --preset paper$"):
        gpu.main(["status", *common])
    listing = capsys.readouterr().out
    assert re.search(r"^convnet-state +kept in .*carry/paper/convnet-state, not restored here$", listing, re.M)
    assert re.search(r"^vit-state +not started$", listing, re.M) and "command:" not in listing
    assert gpu.main(["carry", *common]) == 0
    listing = capsys.readouterr().out
    assert "no slot planned: " in listing and "command:" not in listing
    assert {p.name: p.read_bytes() for p in kept.iterdir()} == before


@pytest.fixture
def code_tree(monkeypatch):
    """The slot plans count the working tree a device call sends: here the code's alone, without the runs this
    repository's carry/ holds at the moment (they come and go with the study; the plans under test carry their
    own runs from tmp_path)."""
    slots = load_script("gpu_slots")
    real = slots.travelling_bytes
    monkeypatch.setattr(slots, "travelling_bytes",
                        lambda root, leave_out=None: real(root, leave_out) - slots.tree_bytes(REPO / "carry"))


def test_a_run_stopped_in_one_slot_resumes_in_the_next_exactly(tmp_path, data, two_epochs, capsys, code_tree):
    gpu = load_script("gpu")
    common = ["--config", str(two_epochs), "--preset", "tiny", "--data", str(data)]
    slot = ["--work", str(tmp_path / "work"), "--collect-workers", "1", "--threads", "1"]
    data_hash = dataset_fingerprint(data)["dataset_hash"]
    gpu1, home, gpu2 = tmp_path / "gpu1", tmp_path / "home", tmp_path / "gpu2"

    # slot 1: stopped after 1 of 2 epochs, carried home with its optimiser state
    assert gpu.main(["train", *common, "--run-dir", str(gpu1), "--out", str(tmp_path / "back1"), *slot,
                     "--runs", "vit_lstm-state", "--stop-after-epochs", "1"]) == 0
    entry = json.loads((tmp_path / "back1" / "gpu_reproduce.json").read_text())["runs"]["vit_lstm-state"]
    assert (entry["state"], entry["epochs"], entry["max_epochs"], entry["packed"]) == ("unfinished", [0, 1], 2, True)

    assert gpu.main(["unpack", *common, "--run-dir", str(home), str(tmp_path / "back1")]) == 0
    run = home / "train" / "vit_lstm-state"
    assert not (run / "done.json").exists()  # never as done
    marker = json.loads((run / "unfinished.json").read_text())
    assert (marker["epochs"], marker["max_epochs"], marker["dataset_hash"]) == (1, 2, data_hash)
    assert marker["slots"][0]["device"] == "cpu" and marker["moments"] == "fp32"
    assert 0 < marker["slots"][0]["fit_s"] <= marker["slots"][0]["wall_s"]  # the Timer, start-up not in it
    assert 0 < marker["first_epoch_s"] == marker["epoch_s"]  # one epoch measured: it is the first and the steady
    saved = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert (saved["epoch"], saved["global_step"]) == (0, 2)
    assert saved["optimizer_states"][0]["state"][0]["exp_avg_sq"].dtype == torch.float32
    fit_s = saved["callbacks"]["Timer"]["time_elapsed"]["train"]  # the stopwatch travels with the run
    cost = json.loads((run / "cost.json").read_text())
    assert fit_s > 0 and (cost["sessions"], cost["fit_s"], cost["killed_s"]) == (1, fit_s, 0.0)
    dirs = {s["dirpath"] for s in saved["callbacks"].values() if "dirpath" in s}
    assert dirs == {os.path.realpath(run / "checkpoints")}  # pointed at its new home

    capsys.readouterr()
    (home / "train" / "convnet-nostate").mkdir()  # a run in its first epoch here: a folder, no epoch yet
    assert gpu.main(["status", *common, "--run-dir", str(home)]) == 0
    listing = capsys.readouterr().out
    assert "vit_lstm-state   unfinished: 1/2 epochs" in listing and "convnet-state    not started\n" in listing
    assert "convnet-nostate  not started (its folder exists: no epoch ended yet)\n" in listing
    assert "about 1 more slot of" in listing
    assert re.search(r"starts: .*convnet-nostate", listing)
    holder = Holder(home / "train" / "convnet-nostate")  # a process here trains it now, in its first epoch
    try:
        assert gpu.main(["status", *common, "--run-dir", str(home)]) == 0
        busy = capsys.readouterr().out
    finally:
        holder.release()
    assert re.search(rf"convnet-nostate  started here: no epoch ended yet, training here now \(pid {holder.proc.pid} "
                     r"on \S+, since [^)]+\)\n", busy)
    assert not re.search(r"starts: .*convnet-nostate", busy)  # so no slot starts it beside that process
    # ViT+LSTM's lean state with fp32 moments and its best epoch in fp16 (the tiny preset flies the best epoch):
    # 3,563,663 x (12 x 0.85, last.* squeezed as planned + 2) + 196,608 bytes = 41.7 MiB, within what the working
    # tree travelling light (this repository's code without weights/ and docs/, nor the runs its carry/ holds:
    # code_tree) leaves of 64 MiB
    assert re.search(r"next slot carries 1 unfinished runs, 41\.7 MiB of the \d+\.\d MiB a call leaves", listing)
    assert re.search(r"carries: vit_lstm-state +last\.\* with fp32 moments", listing)
    assert "travel light" in listing
    follow_on = re.search(r"\n +(python3 scripts/gpu\.py train .*) --go-on --deadline-s \$\(\(T - 10 - SECONDS\)\)\n",
                          listing)
    assert follow_on and f"  command: {follow_on.group(1)}\n" in listing  # the first call's, and --go-on
    holder = Holder(run)  # vitfly reproduce goes on with the unfinished run here: no slot carries it meanwhile
    try:
        assert gpu.main(["status", *common, "--run-dir", str(home)]) == 0
        busy = capsys.readouterr().out
    finally:
        holder.release()
    assert "training here now, so in no slot: vit_lstm-state (stop them first" in busy
    assert "carries: vit_lstm-state" not in busy and "next slot carries 0 unfinished runs" in busy
    # a run of train.cpu_models goes in no slot anyway: nothing to stop, nothing said
    config = yaml.safe_load(two_epochs.read_text())
    config["presets"]["tiny"]["train"]["cpu_models"] = ["vit_lstm"]
    cpu_vit = tmp_path / "cpu_vit_lstm.yaml"
    cpu_vit.write_text(yaml.safe_dump(config))
    holder = Holder(run)
    try:
        assert gpu.main(["status", "--config", str(cpu_vit), *common[2:], "--run-dir", str(home)]) == 0
        busy = capsys.readouterr().out
    finally:
        holder.release()
    assert "training here now (pid" in busy and "so in no slot" not in busy and "carries: vit_lstm-state" not in busy

    # a resume state of other data is refused before anything trains
    bad = tmp_path / "bad" / "vit_lstm-state"
    shutil.copytree(run, bad)
    (bad / "unfinished.json").write_text(json.dumps({**marker, "dataset_hash": "0000000000000000"}))
    refused = ["train", *common, "--run-dir", str(gpu2), "--out", str(tmp_path / "refused"), *slot]
    assert gpu.main([*refused, "--resume-from", str(bad)]) == 1
    error = json.loads((tmp_path / "refused" / "gpu_reproduce.json").read_text())["error"]
    assert "trained on dataset_hash 0000000000000000" in error and not (gpu2 / "train").exists()

    # slot 2, another machine: it goes on from epoch 1 and finishes
    assert gpu.main(["train", *common, "--run-dir", str(gpu2), "--out", str(tmp_path / "back2"), *slot,
                     "--resume-from", str(run)]) == 0
    entry = json.loads((tmp_path / "back2" / "gpu_reproduce.json").read_text())["runs"]["vit_lstm-state"]
    assert (entry["state"], entry["epochs"], entry["packed"]) == ("finished", [1, 2], True)
    cost = json.loads((gpu2 / "train" / "vit_lstm-state" / "cost.json").read_text())
    assert cost["sessions"] == 2 and cost["fit_s"] > fit_s and cost["killed_s"] == 0.0  # a slot's end is no kill

    # ... exactly where an uninterrupted 2-epoch run ends (its LSTM dropout included)
    cfg = load_reproduce_config(two_epochs, "tiny", {"data": str(data)})
    stage, callbacks = train_callbacks(train_stage(cfg, "vit_lstm", True), cfg, "test")
    reference = tmp_path / "reference"
    stage_train(stage, data, reference, 1, progress=False, callbacks=callbacks)
    resumed = gpu2 / "train" / "vit_lstm-state"
    assert_same_training(reference / "checkpoints" / "last.ckpt", resumed / "checkpoints" / "last.ckpt")
    with open(resumed / "metrics.csv") as f:  # both slots' epochs: the first set aside, joined after the fit
        assert [r["epoch"] for r in csv.DictReader(f) if r["val/loss"]] == ["0", "1"]

    assert gpu.main(["unpack", *common, "--run-dir", str(home), str(tmp_path / "back2")]) == 0
    assert not (run / "unfinished.json").exists()
    done = json.loads((run / "done.json").read_text())
    assert (done["trained_on"]["epochs"], len(done["trained_on"]["slots"])) == (2, 2)
    with open(run / "metrics.csv") as f:
        assert [r["epoch"] for r in csv.DictReader(f) if r["val/loss"]] == ["0", "1"]  # the curve of both slots
    best = load_network(done["checkpoint"]).state_dict()
    for name, value in load_network(reference / "checkpoints" / "best.ckpt").state_dict().items():
        assert torch.equal(value.half().float() if value.is_floating_point() else value, best[name]), name

    # finished: never trained again, here or there
    capsys.readouterr()
    assert gpu.main(["train", *common, "--run-dir", str(gpu2), "--out", str(tmp_path / "back3"), *slot,
                     "--runs", "vit_lstm-state"]) == 0
    assert "not retrained" in capsys.readouterr().out and not list((tmp_path / "back3").glob("runs.tar.*"))
    assert gpu.main(["unpack", *common, "--run-dir", str(home), str(tmp_path / "back1")]) == 0
    assert "left alone" in capsys.readouterr().out and not (run / "unfinished.json").exists()
    assert gpu.main(["status", *common, "--run-dir", str(home)]) == 0
    assert "vit_lstm-state   done (2 epochs on cpu)" in capsys.readouterr().out

    # returned runs of other data are refused as a whole
    other = other_data(data, tmp_path)
    with pytest.raises(SystemExit, match="trained on dataset_hash .* the local .*other.h5 has .* nothing unpacked"):
        gpu.main(["unpack", "--config", str(two_epochs), "--preset", "tiny", "--data", str(other),
                  "--run-dir", str(tmp_path / "elsewhere"), str(tmp_path / "back1")])
    assert not (tmp_path / "elsewhere" / "train" / "vit_lstm-state").exists()

    # Adam moments in bf16: a third of the bytes less, and the resumed run ends close to the exact one
    slots = load_script("gpu_slots")
    light = tmp_path / "bf16"
    shutil.copytree(gpu1 / "train" / "vit_lstm-state", light)
    last = light / "checkpoints" / "last.ckpt"
    slots.save_atomic(slots.relocate(slots.compact_moments(torch.load(last, weights_only=True), "bf16"),
                                     last.parent), last)
    assert trained_state(last)[1][0]["exp_avg"].dtype == torch.bfloat16
    start = trained_state(last)[0]
    stage_train(stage, data, light, 1, progress=False, callbacks=callbacks)
    (exact, _), (close, adam) = trained_state(reference / "checkpoints" / "last.ckpt"), trained_state(last)
    assert adam[0]["exp_avg"].dtype == torch.float32  # back in fp32 once loaded
    moved, off = (torch.cat([(a[k] - b[k]).flatten() for k in exact]).norm() for a, b in ((exact, start),
                                                                                          (exact, close)))
    assert 0 < off < 0.01 * moved  # measured: 0.14 % of the distance the resumed epoch moved the weights


def test_states_too_large_for_the_trip_back_come_home_with_bf16_moments(tmp_path, data, two_epochs):
    """ViT+LSTM (39.4 MiB squeezed with fp32 moments, 25.8 with bf16, as measured) and ConvNet (2.6 MiB) against a
    36 MiB trip back: only ViT+LSTM's moments need to shrink, and nothing is left behind."""
    gpu = load_script("gpu")
    out = tmp_path / "back"
    assert gpu.main(["train", "--config", str(two_epochs), "--preset", "tiny", "--data", str(data), "--run-dir",
                     str(tmp_path / "gpu"), "--out", str(out), "--work", str(tmp_path / "work"), "--collect-workers",
                     "1", "--threads", "1", "--runs", "vit_lstm-state", "convnet-state", "--stop-after-epochs", "1",
                     "--return-mib", "36"]) == 0
    report = json.loads((out / "gpu_reproduce.json").read_text())
    assert report["pack"]["left_out"] == [] and report["runs"]["vit_lstm-state"]["moments"] == "bf16"
    assert "moments" not in report["runs"]["convnet-state"]
    assert gpu.main(["unpack", "--config", str(two_epochs), "--preset", "tiny", "--data", str(data), "--run-dir",
                     str(tmp_path / "home"), str(out)]) == 0
    for label, moments, dtype in (("vit_lstm-state", "bf16", torch.bfloat16), ("convnet-state", "fp32", torch.float32)):
        run = tmp_path / "home" / "train" / label
        assert json.loads((run / "unfinished.json").read_text())["moments"] == moments
        assert trained_state(run / "checkpoints" / "last.ckpt")[1][0]["exp_avg"].dtype == dtype


def stop_after_one_epoch(cfg, label: str, data: Path, train_dir: Path) -> None:
    """``vitfly reproduce``'s training of ``label``, ended after its first epoch as a session's end ends it."""
    slots = load_script("gpu_slots")
    run = load_script("gpu_reproduce").parse_label(label)
    stage, callbacks = train_callbacks(train_stage(cfg, run.model, run.use_state), cfg, "test")
    with pytest.raises(slots.SlotEnded):
        stage_train(stage, data, train_dir, 1, progress=False, callbacks=[*callbacks, slots.SlotStop(None, 1)])


def test_runs_outlive_the_session_in_the_carry(tmp_path, data, two_epochs, capsys, code_tree):
    """A new checkout has no runs/: ``carry`` keeps every run that trained here in carry/<preset>/ as safetensors
    and JSON (no pickle), ``restore`` puts them back, and they go on: one stopped by a slot resumes on the GPU
    machine, one started by ``vitfly reproduce`` resumes here and ends bit for bit where an uninterrupted run
    ends; a finished run comes back as done; runs of other data are refused."""
    gpu = load_script("gpu")
    common = ["--config", str(two_epochs), "--preset", "tiny", "--data", str(data)]
    slot = ["--work", str(tmp_path / "work"), "--collect-workers", "1", "--threads", "1"]
    cfg = load_reproduce_config(two_epochs, "tiny", {"data": str(data)})
    home, carry, back1, back2 = (tmp_path / name for name in ("home", "carry", "back1", "back2"))
    assert gpu.main(["train", *common, "--run-dir", str(tmp_path / "gpu1"), "--out", str(back1), *slot,
                     "--runs", "convnet-state", "--stop-after-epochs", "1"]) == 0
    with tarfile.open(fileobj=io.BytesIO(b"".join(p.read_bytes() for p in sorted(back1.glob("runs.tar.*"))))) as tar:
        travelled = sorted(m.name for m in tar.getmembers() if "checkpoints/" in m.name)
    assert travelled == ["convnet-state/checkpoints/best.ckpt.bpz", "convnet-state/checkpoints/last.ckpt.bpz"]
    assert gpu.main(["unpack", *common, "--run-dir", str(home), str(back1)]) == 0
    assert sorted(p.name for p in (home / "train" / "convnet-state" / "checkpoints").iterdir()) == [
        "best.ckpt", "last.ckpt"]  # read back before anything else reads them
    stop_after_one_epoch(cfg, "convnet-nostate", data, home / "train" / "convnet-nostate")
    live = home / "train" / "convnet-nostate" / "metrics.csv"
    with open(live) as f:  # carried while training: the logger has a row of an epoch last.ckpt does not hold
        header = next(csv.reader(f))
    with open(live, "a", newline="") as f:
        csv.DictWriter(f, fieldnames=header).writerow({"epoch": 1, "step": 99})

    capsys.readouterr()
    holder = Holder(home / "train" / "vit_lstm-state")  # vitfly reproduce in its first epoch here: no checkpoint
    try:
        assert gpu.main(["carry", *common, "--run-dir", str(home), "--carry-dir", str(carry)]) == 0
    finally:
        holder.release()
    out = capsys.readouterr().out
    assert "carries: convnet-state" in out and "kept: convnet-nostate (unfinished, fp32 moments)" in out
    kept = carry / "tiny"
    assert "not yet: vit_lstm-state (no epoch has ended here" in out and not (kept / "vit_lstm-state").exists()
    shutil.rmtree(home / "train" / "vit_lstm-state")  # stopped before its first epoch's end
    files = sorted(p.name for p in (kept / "convnet-state").iterdir())
    assert files == ["best.json", "best.safetensors", "cost.json", "data.json", "hparams.yaml", "last.json",
                     "last.safetensors.bpz", "metrics.csv", "split.json", "unfinished.json"]  # last.* squeezed
    marker = json.loads((kept / "convnet-nostate" / "unfinished.json").read_text())  # written for the CPU run
    assert (marker["epochs"], marker["max_epochs"], marker["slots"][0]["device"]) == (1, 2, "cpu")
    with open(kept / "convnet-nostate" / "metrics.csv") as f:
        assert {r["epoch"] for r in csv.DictReader(f)} == {"0"}  # the rows of the epoch it holds, no more
    assert 0 < marker["slots"][0]["fit_s"] == marker["slots"][0]["wall_s"]  # a CPU run's time is its Timer's
    assert marker["dataset_hash"] == dataset_fingerprint(data)["dataset_hash"]
    # a preset that trains ConvNet on a CPU: a slot does not resume its carried runs unless --runs names them
    config = yaml.safe_load(two_epochs.read_text())
    config["presets"]["tiny"]["train"]["cpu_models"] = ["convnet"]
    cpu_convnet = tmp_path / "cpu_convnet.yaml"
    cpu_convnet.write_text(yaml.safe_dump(config))
    capsys.readouterr()
    with pytest.raises(SystemExit, match="nothing to train"):
        gpu.main(["train", "--config", str(cpu_convnet), "--preset", "tiny", "--data", str(data), "--run-dir",
                  str(tmp_path / "gpu_cpu"), "--out", str(tmp_path / "back_cpu"), *slot, "--resume-from", str(kept)])
    skipped = capsys.readouterr().out
    assert all(f"{label}: trains on a CPU (train.cpu_models); not resumed here" in skipped
               for label in ("convnet-state", "convnet-nostate"))
    stranger = tmp_path / "not_a_carry"
    (stranger / "tiny" / "notes").mkdir(parents=True)
    with pytest.raises(SystemExit, match="holds notes, not carried runs; nothing written"):
        gpu.main(["carry", *common, "--run-dir", str(home), "--carry-dir", str(stranger)])
    before = {p: p.read_bytes() for p in kept.rglob("*") if p.is_file()}
    capsys.readouterr()  # a new checkout that did not restore: what is carried stays as it was
    assert gpu.main(["carry", *common, "--run-dir", str(tmp_path / "empty"), "--carry-dir", str(carry)]) == 0
    assert capsys.readouterr().out.count("kept as it was") == 2
    assert {p: p.read_bytes() for p in kept.rglob("*") if p.is_file()} == before

    # a new checkout: restored, the CPU run goes on here as vitfly reproduce would, to the uninterrupted end
    new = tmp_path / "new"
    assert gpu.main(["restore", *common, "--run-dir", str(new), "--carry-dir", str(carry)]) == 0
    resumed = new / "train" / "convnet-nostate"
    assert sorted(p.name for p in (resumed / "checkpoints").iterdir()) == ["best.ckpt", "last.ckpt"]
    # its best epoch comes back as trained (fp32), not rounded: finished without a better epoch, it flies that
    trained_best = load_network(home / "train" / "convnet-nostate" / "checkpoints" / "best.ckpt").state_dict()
    for name, value in load_network(resumed / "checkpoints" / "best.ckpt").state_dict().items():
        assert value.dtype == trained_best[name].dtype and torch.equal(value, trained_best[name]), name
    assert any(v.dtype == torch.float32 and not torch.equal(v, v.half().float()) for v in trained_best.values())
    stage, callbacks = train_callbacks(train_stage(cfg, "convnet", False), cfg, "test")
    stage_train(stage, data, resumed, 1, progress=False, callbacks=callbacks)
    reference = tmp_path / "reference"
    stage_train(stage, data, reference, 1, progress=False, callbacks=train_callbacks(stage, cfg, "test")[1])
    assert_same_training(reference / "checkpoints" / "last.ckpt", resumed / "checkpoints" / "last.ckpt")
    with open(resumed / "metrics.csv") as f:  # both sessions' epochs
        assert [r["epoch"] for r in csv.DictReader(f) if r["val/loss"]] == ["0", "1"]

    # ... and the slot's run on the GPU machine, from the carry as it travels with the tree
    assert gpu.main(["train", *common, "--run-dir", str(tmp_path / "gpu2"), "--out", str(back2), *slot,
                     "--resume-from", str(kept / "convnet-state")]) == 0
    entry = json.loads((back2 / "gpu_reproduce.json").read_text())["runs"]["convnet-state"]
    assert (entry["state"], entry["epochs"]) == ("finished", [1, 2])
    assert gpu.main(["unpack", *common, "--run-dir", str(new), str(back2)]) == 0
    capsys.readouterr()
    assert gpu.main(["carry", *common, "--run-dir", str(new), "--carry-dir", str(carry)]) == 0
    assert "kept: convnet-state (done, the flown weights)" in capsys.readouterr().out
    assert sorted(p.name for p in (kept / "convnet-state").glob("*.*")) == [
        "best.json", "best.safetensors", "cost.json", "data.json", "done.json", "hparams.yaml", "metrics.csv",
        "split.json"]
    # committed once, a finished run's weights leave the tree for git's history (they would take a device call's
    # room), and restore reads them back from there
    commit = ["git", "-C", str(carry), "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "carry"]
    subprocess.run(["git", "init", "-q", str(carry)], check=True)
    subprocess.run(["git", "-C", str(carry), "add", "."], check=True)
    subprocess.run(commit, check=True)
    capsys.readouterr()
    assert gpu.main(["carry", *common, "--run-dir", str(new), "--carry-dir", str(carry)]) == 0
    assert capsys.readouterr().out.count("its weights now in git's history") == 2
    assert not list(kept.rglob("best.*")) and (kept / "convnet-state" / "stowed.json").exists()
    subprocess.run(["git", "-C", str(carry), "add", "-A"], check=True)
    subprocess.run(commit, check=True)
    third = tmp_path / "third"
    assert gpu.main(["restore", *common, "--run-dir", str(third), "--carry-dir", str(carry)]) == 0
    assert not (third / "train" / "convnet-state" / "stowed.json").exists()
    done = json.loads((third / "train" / "convnet-state" / "done.json").read_text())
    assert Path(done["checkpoint"]) == (third / "train" / "convnet-state" / "checkpoints" / "best.ckpt").resolve()
    for label in ("convnet-state", "convnet-nostate"):  # the weights each flew: fp16 from the slot, fp32 from here
        flown = load_network(new / "train" / label / "checkpoints" / "best.ckpt").state_dict()
        done_there = json.loads((third / "train" / label / "done.json").read_text())
        for name, value in load_network(done_there["checkpoint"]).state_dict().items():
            assert torch.equal(value, flown[name]), (label, name)
    stage, callbacks = train_callbacks(train_stage(cfg, "convnet", True), cfg, "test")
    capsys.readouterr()
    stage_train(stage, data, third / "train" / "convnet-state", 1, progress=False, callbacks=callbacks)
    assert "done before" in capsys.readouterr().out  # taken as done, not trained again
    capsys.readouterr()
    assert gpu.main(["restore", *common, "--run-dir", str(third), "--carry-dir", str(carry)]) == 0
    assert "done here; left alone" in capsys.readouterr().out

    other = other_data(data, tmp_path)
    with pytest.raises(SystemExit, match="trained on dataset_hash .* the local .*other.h5 has .* nothing restored"):
        gpu.main(["restore", "--config", str(two_epochs), "--preset", "tiny", "--data", str(other), "--run-dir",
                  str(tmp_path / "fourth"), "--carry-dir", str(carry)])
    assert not (tmp_path / "fourth" / "train").exists()


def test_a_restored_run_that_did_not_train_is_carried_as_it_was(tmp_path, data, two_epochs, capsys, code_tree):
    """``carry`` in a session that restored a run and did not train it writes nothing new for it (a commit would
    weigh its old bytes and its new): kept byte for byte, its marker's moments as carried, unless the slot's plan
    needs lighter moments, which it says."""
    gpu = load_script("gpu")
    common = ["--config", str(two_epochs), "--preset", "tiny", "--data", str(data)]
    cfg = load_reproduce_config(two_epochs, "tiny", {"data": str(data)})
    carry, kept = tmp_path / "carry", tmp_path / "carry" / "tiny" / "convnet-nostate"

    def carry_from(run_dir: str, *flags: str) -> str:
        capsys.readouterr()
        assert gpu.main(["carry", *common, "--run-dir", str(tmp_path / run_dir), "--carry-dir", str(carry),
                         *flags]) == 0
        return capsys.readouterr().out

    def restore_to(run_dir: str) -> None:
        assert gpu.main(["restore", *common, "--run-dir", str(tmp_path / run_dir), "--carry-dir", str(carry)]) == 0

    def carried() -> dict:
        return {p: p.read_bytes() for p in kept.rglob("*") if p.is_file()}

    stop_after_one_epoch(cfg, "convnet-nostate", data, tmp_path / "home" / "train" / "convnet-nostate")
    assert "kept: convnet-nostate (unfinished, fp32 moments)" in carry_from("home")
    before = carried()
    restore_to("new")
    # planned into the slot with fp32 moments (they fit): the carried folder stays, byte for byte
    assert "kept as it was: convnet-nostate (has not trained since it was carried, fp32 moments)" in carry_from("new")
    assert carried() == before
    # a slot planned with bf16 moments needs it lighter: written again, and said so
    assert ("convnet-nostate: has not trained since it was carried with fp32 moments, written again with bf16 for "
            "the slot's room") in carry_from("new", "--carry-moments", "bf16")
    assert json.loads((kept / "unfinished.json").read_text())["carried_moments"] == "bf16"
    before = carried()
    # restored with bf16 moments and asked for exact ones: it stays bf16, as its marker says (fp32 would hold the
    # same rounded values and a marker claiming an exact resume)
    restore_to("newer")
    assert "kept as it was: convnet-nostate (has not trained since it was carried, bf16 moments)" in carry_from(
        "newer", "--carry-moments", "fp32")
    assert carried() == before


def test_a_follow_on_call_on_the_warm_machine_goes_on_from_its_run_folders(tmp_path, data, two_epochs, capsys):
    """What a lease leaves after the first 10-minute call trains on in a second call on the still-warm machine:
    ``--go-on`` resumes each run from the first call's run folder there (its full state, exact), not from the
    carry the first call started from; on a fresh machine it resumes from --resume-from alone."""
    gpu = load_script("gpu")
    common = ["--config", str(two_epochs), "--preset", "tiny", "--data", str(data)]
    machine, home = tmp_path / "machine", tmp_path / "home"
    call = ["train", *common, "--run-dir", str(machine), "--work", str(tmp_path / "work"), "--collect-workers", "1",
            "--threads", "1", "--go-on"]
    assert gpu.main([*call, "--out", str(tmp_path / "back1"), "--runs", "convnet-state",
                     "--stop-after-epochs", "1"]) == 0
    assert "no earlier call's runs" in capsys.readouterr().out
    run = machine / "train" / "convnet-state"
    marker = json.loads((run / "unfinished.json").read_text())  # the run folder there says where it stands
    assert (marker["epochs"], marker["max_epochs"], marker["moments"], len(marker["slots"])) == (1, 2, "fp32", 1)
    assert gpu.main(["unpack", *common, "--run-dir", str(home), str(tmp_path / "back1")]) == 0

    # the follow-on call, with the first call's carry named too (as the slot's command has it): the machine's
    # folder, named last, holds as many epochs and the full state
    carried = home / "train" / "convnet-state"
    assert gpu.main([*call, "--out", str(tmp_path / "back2"), "--resume-from", str(carried)]) == 0
    report = json.loads((tmp_path / "back2" / "gpu_reproduce.json").read_text())
    assert report["resumed"] == {"convnet-state": str(run)}
    assert (report["runs"]["convnet-state"]["state"], report["runs"]["convnet-state"]["epochs"]) == ("finished", [1, 2])
    cfg = load_reproduce_config(two_epochs, "tiny", {"data": str(data)})
    stage, callbacks = train_callbacks(train_stage(cfg, "convnet", True), cfg, "test")
    reference = tmp_path / "reference"
    stage_train(stage, data, reference, 1, progress=False, callbacks=callbacks)
    assert_same_training(reference / "checkpoints" / "last.ckpt", run / "checkpoints" / "last.ckpt")
    with open(run / "metrics.csv") as f:  # both calls' epochs
        assert [r["epoch"] for r in csv.DictReader(f) if r["val/loss"]] == ["0", "1"]

    assert gpu.main(["unpack", *common, "--run-dir", str(home), str(tmp_path / "back2")]) == 0
    done = json.loads((carried / "done.json").read_text())
    assert (done["trained_on"]["epochs"], len(done["trained_on"]["slots"])) == (2, 2)


def test_a_run_found_in_several_resume_folders_goes_on_from_its_most_epochs(tmp_path, capsys):
    reproduce = load_script("gpu_reproduce")

    def folder(name: str, epochs: int) -> Path:
        d = tmp_path / name / "vit-state"
        d.mkdir(parents=True)
        marker = {"label": "vit-state", "preset": "paper", "dataset_hash": "53d8667a84fc34cc", "epochs": epochs,
                  "slots": []}
        (d / "unfinished.json").write_text(json.dumps(marker))
        return d.parent

    carry, machine, twin = folder("carry", 7), folder("machine", 19), folder("twin", 19)
    for order in ([carry, machine], [machine, carry]):
        found = reproduce.resume_sources([str(p) for p in order], "paper")
        assert found["vit-state"][0] == machine / "vit-state" and found["vit-state"][1]["epochs"] == 19
    assert f"{carry / 'vit-state'}: vit-state at 7 epochs; goes on from {machine / 'vit-state'} (19 epochs)" \
        in capsys.readouterr().out
    assert reproduce.resume_sources([str(machine), str(twin)], "paper")["vit-state"][0] == twin / "vit-state"


def test_a_preset_that_flies_the_last_epoch_comes_home_without_a_best_checkpoint(tmp_path, data, two_epochs, capsys):
    """``select: last`` (the paper preset): a slot's run keeps no best.ckpt, there or here; unpacking places it
    all the same (it was refused once, for want of a best epoch to keep at home)."""
    config = yaml.safe_load(two_epochs.read_text())
    config["presets"]["tiny"]["train"]["overrides"]["select"] = "last"
    last_only = tmp_path / "reproduce.yaml"
    last_only.write_text(yaml.safe_dump(config))
    gpu = load_script("gpu")
    common = ["--config", str(last_only), "--preset", "tiny", "--data", str(data)]
    assert gpu.main(["train", *common, "--run-dir", str(tmp_path / "gpu"), "--out", str(tmp_path / "back"),
                     "--work", str(tmp_path / "work"), "--collect-workers", "1", "--threads", "1",
                     "--runs", "convnet-state", "--stop-after-epochs", "1"]) == 0
    capsys.readouterr()
    assert gpu.main(["unpack", *common, "--run-dir", str(tmp_path / "home"), str(tmp_path / "back")]) == 0
    assert "unfinished, 1/2 epochs" in capsys.readouterr().out
    run = tmp_path / "home" / "train" / "convnet-state"
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["last.ckpt"]


def test_a_run_folder_belongs_to_the_data_it_was_trained_on(tmp_path, data, capsys):
    """The same data path holding other bytes (here: one attribute more; in the project, pybullet's and the
    native back end's flights) is refused before any training, finished or not; a folder from before the record
    is adopted aloud."""
    other = tmp_path / "other.h5"
    shutil.copy(data, other)
    with h5py.File(other, "a") as f:
        f.attrs["collected_again"] = "on another machine"
    sha16 = {p: hashlib.sha256(p.read_bytes()).hexdigest()[:16] for p in (data, other)}
    assert sha16[data] != sha16[other]

    run = tmp_path / "run"
    check_trained_data(run, data)
    assert json.loads((run / "data.json").read_text())["dataset_hash"] == sha16[data]
    check_trained_data(run, data)  # the same bytes: nothing to say
    with pytest.raises(VitflyError, match=f"trained on dataset_hash {sha16[data]}.*now has {sha16[other]}"):
        stage_train(TrainStage(model="convnet", max_epochs=1), other, run, 1, progress=False)
    assert not (run / "checkpoints").exists() and not (run / "done.json").exists()

    legacy = tmp_path / "legacy"
    (legacy / "checkpoints").mkdir(parents=True)
    (legacy / "checkpoints" / "last.ckpt").write_bytes(b"")
    capsys.readouterr()
    check_trained_data(legacy, other)
    assert "no record of its data" in capsys.readouterr().out
    assert json.loads((legacy / "data.json").read_text())["dataset_hash"] == sha16[other]


def test_a_slot_stops_a_run_before_an_epoch_that_would_end_too_late():
    slots = load_script("gpu_slots")
    assert slots.stop_reason(100.0, None, None, 0, None) is None
    assert slots.stop_reason(100.0, 200.0, None, 5, None) is None  # no epoch measured yet: start one
    assert slots.stop_reason(100.0, 200.0, 90.0, 1, None) is None
    assert "deadline" in slots.stop_reason(100.0, 200.0, 120.0, 1, None)
    assert "--stop-after-epochs" in slots.stop_reason(100.0, 200.0, 1.0, 2, 2)


def test_a_slot_judges_the_next_epoch_by_its_steady_epochs(monkeypatch):
    """Epochs of 97 s (compile and graph capture), 52 s, 55 s from t = 0 against a deadline at 300 s: after the
    third (t = 204) a fourth of 55 s ends at 259 and starts; judged by the first epoch's 97 s it would not."""
    slots = load_script("gpu_slots")
    clock = iter([0.0, 97.0, 149.0, 204.0, 259.0])
    monkeypatch.setattr(slots.time, "time", lambda: next(clock))
    stop = slots.SlotStop(stop_at=300.0, max_epochs_this_slot=None, epoch_s=64.0)
    for _ in range(4):
        stop.on_train_epoch_start(None, None)
    assert stop.epoch_s == 55.0 and stop.trained == 3
    with pytest.raises(slots.SlotEnded, match="about 55 s"):
        stop.on_train_epoch_start(None, None)  # t = 259: 259 + 55 > 300


def test_a_slot_judges_an_epoch_by_whether_it_validates(monkeypatch):
    """A run validating every 5th epoch (the paper preset) trains epochs 3-8 in a slot from t = 0 to a deadline at
    t = 78: 10 s of training an epoch (the slot's first 20 s: compilation), 6 s more where it validates (epoch 4,
    0-based). The epochs end at 20, 36 (validated), 46, 56, 66; at t = 66 epoch 8 does not validate, 10 s: it ends
    at 76 and starts, where the longest whole epoch (16 s) would have stopped the run; at 76 epoch 9 validates,
    16 s, past the deadline: the slot ends."""
    slots = load_script("gpu_slots")
    clock = [0.0]
    monkeypatch.setattr(slots.time, "time", lambda: clock[0])
    trainer = SimpleNamespace(check_val_every_n_epoch=5, enable_validation=True, sanity_checking=False,
                              current_epoch=3)
    stop = slots.SlotStop(stop_at=78.0, max_epochs_this_slot=None, epoch_s=30.0)
    for train_s in (20.0, 10.0, 10.0, 10.0, 10.0, 10.0):  # epochs 3-8
        stop.on_train_epoch_start(trainer, None)
        clock[0] += train_s
        if (trainer.current_epoch + 1) % 5 == 0:
            stop.on_validation_start(trainer, None)
            clock[0] += 6.0
            stop.on_validation_end(trainer, None)
        trainer.current_epoch += 1
    assert clock[0] == 76.0 and stop.trained == 5 and stop.epoch_s == 10.0  # epoch 8 was judged 10 s at t = 66
    assert stop.val_s == [0.0, 6.0, 0.0, 0.0, 0.0]
    with pytest.raises(slots.SlotEnded, match="about 16 s"):
        stop.on_train_epoch_start(trainer, None)  # epoch 9 at t = 76: 76 + 10 + 6 > 78
    assert slots.steady_epoch_s(stop.measured) == 16.0  # what judged every epoch before

    assert slots.next_epoch_s([20.0, 16.0, 10.0], [0.0, 6.0, 0.0], validates=None) == 16.0  # not known: as before
    # a validating epoch before any validation was measured here: the previous slot's epoch at most
    assert slots.next_epoch_s([20.0, 10.0], [0.0, 0.0], validates=True, hint_s=14.0) == 14.0
    assert slots.next_epoch_s([20.0, 10.0], [0.0, 0.0], validates=True) == 10.0
    assert slots.epoch_validates(None) is None
    assert slots.epoch_validates(SimpleNamespace(check_val_every_n_epoch=None, enable_validation=True,
                                                 current_epoch=4)) is None
    assert slots.epoch_validates(SimpleNamespace(check_val_every_n_epoch=5, enable_validation=False,
                                                 current_epoch=4)) is False


def test_a_run_still_going_at_the_deadline_is_killed():
    gpu = load_script("gpu_reproduce")
    quick = subprocess.Popen([sys.executable, "-c", "pass"], start_new_session=True)
    slow = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)
    now = time.monotonic()
    # 10 s: time for the quick one to start and end on a loaded machine, well before the slow one's 60
    ended = gpu.wait_runs({"quick": (quick, now), "slow": (slow, now)}, now + 10)
    assert ended["quick"][0] == 0 and ended["slow"][0] is None and 10 <= ended["slow"][1] < 40
    assert slow.poll() is not None


def write_tar(path: Path, build) -> Path:
    with tarfile.open(path, "w") as tar:
        build(tar)
    return path


@pytest.mark.parametrize("filter_present", [True, False], ids=["data_filter", "python_3.11.2"])
def test_unpacking_stays_inside_its_folder_on_every_python(tmp_path, monkeypatch, filter_present):
    slots = load_script("gpu_slots")
    if not filter_present:  # TarFile.extractall(filter=...) arrived in 3.10.12 / 3.11.4
        monkeypatch.delattr(tarfile, "data_filter", raising=False)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "done.json").write_text("{}")
    good = write_tar(tmp_path / "good.tar", lambda tar: tar.add(tmp_path / "run", arcname="run"))
    slots.safe_extract(good, tmp_path / "into")
    assert (tmp_path / "into" / "run" / "done.json").read_text() == "{}"

    def member(name: str, kind: bytes = tarfile.REGTYPE, target: str = ""):
        def build(tar):
            info = tarfile.TarInfo(name)
            info.type, info.linkname, info.size = kind, target, 2 if kind == tarfile.REGTYPE else 0
            tar.addfile(info, io.BytesIO(b"{}") if kind == tarfile.REGTYPE else None)
        return build

    for i, build in enumerate([member("../escaped.json"), member("/tmp/absolute.json"),
                               member("run/link", tarfile.SYMTYPE, "/etc/passwd"),
                               member("run/hard", tarfile.LNKTYPE, "../../escaped.json")]):
        bad = write_tar(tmp_path / f"bad{i}.tar", build)
        with pytest.raises(SystemExit, match=f"{bad}: member"):
            slots.safe_extract(bad, tmp_path / f"bad{i}")
        assert not (tmp_path / f"bad{i}").exists()  # refused before anything is written


def test_bf16_moments_load_back_as_fp32():
    slots = load_script("gpu_slots")
    param = torch.nn.Parameter(torch.randn(5))
    adam = torch.optim.Adam([param])
    param.grad = torch.randn(5)
    adam.step()
    light = slots.compact_moments({"optimizer_states": [adam.state_dict()]}, "bf16")["optimizer_states"][0]
    again = torch.optim.Adam([param])
    again.load_state_dict(light)
    assert again.state[param]["exp_avg"].dtype == torch.float32  # torch casts to the parameter's dtype
    assert torch.equal(again.state[param]["exp_avg"], adam.state[param]["exp_avg"].bfloat16().float())


def test_a_finished_runs_checkpoint_is_found_relative_to_its_folder_or_the_working_directory(tmp_path, monkeypatch):
    from types import SimpleNamespace

    carry = load_script("gpu_carry")
    monkeypatch.chdir(tmp_path)
    folder = Path("runs") / "lstmnet-state"  # `vitfly reproduce --out runs`: done.json names runs/.../last.ckpt
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "checkpoints" / "last.ckpt").write_bytes(b"")
    run = SimpleNamespace(folder=folder)
    (folder / "done.json").write_text(json.dumps({"checkpoint": str(folder / "checkpoints" / "last.ckpt")}))
    assert carry.flown_checkpoint(None, run) == folder / "checkpoints" / "last.ckpt"
    (folder / "done.json").write_text(json.dumps({"checkpoint": "checkpoints/last.ckpt"}))  # as carried runs say
    assert carry.flown_checkpoint(None, run) == folder / "checkpoints" / "last.ckpt"


def test_a_carried_run_resumed_on_this_cpu_keeps_a_slot_for_each_session(tmp_path, data, two_epochs, capsys):
    """A restored run that ``vitfly reproduce`` took further here goes back into the carry with one more CPU
    slot: the epochs since the marker's last slot, and the fitting seconds its checkpoint's Timer gained;
    ``status`` counts them too."""
    carry = load_script("gpu_carry")
    run = tmp_path / "lstmnet-nostate"
    (run / "checkpoints").mkdir(parents=True)

    def trained(epochs: int, fit_s: float) -> None:
        torch.save({"epoch": epochs - 1, "callbacks": {"Timer": {"time_elapsed": {"train": fit_s}}}},
                   run / "checkpoints" / "last.ckpt")

    cpu = {"device": "cpu", "epochs": [0, 18], "wall_s": 5242.8}  # an older marker: no fit_s
    trained(18, 5242.8)
    assert carry.caught_up({"epochs": 18, "slots": [cpu]}, run) == {"epochs": 18, "slots": [cpu]}
    trained(82, 14242.8)  # 64 epochs in 9,000 s more
    marker = carry.caught_up({"epochs": 82, "slots": [cpu]}, run)
    assert marker["slots"][1] == {"device": "cpu", "epochs": [18, 82], "wall_s": 9000.0, "fit_s": 14242.8}
    trained(90, 15000.0)  # the next session counts from the fit_s the last one recorded
    assert carry.caught_up(marker, run)["slots"][2] == {"device": "cpu", "epochs": [82, 90], "wall_s": 757.2,
                                                        "fit_s": 15000.0}
    # after a GPU slot whose wall_s (start-up included) outran the Timer: never a negative CPU slot
    gpu = {"device": "NVIDIA H200", "epochs": [0, 7], "wall_s": 344.0}
    trained(8, 300.0)
    assert carry.caught_up({"epochs": 8, "slots": [gpu]}, run)["slots"][1]["wall_s"] == 0.0
    trained(9, 400.0)
    assert carry.caught_up({"epochs": 9, "slots": [gpu]}, run)["slots"][1]["wall_s"] == 56.0

    # status: one GPU slot of 1 epoch (30 s, 20 s of them fitting), then 1 epoch here (60 s more on the Timer)
    home = tmp_path / "home"
    restored = home / "train" / "convnet-nostate"
    shutil.copytree(run, restored)
    torch.save({"epoch": 1, "callbacks": {"Timer": {"time_elapsed": {"train": 80.0}}}},
               restored / "checkpoints" / "last.ckpt")
    (restored / "unfinished.json").write_text(json.dumps({
        "label": "convnet-nostate", "preset": "tiny", "dataset_hash": dataset_fingerprint(data)["dataset_hash"],
        "epochs": 1, "slots": [{"device": "NVIDIA H200", "epochs": [0, 1], "wall_s": 30.0, "fit_s": 20.0}]}))
    config = yaml.safe_load(two_epochs.read_text())
    config["presets"]["tiny"]["train"]["overrides"]["max_epochs"] = 3
    three = tmp_path / "three.yaml"
    three.write_text(yaml.safe_dump(config))
    gpu = load_script("gpu")
    capsys.readouterr()
    assert gpu.main(["status", "--config", str(three), "--preset", "tiny", "--data", str(data), "--run-dir",
                     str(home)]) == 0
    assert "convnet-nostate  unfinished: 2/3 epochs, 1.5 min on NVIDIA H200 + cpu" in capsys.readouterr().out
