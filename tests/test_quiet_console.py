"""Importing the packages and running ops prints nothing (DESIGN.md: a quiet console).

Run in a fresh interpreter: Warp's C library writes its CUDA-driver warning to the process's
stderr file descriptor once, at ``warp.init()``, which pytest's capture of an already-imported
module would never see.
"""

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import jax.numpy as jnp
    import torch

    import geomjax
    import torch_bridge
    import warp_ffi

    sphere = geomjax.icosphere(1)
    controls = sphere.points[:4]
    moved = geomjax.morph_points(sphere.points, controls, 0.1 * controls, radius=0.5, implementation="warp")
    distances = geomjax.signed_distance_field(sphere.points, sphere.cells, jnp.zeros((2, 3)), implementation="warp")
    energy = torch_bridge.simplex_measure_energy(torch.rand(4, 3), torch.rand(4, 3), torch.tensor([[0, 1, 2], [1, 2, 3]]))
    print(float(moved.sum()), float(distances[0].sum()), float(energy))
    """
)


def test_imports_and_first_calls_print_nothing_to_stderr():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert result.stderr == "", result.stderr
    assert len(result.stdout.split()) == 3, result.stdout
