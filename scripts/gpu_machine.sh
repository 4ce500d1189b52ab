#!/usr/bin/env bash
# vitfly end to end (collect, train, evaluate) on the project's GPU machine.
#
# That machine runs Python 3.12 with PyTorch, Lightning, timm, h5py, ONNX Runtime, matplotlib, scipy, rich,
# PyYAML, torchmetrics, TensorBoard and onnxscript preinstalled (/work/.library/device/KINDS.md), reaches no
# package index, and takes at most 64 MiB of carried files. So vitfly runs there from its source tree
# (PYTHONPATH, no `pip install`: its torch pin would ask for a torch the machine cannot fetch), on the native
# physics back end (no pybullet wheel exists for CPython 3.12), with the few pure-Python wheels it lacks
# carried in .whl/:
#
#   scripts/gpu_machine.sh fetch          # here, with pip and an index: the wheels into .whl/ (about 1 MiB)
#   scripts/gpu_machine.sh run [DIR]      # there: install them to /tmp/site, check, run the pipeline
#
# With the device tool (its README, "Notes"): once, `echo /.whl/ >> .git/info/exclude` and the fetch; then
#   run(command="scripts/gpu_machine.sh run $OUT", carry=[".whl"], timeout_s=600)
# DIR (default runs/gpu_machine) receives what comes back small: pipeline.json, summary.md, timings.txt and
# run.log; the dataset and checkpoints stay in /tmp/vitfly (CONFIG=... picks another
# pipeline YAML, default scripts/gpu_machine.yaml). The pipeline alone (150 trajectories, 6 epochs,
# 3 x 40 trials) took 1.5 minutes on the 2-core CPU machine of docs/install.md; on 16 cores and a GPU, less.
set -euo pipefail
cd "$(dirname "$0")/.."

# vitfly's dependencies that the machine lacks: jsonargparse and omegaconf (with theirs) for `vitfly fit`
# (LightningCLI). The pipeline itself needs none of them; wandb (optional, ~25 MiB with its needs) is left out.
WHEELS=(jsonargparse==4.53.0 docstring-parser==0.18.0 typeshed-client==2.14.0 omegaconf==2.4.0)

case "${1:-}" in
fetch)
    rm -rf .whl && mkdir -p .whl
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform any -d .whl "${WHEELS[@]}"
    ls -l .whl && du -sh .whl
    ;;
run)
    out=${2:-runs/gpu_machine}
    config=${CONFIG:-scripts/gpu_machine.yaml}
    work=${WORK:-/tmp/vitfly}
    mkdir -p "$out" "$work"
    log="$out/run.log"
    start=$(date +%s)
    if compgen -G ".whl/*.whl" > /dev/null; then
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    fi
    export PYTHONPATH="/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}" MPLBACKEND=Agg WANDB_MODE=offline PYTHONUNBUFFERED=1
    python3 - <<'PY' 2>&1 | tee "$log"
import importlib, platform, torch
print(f"python {platform.python_version()}, torch {torch.__version__}, cuda {torch.cuda.is_available()}"
      + (f" ({torch.cuda.get_device_name(0)})" if torch.cuda.is_available() else ""))
for name in ("lightning", "timm", "h5py", "onnxruntime", "numpy", "scipy", "matplotlib", "jsonargparse", "omegaconf"):
    try:
        print(f"  {name} {importlib.import_module(name).__version__}")
    except ImportError as err:
        print(f"  {name}: missing ({err})")
from vitfly.sim.physics import pybullet_available, resolve_physics
print(f"  physics: pybullet {'installed' if pybullet_available() else 'not installed'}; auto -> {resolve_physics('auto')}")
PY
    python3 -m vitfly.cli pipeline --config "$config" --out "$work/run" --data "$work/data.h5" --no-progress \
        2>&1 | tee -a "$log"
    end=$(date +%s)
    cp "$work/run/pipeline.json" "$work/run/eval/summary.md" "$out/"  # 4 files: the device tool returns 8 at most
    python3 - "$work/run/pipeline.json" "$((end - start))" <<'PY' | tee "$out/timings.txt"
import json, sys
p = json.load(open(sys.argv[1]))
t = p["timings_s"]
print(f"whole script {sys.argv[2]} s; pipeline: collect {t['collect_s']:.0f} s, train {t['train_s']:.0f} s, "
      f"evaluate {t['evaluate_s']:.0f} s, report {t['report_s']:.0f} s")
print("success: " + ", ".join(f"{k} {100 * v:.0f} %" for k, v in sorted(p["success_rate"].items())))
PY
    ;;
*)
    sed -n '2,24p' "$0"
    exit 2
    ;;
esac
