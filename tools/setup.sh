#!/usr/bin/env bash
# Create .venv (if needed) and install geomjax with its torch, test, example and io extras.
#
# torch: a bare "torch" requirement on a machine without torch pulls a CUDA build of several GB.
# We keep any torch that is already installed and otherwise install the CPU build 2.13.0, which pip
# finds locally on our machines (override with GEOMJAX_TORCH_SPEC, e.g. "torch==2.13.0+cu126").
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -m venv .venv
fi
PIP=(.venv/bin/python -m pip --disable-pip-version-check --quiet)
"${PIP[@]}" install --upgrade pip
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
    "${PIP[@]}" install "${GEOMJAX_TORCH_SPEC:-torch==2.13.0}"
fi
"${PIP[@]}" install -e ".[torch,test,examples,io]"
.venv/bin/python -c "import geomjax, torch_bridge, warp_ffi, torch, jax; print('geomjax', geomjax.__version__, '| jax', jax.__version__, '| torch', torch.__version__)"
