#!/usr/bin/env bash
# The GPU paths in ~10 minutes on one CUDA GPU, one JSON summary (see gpu_check.py). Without CUDA every part is
# reported as skipped and the script exits 0.
#   bash benchmarks/gpu_check.sh [--out outputs/gpu_check] [--minutes-nerf-sh 5]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
exec "$PY" benchmarks/gpu_check.py "$@"
