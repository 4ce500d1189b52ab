"""The GPU machine itself: the wheels it lacks, its setup before every job there, and the pipeline end to end.

That machine runs Python 3.12 with PyTorch, Lightning, timm, h5py, ONNX Runtime, matplotlib, scipy, rich,
PyYAML, torchmetrics, TensorBoard and onnxscript preinstalled (/work/.library/device/KINDS.md), reaches no
package index, and takes the working tree and carried files, 64 MiB together. So vitfly runs there from its source tree
(PYTHONPATH, no ``pip install``: its torch pin would ask for a torch the machine cannot fetch), on the native
physics back end (no pybullet wheel exists for CPython 3.12), with the few pure-Python wheels it lacks carried
in ``.whl/``:

    python3 scripts/gpu.py wheels              # here, with pip and an index: the wheels into .whl/ (about 1 MiB)
    python3 scripts/gpu.py pipeline --out $OUT # there: vitfly pipeline (scripts/gpu_machine.yaml), packed

Every subcommand that runs there (train, study, evaluate, pipeline) first calls :func:`prepare`: the carried
wheels installed to /tmp/site (once a machine) and put on the path of the command and of every process it
starts. ``pipeline`` runs ``vitfly pipeline`` (the quick start with 14 collect workers, training on the GPU)
with the dataset and checkpoints in ``--work``, and returns ``run.log``, ``gpu_pipeline.json`` (versions,
timings, success rates, the pieces' manifest) and ``pipeline.tar.NNN`` (pipeline.json and the evaluation's
records and reports); ``scripts/gpu.py unpack DIR --into runs/gpu_machine`` unpacks them here.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
WHEELS_DIR = ROOT / ".whl"
SITE = Path("/tmp/site")
REPORT = "gpu_pipeline.json"  # versions, timings, success, and the manifest of pipeline.tar.NNN
# vitfly's dependencies that the machine lacks: jsonargparse and omegaconf (with theirs) for `vitfly fit`
# (LightningCLI). The pipeline itself needs none of them; wandb (optional, ~25 MiB with its needs) is left out.
WHEELS = ("jsonargparse==4.53.0", "docstring-parser==0.18.0", "typeshed-client==2.14.0", "omegaconf==2.4.0")
CHECKED = ("lightning", "timm", "h5py", "onnxruntime", "numpy", "scipy", "matplotlib", "jsonargparse", "omegaconf")


def fetch_wheels(args: argparse.Namespace) -> int:
    """Here: the wheels the machine lacks, for CPython 3.12 on x86-64, into ``.whl/`` (which the call carries)."""
    dest = Path(args.dest)
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    cmd = [args.python, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version",
           "3.12", "--implementation", "cp", "--platform", "manylinux_2_28_x86_64", "--platform",
           "manylinux_2_17_x86_64", "--platform", "any", "-d", str(dest), *WHEELS]
    subprocess.run(cmd, check=True)
    wheels = sorted(dest.glob("*.whl"))
    for whl in wheels:
        print(f"{whl.stat().st_size / 2**10:8.0f} KiB  {whl.name}")
    print(f"{dest}: {len(wheels)} wheels; carry it: run(..., carry=[\"{dest.name}\"])")
    return 0


def prepare() -> None:
    """There: the carried wheels installed to /tmp/site once, and /tmp/site and the tree on the path of this
    process and of the ones it starts. Nothing to do without ``.whl/`` (here, or a machine that has them all)."""
    wheels = sorted(WHEELS_DIR.glob("*.whl"))
    os.environ.setdefault("MPLBACKEND", "Agg")
    os.environ.setdefault("WANDB_MODE", "offline")
    os.environ["PYTHONUNBUFFERED"] = "1"
    if not wheels:
        return
    stamp = SITE / ".vitfly-wheels"
    names = "\n".join(w.name for w in wheels)
    if not (stamp.exists() and stamp.read_text() == names):
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
                        "--no-cache-dir", "--upgrade", "--target", str(SITE), *map(str, wheels)], check=True)
        stamp.write_text(names)
    if str(SITE) not in sys.path:
        sys.path.insert(0, str(SITE))
    path = [str(SITE), str(ROOT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    os.environ["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(path))


def versions() -> list[str]:
    """Python, torch and the packages vitfly needs, as found here; the physics back end ``auto`` picks."""
    import torch

    from vitfly.sim.physics import pybullet_available, resolve_physics

    cuda = f" ({torch.cuda.get_device_name(0)})" if torch.cuda.is_available() else ""
    lines = [f"python {platform.python_version()}, torch {torch.__version__}, cuda {torch.cuda.is_available()}{cuda}"]
    for name in CHECKED:
        try:
            lines.append(f"  {name} {importlib.import_module(name).__version__}")
        except ImportError as err:
            lines.append(f"  {name}: missing ({err})")
    lines.append(f"  physics: pybullet {'installed' if pybullet_available() else 'not installed'}; "
                 f"auto -> {resolve_physics('auto')}")
    return lines


def pipeline(args: argparse.Namespace) -> int:
    """There: ``vitfly pipeline`` end to end; its outcome and evaluation records packed for the trip back."""
    from scripts.gpu_evaluate import copy_records
    from scripts.gpu_pack import fresh_dir, pack

    start = time.monotonic()
    out, work = Path(args.out), Path(args.work)
    out.mkdir(parents=True, exist_ok=True)
    (out / REPORT).unlink(missing_ok=True)
    run = work / "run"
    found = versions()
    print("\n".join(found), flush=True)
    cmd = [sys.executable, "-m", "vitfly.cli", "pipeline", "--config", args.config, "--out", str(run),
           "--data", str(work / "data.h5"), "--no-progress"]
    with open(out / "run.log", "w") as logfile:
        logfile.write("\n".join(found) + "\n")
        logfile.flush()
        rc = subprocess.run(cmd, stdout=logfile, stderr=subprocess.STDOUT, cwd=ROOT).returncode
    report: dict = {"versions": found, "rc": rc, "elapsed_s": round(time.monotonic() - start, 1)}
    stage = fresh_dir(work / "stage")
    if (run / "pipeline.json").exists():
        outcome = json.loads((run / "pipeline.json").read_text())
        report.update({k: outcome.get(k) for k in ("timings_s", "success_paper", "success_strict")})
        shutil.copy(run / "pipeline.json", stage / "pipeline.json")
    copy_records(run / "eval", stage / "eval")
    entries = [(p.name, p) for p in sorted(stage.iterdir())]
    report["pack"] = pack(entries, out, "pipeline", work)
    (out / REPORT).write_text(json.dumps(report, indent=1) + "\n")
    t = report.get("timings_s") or {}
    print(f"whole command {report['elapsed_s']:.0f} s; pipeline rc {rc}: "
          + ", ".join(f"{k.removesuffix('_s')} {v:.0f} s" for k, v in t.items()))
    rates = report.get("success_paper") or {}
    if rates:
        print("success (paper): " + ", ".join(f"{k} {100 * v:.0f} %" for k, v in sorted(rates.items())))
    return rc


def unpack(src: Path, into: Path) -> None:
    """Here: pipeline.json and the evaluation's records into ``into``."""
    from scripts.gpu_pack import unpack as unpack_pieces

    unpack_pieces(src, "pipeline", into, REPORT)
    print(f"{into}: pipeline.json, eval/ unpacked")


def add_commands(sub) -> dict:
    """``wheels`` and ``pipeline`` on ``scripts/gpu.py``'s subparsers; returns name -> handler."""
    w = sub.add_parser("wheels", help="here: the pure-Python wheels the machine lacks, into .whl/")
    w.add_argument("--dest", default=str(WHEELS_DIR))
    w.add_argument("--python", default="python3", help="the Python whose pip downloads them")
    p = sub.add_parser("pipeline", help="there: vitfly pipeline end to end (scripts/gpu_machine.yaml), packed")
    p.add_argument("--out", default="runs/gpu_machine", help="what comes back: run.log, gpu_pipeline.json, pieces")
    p.add_argument("--config", default=os.environ.get("CONFIG", "scripts/gpu_machine.yaml"))
    p.add_argument("--work", default=os.environ.get("WORK", "/tmp/vitfly"), help="the dataset and the run")
    return {"wheels": fetch_wheels, "pipeline": pipeline}
