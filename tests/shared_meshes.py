"""The shared real meshes (``../shared/meshes`` beside the checkout) for the tests that use them.

Public libigl tutorial meshes (see the README there): scans, CAD parts, open and tetrahedral
meshes. Tests that read them are marked ``requires_shared_meshes`` and skip where the folder is
absent (a checkout on its own). Surfaces are normalised to the unit box as in
``benchmarks/bench_real_meshes.py``: minus the bounding-box minimum, over the largest extent.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

MESH_DIR = Path(__file__).resolve().parents[2] / "shared" / "meshes"

requires_shared_meshes = pytest.mark.skipif(not MESH_DIR.is_dir(), reason="the shared meshes are not beside the checkout")


@functools.cache
def _shared_cells(name: str, cell_type: str) -> tuple[np.ndarray, np.ndarray]:
    """``(points (V, 3) float64 in the unit box, cells (C, k) int32)`` of one cell type of a file."""
    meshio = pytest.importorskip("meshio")
    mesh = meshio.read(MESH_DIR / name)
    cells = np.concatenate([block.data for block in mesh.cells if block.type == cell_type]).astype(np.int32)
    points = np.asarray(mesh.points, np.float64)
    points = points - points.min(axis=0)
    return points / points.max(), cells


def shared_surface(name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(points (V, 3) float64 in the unit box, triangles (F, 3) int32)`` of a shared mesh file."""
    return _shared_cells(name, "triangle")


def shared_volume(name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(points (V, 3) float64 in the unit box, tetrahedra (C, 4) int32)`` of a shared volume mesh file.

    Normalised as :func:`shared_surface`, so the two agree on the same file (its boundary triangles).
    """
    return _shared_cells(name, "tetra")
