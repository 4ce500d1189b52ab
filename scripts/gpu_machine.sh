#!/usr/bin/env bash
# The old command line of the GPU machine's pipeline; scripts/gpu.py is the one entry point now
# (docs/reproduce.md, "Work on a GPU machine"):
#
#   scripts/gpu_machine.sh fetch          # = python3 scripts/gpu.py wheels: the wheels the machine lacks, into .whl/
#   scripts/gpu_machine.sh run [DIR]      # = python3 scripts/gpu.py pipeline --out DIR
#
# CONFIG=... and WORK=... still pick the pipeline YAML (default scripts/gpu_machine.yaml) and the work folder.
set -euo pipefail
cd "$(dirname "$0")/.."
case "${1:-}" in
fetch) exec python3 scripts/gpu.py wheels ;;
run) exec python3 scripts/gpu.py pipeline --out "${2:-runs/gpu_machine}" ;;
*)
    sed -n '2,8p' "$0"
    exit 2
    ;;
esac
