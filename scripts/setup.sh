#!/usr/bin/env bash
# Create .venv, install wast3d with its pinned dependencies, build the native CPU kernels.
# Idempotent: a second run only checks (a few seconds).
#   WAST3D_TORCH   torch requirements (default "torch==2.14.1 torchvision==0.29.1": open_clip needs
#                  torchvision, and this is the newest pair that imports together on this project's
#                  machines, where both lie on disk; a CUDA build that also runs on the CPU, ~5.5 GB).
#   WAST3D_EXTRAS  pip extras (default "dev"; add "cuda" for gsplat, "keops" for pykeops).
#   PYTHON         interpreter for the venv (default python3.11, else python3).
#   WAST3D_NEED_GB free disk a new .venv asks for before it starts (default 8).
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-$(command -v python3.11 || command -v python3)}"
if [ ! -x .venv/bin/python ]; then
  # a new venv holds ~7 GB (torch's CUDA build 5.5 GB): say so before pip fails half-way with ENOSPC
  need_gb="${WAST3D_NEED_GB:-8}"
  free_gb=$(df -Pk . | awk 'NR==2 {print int($4 / 1048576)}')
  if [ "$free_gb" -lt "$need_gb" ]; then
    echo "setup: $(pwd) has ${free_gb} GB free; a new .venv needs about ${need_gb} GB (set WAST3D_NEED_GB to override)" >&2
    exit 1
  fi
  "$PY" -m venv .venv
fi
PIP=(.venv/bin/python -m pip install -q --disable-pip-version-check)
# torch first and alone, so that nothing else can pull a multi-GB CUDA build on a CPU machine
"${PIP[@]}" ${WAST3D_TORCH:-torch==2.14.1 torchvision==0.29.1} 2>&1 | { grep -v "^WARNING: Location" || true; }
"${PIP[@]}" -c requirements/constraints.txt -e ".[${WAST3D_EXTRAS:-dev}]" 2>&1 | { grep -v "^WARNING: Location" || true; }
.venv/bin/python -c "import wast3d, torch; print('wast3d ready: torch', torch.__version__, '| cuda', torch.cuda.is_available())"
.venv/bin/wast3d build-ext >/dev/null || echo "note: native CPU kernels not built; the PyTorch reference rasterizer will be used"
