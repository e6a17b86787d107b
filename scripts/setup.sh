#!/usr/bin/env bash
# Create .venv and install physgm with its pinned dependencies (CPU machines never pull an unpinned torch).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$(command -v python3.11 || command -v python3)}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade "pip>=24"
.venv/bin/python -m pip install --quiet -e ".[dev,view]"
.venv/bin/python -c "import torch, torchvision, warp, lightning, hydra, lpips, timm; print('setup: ok, torch', torch.__version__, 'warp', warp.__version__)"
