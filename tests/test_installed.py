"""vitfly as another project depends on it: the wheel of this tree installed (not editable) into a fresh venv,
and run from an empty directory, nothing from the clone in reach.

The venv sees the test environment's packages (torch, Lightning, ...) through a ``.pth`` file listing its import
path: a venv made with ``--system-site-packages`` from inside a venv sees the base interpreter's packages, not the
venv's. A ``.pth`` line adds a directory without running the ``.pth`` files in it, so the outer environment's
editable vitfly (an import hook installed by such a file) stays out of reach; the tests check that the vitfly
that runs is the venv's. Offline: the wheel is built without build isolation and installed without
dependencies. ``$VITFLY_WHEEL`` tests a wheel built elsewhere (``.ci/run`` hands over the one it built from the
sdist).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

# about 1.5 min: a wheel, two venvs, five evaluation trials and the tiny main job; the tests share one venv, so
# they run on one xdist worker (`--dist loadgroup`)
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("installed_wheel")]

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "vitfly", "configs", "weights")


def copy_tree(src: Path) -> Path:
    """What the build reads, copied (the tree gets no build/ or egg-info)."""
    pytest.importorskip("setuptools", minversion="77", reason="building vitfly offline needs setuptools >= 77 "
                        "(pip install -e '.[dev]')")
    src.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, src / name)
    return src


def build_wheel(out: Path) -> Path:
    """The wheel of this tree, built offline."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(copy_tree(out / "src")), "--no-deps",
                    "--no-build-isolation", "--no-index", "-q", "-w", str(out / "dist")], check=True)
    return next((out / "dist").glob("vitfly-*.whl"))


def outer_paths() -> list[str]:
    """The test environment's import path (its site-packages and what their .pth files added), less this tree's
    sources (a venv inside the checkout, as CI's .venv, stays: it holds the dependencies)."""
    env = Path(sys.prefix).resolve()

    def ours(p: Path) -> bool:
        return p.is_relative_to(REPO) and not p.is_relative_to(env)

    return [p for p in sys.path if p and Path(p).is_dir() and not ours(Path(p).resolve())]


