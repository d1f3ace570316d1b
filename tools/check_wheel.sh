#!/usr/bin/env bash
# Build geomjax's wheel and prove it works as users get it: installed (not editable) into a fresh
# venv, imported from a directory outside the checkout (so nothing is found through the source
# tree), with one op run on each backend and one through torch_bridge.
#
# Dependencies come from the same indexes as tools/setup.sh (pip's cache makes a second install
# cheap); torch is the CPU build that setup.sh installs, so no CUDA build is pulled in.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
WORK=$(mktemp -d "${TMPDIR:-/tmp}/geomjax-wheel.XXXXXX")
trap 'rm -rf "$WORK"' EXIT
PYTHON=${PYTHON:-python3}

.venv/bin/python -m pip wheel --quiet --disable-pip-version-check --no-deps --wheel-dir "$WORK/dist" "$ROOT"
wheel=$(ls "$WORK"/dist/geomjax-*.whl)
echo "built $(basename "$wheel")"
"$PYTHON" -m venv "$WORK/venv"
PIP=("$WORK/venv/bin/python" -m pip --disable-pip-version-check --quiet)
"${PIP[@]}" install "${GEOMJAX_TORCH_SPEC:-torch==$(.venv/bin/python -c 'import torch; print(torch.__version__.split("+")[0])')}"
"${PIP[@]}" install "$wheel[torch]"

cd "$WORK"
"$WORK/venv/bin/python" - "$ROOT" <<'PY'
import pathlib
import sys

import jax.numpy as jnp
import numpy as np
import torch

import geomjax
import torch_bridge
import warp_ffi

root = pathlib.Path(sys.argv[1]).resolve()
for module in (geomjax, torch_bridge, warp_ffi):
    where = pathlib.Path(module.__file__).resolve()
    assert root not in where.parents, f"{module.__name__} imported from the checkout ({where}), not the wheel"

points = jnp.array([[0.25, 0.25, 0.5], [0.75, 0.25, 0.5]])
controls = jnp.array([[0.0, 0.0, 0.5], [1.0, 1.0, 0.5]])
moves = jnp.array([[0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
by_backend = {
    impl: np.asarray(geomjax.morph_points(points, controls, moves, radius=0.8, implementation=impl))
    for impl in ("jax", "warp")
}
np.testing.assert_allclose(by_backend["warp"], by_backend["jax"], rtol=1e-6)
bridged = torch_bridge.morph_points(torch.tensor(np.asarray(points)), torch.tensor(np.asarray(controls)), torch.tensor(np.asarray(moves)), radius=0.8)
np.testing.assert_allclose(bridged.numpy(), by_backend["jax"], rtol=1e-6)
print("wheel ok:", geomjax.__version__, "| morph_points on jax, warp and torch_bridge agree")
PY
