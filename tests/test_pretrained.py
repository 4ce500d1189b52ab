"""Pretrained weights: fp16 safetensors + manifest, loaded by name, refused with one line when anything is off."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from vitfly.errors import VitflyError
from vitfly.eval import records
from vitfly.eval.policy_source import PolicySource
from vitfly.zoo import create_model, load_pretrained, save_checkpoint, save_pretrained
from vitfly.zoo.pretrained import file_sha256, read_manifest, update_manifest

torch.set_num_threads(1)


def random_checkpoint(tmp_path, name="lstmnet", use_state=True, seed=0):
    torch.manual_seed(seed)
    net = create_model(name, use_state=use_state).eval()
    with torch.no_grad():  # batch-norm statistics away from their defaults, so they round-trip too
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.normal_(0, 0.1)
                m.running_var.uniform_(0.5, 2.0)
    path = tmp_path / f"{name}.ckpt"
    save_checkpoint(net, name, use_state, path)
    return net, path


def inputs(t=5, seed=1):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(2, t, 1, 60, 90, generator=g), torch.full((2, t, 1), 5.0),
            torch.nn.functional.normalize(torch.randn(2, t, 4, generator=g), dim=-1))


@pytest.mark.parametrize("name,use_state", [("lstmnet", True), ("convnet", False)])
def test_round_trip_is_the_fp16_rounding_of_the_network(tmp_path, name, use_state):
    net, ckpt = random_checkpoint(tmp_path, name, use_state)
    weights = tmp_path / "weights"
    path = save_pretrained(ckpt, f"my_{name}", {"preset": "tiny", "closed_loop": {"spheres": {"3": 0.5}}}, weights)
    assert path == weights / f"my_{name}.safetensors"
    stored = load_file(str(path))
    for k, v in net.state_dict().items():  # floats stored as fp16, integer buffers as they were
        assert stored[k].dtype == (torch.float16 if v.is_floating_point() else v.dtype), k
    loaded = load_pretrained(f"pretrained:my_{name}", weights)
    assert not loaded.training and loaded.use_state is use_state
    for k, v in net.state_dict().items():
        expected = v.half().to(v.dtype) if v.is_floating_point() else v
        assert torch.equal(loaded.state_dict()[k], expected), k  # exactly the fp16 rounding, back in fp32
        assert loaded.state_dict()[k].dtype == v.dtype
    with torch.no_grad():
        out, _ = net(*inputs())
        out_loaded, _ = loaded(*inputs())
    # fp16 keeps 11 significant bits (relative rounding 2^-11 ~ 5e-4 per weight): outputs agree to ~1e-3
    torch.testing.assert_close(out_loaded, out, atol=5e-3, rtol=5e-3)
    entry = read_manifest(weights)["models"][f"my_{name}"]
    assert entry["sha256"] == file_sha256(path) and entry["model"] == name and entry["use_state"] is use_state
    assert entry["preset"] == "tiny" and entry["closed_loop"] == {"spheres": {"3": 0.5}}
    assert entry["dtype"] == "float16" and entry["file"] == path.name
    update_manifest(f"my_{name}", {"closed_loop": {"spheres": {"3": 0.75}}}, weights)
    assert read_manifest(weights)["models"][f"my_{name}"]["closed_loop"] == {"spheres": {"3": 0.75}}
    assert read_manifest(weights)["models"][f"my_{name}"]["sha256"] == entry["sha256"]



def test_the_same_checkpoint_published_again_is_the_same_file(tmp_path):
    from safetensors import safe_open

    _, ckpt = random_checkpoint(tmp_path, "lstmnet")
    # safetensors alone orders its 4 metadata keys at random, call by call: 5 publications alike by chance ~ 24^-4
    paths = [save_pretrained(ckpt, "my_lstmnet", {}, tmp_path / f"w{i}") for i in range(5)]
    assert len({file_sha256(p) for p in paths}) == 1
    size = int.from_bytes(paths[0].read_bytes()[:8], "little")
    header = json.loads(paths[0].read_bytes()[8:8 + size])
    assert list(header["__metadata__"]) == ["format", "model", "model_kwargs", "use_state"]
    with safe_open(str(paths[0]), "pt") as f:  # still a valid file: safetensors reads it back
        assert f.metadata()["model"] == "lstmnet" and f.metadata()["use_state"] == "true"
    assert load_pretrained("pretrained:my_lstmnet", tmp_path / "w4").use_state
def test_tampered_missing_and_mismatched_files_are_one_line(tmp_path):
    _, ckpt = random_checkpoint(tmp_path, "convnet")
    weights = tmp_path / "weights"
    path = save_pretrained(ckpt, "convnet", {}, weights)
    data = bytearray(path.read_bytes())
    data[-3] ^= 0x01  # one bit of one weight
    path.write_bytes(bytes(data))
    with pytest.raises(VitflyError, match=r"convnet.safetensors: sha256 .* differs from the manifest's .*refusing"):
        load_pretrained("convnet", weights)
    path.unlink()
    with pytest.raises(VitflyError, match=r"convnet.safetensors: missing \(the manifest lists it for pretrained:conv"):
        load_pretrained("convnet", weights)
    with pytest.raises(VitflyError, match=r"pretrained:vit_lstm: not in .*manifest.json \(available: convnet\)"):
        load_pretrained("vit_lstm", weights)
    with pytest.raises(VitflyError, match=r"manifest.json: no pretrained weights manifest"):
        load_pretrained("convnet", tmp_path / "nowhere")
    # a file whose hash the manifest vouches for but whose shapes are another network's
    manifest = read_manifest(weights)
    other = {k: v.half() if v.is_floating_point() else v for k, v in create_model("lstmnet").state_dict().items()}
    save_file(other, str(weights / "odd.safetensors"))
    manifest["models"]["odd"] = {**manifest["models"]["convnet"], "file": "odd.safetensors",
                                 "sha256": file_sha256(weights / "odd.safetensors")}
    (weights / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(VitflyError, match=r"odd.safetensors: does not fit architecture 'convnet': missing keys"):
        load_pretrained("odd", weights)
    manifest["models"]["odd"]["file"] = "../x.safetensors"
    (weights / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(VitflyError, match=r"field 'file' must be a file name inside"):
        load_pretrained("odd", weights)
    with pytest.raises(VitflyError, match=r"manifest field 'sha256' is written by the publisher"):
        save_pretrained(ckpt, "x", {"sha256": "0"}, weights)
    with pytest.raises(VitflyError, match=r"pretrained name '../x'"):
        save_pretrained(ckpt, "../x", {}, weights)


def test_cli_evaluates_and_exports_pretrained_weights(tmp_path, monkeypatch, capsys):
    from vitfly.cli import main

    _, ckpt = random_checkpoint(tmp_path, "convnet")
    weights = tmp_path / "weights"
    save_pretrained(ckpt, "convnet", {"preset": "test"}, weights)
    monkeypatch.setenv("VITFLY_WEIGHTS_DIR", str(weights))
    out = tmp_path / "eval"
    assert main(["evaluate", "--policy", "pretrained:convnet", "--speeds", "7", "--trials", "1", "--out", str(out),
                 "--no-gif", "--no-plots", "--no-progress", "--timeout", "3"]) == 0
    rec = json.loads((out / "trials.jsonl").read_text().splitlines()[0])
    assert rec["policy"] == "convnet" and rec["extra"]["policy_source"] == "pretrained:convnet"
    capsys.readouterr()
    assert main(["export", "pretrained:convnet", "--out", str(tmp_path / "p.onnx")]) == 0
    assert "from pretrained:convnet" in capsys.readouterr().out and (tmp_path / "p.onnx").is_file()
    assert main(["evaluate", "--policy", "pretrained:nope", "--out", str(tmp_path / "e2")]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and "vitfly: error: pretrained:nope: not in" in errors[0]


def test_publish_weights_command_records_the_dataset(tmp_path):
    from test_datamodule import write_dataset

    _, ckpt = random_checkpoint(tmp_path, "convnet")
    data = write_dataset(tmp_path / "d.h5", [4, 6])
    weights = tmp_path / "w"
    run = subprocess.run([sys.executable, "-m", "vitfly.cli", "publish-weights", str(ckpt), "--name", "convnet",
                          "--weights-dir", str(weights), "--preset", "laptop", "--dataset", data,
                          "--field", "notes=\"mirror 0.5\""], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    entry = read_manifest(weights)["models"]["convnet"]
    assert entry["preset"] == "laptop" and entry["notes"] == "mirror 0.5"
    assert entry["dataset_frames"] == 10 and entry["dataset_trajectories"] == 2 and len(entry["dataset_hash"]) == 16
    assert PolicySource("pretrained:convnet").is_pretrained


def test_shipped_manifest_is_valid():
    manifest = read_manifest()  # the repository's weights/manifest.json
    for name, entry in manifest["models"].items():
        load_pretrained(name)  # every shipped entry loads (hash, keys, shapes)
        assert entry["dtype"] == "float16"


def test_published_weights_fly_with_their_training_sensor(tmp_path):
    # a checkpoint trained at 15 Hz: its published weights must fly at 15 Hz too (steps of 1/15 s), not the default 30
    ckpt = tmp_path / "convnet15.ckpt"
    save_checkpoint(create_model("convnet"), "convnet", True, ckpt,
                    sensor={"depth_max_m": 10.0, "camera": None, "control_hz": 15.0})
    weights = tmp_path / "weights"
    save_pretrained(ckpt, "convnet", {}, weights)
    assert read_manifest(weights)["models"]["convnet"]["sensor"]["control_hz"] == 15.0
    env = {**__import__("os").environ, "VITFLY_WEIGHTS_DIR": str(weights)}
    out = tmp_path / "eval"
    run = subprocess.run(
        [sys.executable, "-m", "vitfly.cli", "evaluate", "--policy", "pretrained:convnet", "--speeds", "7",
         "--trials", "1", "--out", str(out), "--no-gif", "--no-plots", "--no-progress", "--timeout", "2"],
        capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr
    (rec,) = records.read_sweep(out)
    np.testing.assert_allclose(np.diff(rec.path_arrays()["time"]), 1 / 15, atol=1e-3)  # one tick = 1 / 15 s


def test_publish_weights_takes_closed_loop_numbers_only_from_trials_of_those_weights(tmp_path, capsys):
    from vitfly.cli import main

    _, ckpt = random_checkpoint(tmp_path, "convnet")
    (tmp_path / "other").mkdir()
    _, other = random_checkpoint(tmp_path / "other", "convnet", seed=1)
    sweeps = {env: tmp_path / "eval" / env for env in ("spheres", "trees")}
    for env, out in sweeps.items():
        assert main(["evaluate", "--policy", str(ckpt), "--name", "mine", "--env", env, "--speeds", "3", "5",
                     "--trials", "2", "--out", str(out), "--no-gif", "--no-plots", "--no-progress",
                     "--timeout", "2"]) == 0
    weights = tmp_path / "w"
    publish = ["publish-weights", str(ckpt), "--name", "convnet_test", "--weights-dir", str(weights),
               "--closed-loop-from", *map(str, sweeps.values()), "--closed-loop-policy", "mine"]
    assert main(publish) == 0
    numbers = read_manifest(weights)["models"]["convnet_test"]["closed_loop"]
    assert {k: numbers[k] for k in ("eval_seed", "scene_preset", "success", "backend")} == {
        "eval_seed": 0, "scene_preset": "medium", "success": "no collision", "backend": "eager"}
    for env, out in sweeps.items():  # each cell by hand from the trials
        recs = records.read_sweep(out)
        for speed in (3.0, 5.0):
            cell = [r for r in recs if r.speed == speed]
            assert numbers[env][f"{speed:g}"] == {
                "success": sum(r.success_paper for r in cell) / 2, "trials": 2,
                "success_strict": sum(r.success_strict for r in cell) / 2,
                "collisions_per_trial": pytest.approx(sum(r.metrics["collisions"] for r in cell) / 2)}
    # trials of other weights under the label, or no trials of it: one line, nothing written
    capsys.readouterr()
    refused = tmp_path / "refused"
    other_weights = ["publish-weights", str(other), "--name", "convnet_test", "--weights-dir", str(refused),
                     "--closed-loop-from", str(sweeps["spheres"]), "--closed-loop-policy", "mine"]
    assert main(other_weights) == 2
    assert "was flown with other weights" in capsys.readouterr().err and not refused.exists()
    assert main([*other_weights[:-1], "nobody"]) == 2
    assert "no trials of policy 'nobody'" in capsys.readouterr().err and not refused.exists()


def test_weights_command_lists_the_manifest_and_shows_an_entry(tmp_path, capsys):
    from vitfly.cli import main

    _, ckpt = random_checkpoint(tmp_path, "convnet")
    weights = tmp_path / "w"
    cell = {"success_strict": 0.0, "collisions_per_trial": 1.0, "trials": 4}
    save_pretrained(ckpt, "mine", {"preset": "test", "closed_loop": {"spheres": {
        "3": {**cell, "success": 0.75}, "10": {**cell, "success": 0.25}}}}, weights)
    save_pretrained(ckpt, "bare", {}, weights)
    capsys.readouterr()
    assert main(["weights", "--weights-dir", str(weights)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"weights in {weights}: fly them as pretrained:NAME")
    assert lines[1].split() == ["name", "network", "state", "epochs", "preset", "spheres", "success", "(no",
                                "collision)"]
    # speeds in numeric order (10 after 3), success in %; an entry without numbers or provenance says so
    assert [line.split() for line in lines[2:]] == [
        ["bare", "convnet", "yes", "-", "-", "-"],
        ["mine", "convnet", "yes", "-", "test", "75", "/", "25", "%", "at", "3", "/", "10", "m/s"]]
    assert main(["weights", "mine", "--weights-dir", str(weights)]) == 0
    assert json.loads(capsys.readouterr().out) == read_manifest(weights)["models"]["mine"]
    assert main(["weights", "nope", "--weights-dir", str(weights)]) == 2
    assert "pretrained:nope: not in" in capsys.readouterr().err
    assert main(["weights"]) == 0  # the shipped ones: the paper-budget ConvNet beside the shipped study's
    shipped = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()[2:]}
    assert shipped["convnet_paper"][:5] == ["convnet_paper", "convnet", "yes", "100", "paper"]
    assert shipped["convnet"][3] == "21" and set(shipped) >= {"convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm"}


def test_listing_the_weights_needs_no_torch_and_stops_quietly_when_the_reader_does():
    code = ("import sys; from vitfly.cli import main; code = main(['weights']); "
            "assert 'torch' not in sys.modules, 'torch was imported'; sys.exit(code)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "convnet_paper" in done.stdout
    # a reader that goes before reading anything (as `head` does after its lines): no error line, no traceback,
    # the exit status of a program stopped by SIGPIPE
    piped = subprocess.run(["bash", "-o", "pipefail", "-c", f"'{sys.executable}' -m vitfly.cli weights | true"],
                           capture_output=True, text=True, timeout=60)
    assert (piped.returncode, piped.stderr) == (141, "")
