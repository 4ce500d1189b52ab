"""Shipped configs and weights (``vitfly.packaged``): by path or by name, from any directory; what an installed
vitfly reads and refuses to write; the version; the package list the wheel is built from."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

import vitfly
from vitfly import packaged
from vitfly.cli import main
from vitfly.errors import VitflyError
from vitfly.training.cli import resolve_config_args
from vitfly.workflows.reproduce_config import load_reproduce_config
from vitfly.workflows.reproduce_report import _record_closed_loop
from vitfly.zoo import create_model, save_checkpoint
from vitfly.zoo.pretrained import WEIGHTS_ENV, publish_dir, save_pretrained, weights_dir

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def elsewhere(tmp_path, monkeypatch):
    """Run from an empty directory: no configs/ or weights/ under the working directory."""
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)
    return cwd


@pytest.fixture
def installed(tmp_path, monkeypatch, elsewhere):
    """vitfly as a wheel installs it: configs and weights inside the package (a copy here), no source tree."""
    site = tmp_path / "site" / "vitfly"
    for kind in packaged.SHIPPED:
        shutil.copytree(REPO / kind, site / kind)
    monkeypatch.setattr(packaged, "_installed_dir", lambda kind: site / kind)
    return site


def test_the_source_tree_is_found_and_ships_both():
    assert packaged.source_root() == REPO
    assert packaged.shipped_dir("configs") == REPO / "configs"
    assert packaged.shipped_dir("weights") == REPO / "weights"


@pytest.mark.parametrize("spec", ["quickstart", "configs/quickstart.yaml", "quickstart.yaml",
                                  "./configs/quickstart.yaml"])
def test_a_config_resolves_by_name_from_any_directory(elsewhere, spec):
    assert packaged.config_path(spec) == REPO / "configs" / "quickstart.yaml"


def test_nested_names_and_references_between_configs_resolve(elsewhere):
    assert packaged.config_path("fit/vit_lstm") == REPO / "configs" / "fit" / "vit_lstm.yaml"
    assert packaged.config_path("configs/collect/spheres.yaml") == REPO / "configs" / "collect" / "spheres.yaml"


def test_a_path_that_exists_wins_over_a_name(elsewhere):
    own = elsewhere / "configs" / "quickstart.yaml"
    own.parent.mkdir()
    own.write_text("out: mine\n")
    assert packaged.config_path("configs/quickstart.yaml") == Path("configs/quickstart.yaml")
    assert packaged.config_path("quickstart") == REPO / "configs" / "quickstart.yaml"  # no file named quickstart


@pytest.mark.parametrize("spec", ["nope", "/abs/quickstart.yaml", "../configs/quickstart", "fit", "a b"])
def test_an_unknown_config_is_one_line(elsewhere, spec):
    with pytest.raises(VitflyError) as err:
        packaged.config_path(spec)
    assert str(err.value).startswith(f"{spec}: config file not found") and "vitfly configs" in str(err.value)


def test_every_workflow_loads_its_config_by_name_from_elsewhere(elsewhere):
    from vitfly.eval.config import load_sweep_config
    from vitfly.sim.collect import load_collect_config
    from vitfly.workflows.ablation import load_ablation_config
    from vitfly.workflows.dagger_config import base_collect, load_dagger_config
    from vitfly.workflows.pipeline import load_pipeline_config, stage_collect
    from vitfly.workflows.reproduce_config import train_stage

    pipeline = load_pipeline_config("quickstart")
    assert pipeline.collect_config == "configs/collect/spheres.yaml"  # resolved where it is read, by name here
    assert load_collect_config(pipeline.collect_config).trajectories > 0
    with pytest.raises(VitflyError, match="unknown key 'nope'"):  # the referenced collect config is really read
        stage_collect(pipeline.collect_config, {"nope": 1}, elsewhere / "d.h5")
    reproduce = load_reproduce_config("reproduce", "laptop")  # reads every recipe: train.recipes configs/fit
    assert train_stage(reproduce, "vit_lstm", True).model == "vit_lstm"
    assert load_ablation_config("ablate", "tiny").models == ["convnet"]
    assert base_collect(load_dagger_config("dagger", "tiny")).trajectories > 0
    assert load_sweep_config("eval/trees").env == ["trees"]
    assert load_pipeline_config("quickstart_tiny").collect["trajectories"] <= 10


def test_command_defaults_are_the_shipped_configs(elsewhere, capsys):
    assert main(["reproduce", "--preset", "nope"]) == 2
    assert "no preset 'nope'" in capsys.readouterr().err
    assert main(["pipeline", "--config", "nope"]) == 2
    assert capsys.readouterr().err.strip() == ("vitfly: error: nope: config file not found, nor a config shipped "
                                               "with vitfly by that name (`vitfly configs` lists them)")


def test_fit_config_names_resolve_and_paths_stay(elsewhere):
    fit = REPO / "configs" / "fit"
    assert resolve_config_args(["fit", "--config", "fit/vit_lstm", "-c", "fit/gpu", "--config=fit/trainer/ddp"]) == [
        "fit", "--config", str(fit / "vit_lstm.yaml"), "-c", str(fit / "gpu.yaml"),
        f"--config={fit / 'trainer' / 'ddp.yaml'}"]
    (elsewhere / "mine.yaml").write_text("trainer: {max_epochs: 1}\n")
    kept = ["fit", "--config", "mine.yaml", "--config", "trainer: {max_epochs: 2}", "--data.data_path", "fit/vit"]
    assert resolve_config_args(kept) == kept  # an existing file, YAML text, and a value of another flag


def test_fit_print_config_by_name(elsewhere, capsys):
    assert main(["fit", "--config", "fit/convnet", "--print_config"]) == 0
    assert "class_path: vitfly.zoo.policy.convnet" in capsys.readouterr().out


def test_configs_lists_every_shipped_config(capsys):
    assert main(["configs"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert str(REPO / "configs") in out[0]
    names = {line.split()[0] for line in out[2:]}
    assert names == {p.relative_to(REPO / "configs").with_suffix("").as_posix()
                     for p in (REPO / "configs").rglob("*.yaml")}
    row = next(line for line in out if line.startswith("fit/vit_lstm "))
    assert "vitfly fit" in row and "ViT+LSTM" in row
    assert main(["configs", "fit/vit_lstm"]) == 0
    assert capsys.readouterr().out.strip() == str(REPO / "configs" / "fit" / "vit_lstm.yaml")
    assert main(["configs", "configs/fit/vit_lstm.yaml"]) == 0
    assert capsys.readouterr().out.strip() == str(REPO / "configs" / "fit" / "vit_lstm.yaml")
    for bad in ("nope", "../configs/quickstart", "/etc/quickstart"):
        assert main(["configs", bad]) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_version_has_one_source(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.strip().startswith(f"vitfly {vitfly.__version__} from {REPO / 'vitfly'} (Python ")
    tomllib = pytest.importorskip("tomllib")
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert "version" not in pyproject["project"] and "version" in pyproject["project"]["dynamic"]
    assert pyproject["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "vitfly.__version__"}


def test_checkpoints_record_the_version(tmp_path):
    save_checkpoint(create_model("convnet"), "convnet", True, tmp_path / "c.ckpt", metadata={"source": "x"})
    stamp = torch.load(tmp_path / "c.ckpt", weights_only=True)["vitfly"]
    assert stamp == {"format": "vitfly.checkpoint", "version": 1, "vitfly_version": vitfly.__version__, "source": "x"}


def test_the_wheel_lists_every_package_and_config_folder():
    tomllib = pytest.importorskip("tomllib")
    setup = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    code = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "vitfly").rglob("__init__.py")}
    configs = {".".join(("vitfly", *d.relative_to(REPO).parts)) for d in (REPO / "configs").rglob("*")
               if d.is_dir() and any(d.glob("*.yaml"))} | {"vitfly.configs"}
    assert set(setup["packages"]) == code | configs | {"vitfly.weights"}, "pyproject [tool.setuptools] packages"
    assert all(setup["package-data"].get(p) == ["*.yaml"] for p in configs), "pyproject package-data of configs"


def test_installed_reads_its_own_configs_and_weights(installed):
    assert packaged.source_root() is None
    assert packaged.config_path("quickstart") == installed / "configs" / "quickstart.yaml"
    assert packaged.config_path("configs/collect/spheres.yaml") == installed / "configs" / "collect" / "spheres.yaml"
    assert weights_dir() == installed / "weights"
    from vitfly.zoo import load_pretrained

    assert sum(p.numel() for p in load_pretrained("convnet").parameters()) == 235_269


def test_installed_refuses_to_publish_into_itself(installed, tmp_path, monkeypatch, capsys):
    torch.manual_seed(0)
    ckpt = tmp_path / "c.ckpt"
    save_checkpoint(create_model("convnet"), "convnet", True, ckpt)
    before = {p.name: p.stat().st_mtime_ns for p in (installed / "weights").iterdir()}
    assert main(["publish-weights", str(ckpt), "--name", "mine"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "vitfly is installed as a package" in err[0] and "--weights-dir" in err[0]
    with pytest.raises(VitflyError, match="train.publish_weights: vitfly is installed"):  # before any training
        load_reproduce_config("reproduce", "tiny", {"train": {"publish_weights": True}})
    rows = {"spheres": [{"policy": "convnet", "env": "spheres", "speed": 3.0, "success_paper_rate": 0.5,
                         "trials": 2}]}
    _record_closed_loop(load_reproduce_config("reproduce", "shipped"), rows)  # the shipped preset's report
    assert "closed-loop numbers kept in results.json only" in capsys.readouterr().out
    assert {p.name: p.stat().st_mtime_ns for p in (installed / "weights").iterdir()} == before
    # a directory given, or $VITFLY_WEIGHTS_DIR, is written
    mine = tmp_path / "mine"
    assert save_pretrained(ckpt, "mine", {}, mine) == mine / "mine.safetensors"
    monkeypatch.setenv(WEIGHTS_ENV, str(mine))
    assert publish_dir() == mine
    entry = json.loads((mine / "manifest.json").read_text())["models"]["mine"]
    assert entry["vitfly_version"] == vitfly.__version__


def test_a_clone_publishes_into_its_weights(elsewhere):
    assert publish_dir() == REPO / "weights" == weights_dir()
