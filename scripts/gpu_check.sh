#!/usr/bin/env bash
# The CUDA paths against the CPU ones (rasterizer forward and backward, Sinkhorn, one stylization) and
# paper-scale timings on the GPU, in at most 8 minutes: results/benchmarks/gpu_check.csv (and $OUT/ when
# set). On a machine without CUDA it says so and exits 0. Details: benchmarks/gpu_check.py.
#   PYTHON   the interpreter (default .venv/bin/python, else python3)
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || command -v python3 )}"
OUT_CSV="results/benchmarks/gpu_check.csv"
rc=0
timeout 470 "$PY" benchmarks/gpu_check.py --out "$OUT_CSV" "$@" || rc=$?
if [ -n "${OUT:-}" ] && [ -f "$OUT_CSV" ]; then cp "$OUT_CSV" "$OUT/"; fi
[ "$rc" = 124 ] && echo "gpu_check: stopped at its 8-minute limit; the rows measured so far are in $OUT_CSV"
exit "$rc"