def make_venv(root: Path, *install: str) -> Path:
    """A venv with ``pip install --no-deps *install`` (the wheel, or ``-e DIR``); the test environment's
    site-packages behind it."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root)], check=True)
    python = root / "bin" / "python"
    inner = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                                check=True, capture_output=True, text=True).stdout.strip())
    (inner / "zz_test_environment.pth").write_text("\n".join(outer_paths()) + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index",
                    "--no-build-isolation", "-q", *install], check=True)
    return root


@pytest.fixture(scope="module")
def venv(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("installed")
    wheel = Path(os.environ["VITFLY_WHEEL"]) if os.environ.get("VITFLY_WHEEL") else build_wheel(tmp)
    names = zipfile.ZipFile(wheel).namelist()
    shipped = {p.relative_to(REPO).as_posix() for kind in ("configs", "weights") for p in (REPO / kind).rglob("*")
               if p.is_file() and p.suffix in (".yaml", ".json", ".safetensors")}
    missing = sorted(s for s in shipped if f"vitfly/{s}" not in names)
    assert not missing, f"{wheel.name} lacks {missing}"
    return make_venv(tmp / "venv", str(wheel))


ENV = {**{k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VITFLY_WEIGHTS_DIR")},
       "MPLBACKEND": "Agg", "WANDB_MODE": "offline"}


@pytest.fixture
def run(venv, tmp_path):
    """``vitfly ARGS`` from the venv, in an empty directory, without PYTHONPATH or a weights override."""
    cwd = tmp_path / "elsewhere"
    cwd.mkdir()

    def vitfly(*args: str, rc: int = 0) -> subprocess.CompletedProcess:
        done = subprocess.run([str(venv / "bin" / "vitfly"), *args], cwd=cwd, env=ENV, capture_output=True,
                              text=True, timeout=600)
        assert done.returncode == rc, f"vitfly {' '.join(args)}: exit {done.returncode}\n{done.stdout}\n{done.stderr}"
        return done

    vitfly.cwd = cwd
    return vitfly


def test_the_installed_vitfly_runs_with_its_own_configs_and_weights(venv, run):
    from vitfly import __version__

    site_dir = next((venv / "lib").glob("python*/site-packages"))
    version = run("--version").stdout.strip()
    assert version.startswith(f"vitfly {__version__} from {site_dir / 'vitfly'} ")
    listing = run("configs").stdout
    assert str(site_dir / "vitfly" / "configs") in listing and "fit/vit_lstm" in listing
    weights = run("weights").stdout
    assert str(site_dir / "vitfly" / "weights") in weights and "convnet_paper  convnet" in weights
    out = run("evaluate", "--policy", "pretrained:convnet", "--speeds", "4", "--trials", "1", "--timeout", "3",
              "--out", "eval", "--no-gif", "--no-plots", "--no-progress").stdout
    assert "1 trials flown" in out
    record = json.loads((run.cwd / "eval" / "trials.jsonl").read_text().splitlines()[0])
    assert record["extra"]["vitfly_version"] == __version__
    assert "class_path: vitfly.zoo.policy.vit_lstm" in run("fit", "--config", "fit/vit_lstm", "--print_config").stdout
    # every shipped network flies from the wheel: the same command for the others, in one process of the
    # installed vitfly (vitfly.cli.main, what the `vitfly` script calls) rather than a process start each
    others = ("convnet_paper", "lstmnet", "unet_lstm", "vit", "vit_lstm")
    code = ("import sys; from vitfly.cli import main; sys.exit(max(main(['evaluate', '--policy', f'pretrained:{n}', "
            "'--speeds', '4', '--trials', '1', '--timeout', '1.5', '--out', 'eval', '--no-gif', '--no-plots', "
            f"'--no-progress']) for n in {others!r}))")
    done = subprocess.run([str(venv / "bin" / "python"), "-c", code], cwd=run.cwd, env=ENV, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count("1 trials flown") == len(others)
    policies = {json.loads(line)["policy"] for line in (run.cwd / "eval" / "trials.jsonl").read_text().splitlines()}
    assert policies == {"convnet", *others}
    assert sorted(os.listdir(run.cwd)) == ["eval"]  # nothing else written here, no weights/ or configs/ wanted


def test_the_main_job_by_config_name(venv, run):
    out = run("pipeline", "--config", "quickstart_tiny", "--no-progress").stdout
    assert "[collect]" in out and "[train]" in out and "success over all trials" in out
    result = json.loads((run.cwd / "runs" / "quickstart-tiny" / "pipeline.json").read_text())
    assert set(result["success_paper"]) == {"convnet", "expert", "straight"}
    # the version that wrote them: dataset, checkpoint
    import h5py
    import torch

    from vitfly import __version__

    with h5py.File(run.cwd / "data" / "quickstart_tiny.h5", "r") as f:
        assert f.attrs["vitfly_version"] == __version__
    ckpt = run.cwd / "runs" / "quickstart-tiny" / "train" / "checkpoints" / "best.ckpt"
    assert torch.load(ckpt, map_location="cpu", weights_only=True)["vitfly"]["vitfly_version"] == __version__
    # publishing has no directory to write to: one line, the package's weights untouched
    weights = next((venv / "lib").glob("python*/site-packages")) / "vitfly" / "weights"
    before = {p.name: p.stat().st_mtime_ns for p in weights.iterdir()}
    err = run("publish-weights", str(ckpt), "--name", "mine", rc=2).stderr.strip().splitlines()
    assert len(err) == 1 and "vitfly is installed as a package" in err[0]
    assert {p.name: p.stat().st_mtime_ns for p in weights.iterdir()} == before
    run("publish-weights", str(ckpt), "--name", "mine", "--weights-dir", "mine")
    assert json.loads((run.cwd / "mine" / "manifest.json").read_text())["models"]["mine"]["vitfly_version"]


def test_an_editable_install_reads_the_tree_it_points_at(tmp_path):
    src = copy_tree(tmp_path / "src")
    venv = make_venv(tmp_path / "venv", "-e", str(src))
    cwd = tmp_path / "elsewhere"
    cwd.mkdir()
    code = ("import vitfly; from vitfly.packaged import config_path; from vitfly.zoo.pretrained import publish_dir, "
            "weights_dir; from vitfly.zoo import load_pretrained; load_pretrained('convnet'); "
            "print(vitfly.__file__, config_path('quickstart'), weights_dir(), publish_dir())")
    out = subprocess.run([str(venv / "bin" / "python"), "-c", code], cwd=cwd, env=ENV, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == [str(src / "vitfly" / "__init__.py"), str(src / "configs" / "quickstart.yaml"),
                   str(src / "weights"), str(src / "weights")]
