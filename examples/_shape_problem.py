"""The shape-matching problem shared by ``shape_optimization_jax.py`` and ``shape_optimization_torch.py``.

A unit icosphere is deformed by a Bernstein free-form-deformation lattice until it matches a
peanut: an elongated body pinched at its waist, made by deforming a second, finer icosphere. The
objective is backend-agnostic: it calls the ops by name on a module (``geomjax`` for JAX arrays,
``torch_bridge`` for torch tensors, which share the reference signatures) and only uses array
methods both libraries have, so the two examples optimise literally the same function.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

import geomjax

# Relative weights of the regularisers against the data term (mean squared signed distance).
# The strain weight is small: matching the target needs a 35% stretch, and strain only has to stop
# the surface from sliding and bunching tangentially where the SDF term cannot see it.
STRAIN_WEIGHT = 2e-3
INVERSION_WEIGHT = 10.0
VOLUME_WEIGHT = 0.1

# Problem sizes of the examples' --smoke, default and --full runs, and their Adam step size.
SIZES = {
    "smoke": {"subdivisions": 2, "lattice_shape": (4, 3, 3), "iterations": 40},
    "default": {"subdivisions": 4, "lattice_shape": (6, 4, 4), "iterations": 600},
    "full": {"subdivisions": 5, "lattice_shape": (8, 6, 6), "iterations": 2000},
}
LEARNING_RATE = 0.02


@dataclass(frozen=True)
class ShapeProblem:
    """Arrays (NumPy, float32 coordinates, int32 topology) and settings of one problem size.

    ``probe_points``/``probe_tets`` fill the lattice box with tetrahedra: they follow the same
    free-form deformation, and their inversion energy keeps the map itself from folding over.
    """

    source_points: np.ndarray
    triangles: np.ndarray
    target_points: np.ndarray
    target_triangles: np.ndarray
    probe_points: np.ndarray
    probe_tets: np.ndarray
    lattice_shape: tuple[int, int, int]
    origin: tuple[float, float, float]
    extent: tuple[float, float, float]
    source_area: float
    target_volume_ratio: float

    def initial_lattice(self) -> np.ndarray:
        """The zero lattice ``(*lattice_shape, 3)``: the identity map."""
        return np.zeros((*self.lattice_shape, 3), np.float32)


def peanut(points: np.ndarray) -> np.ndarray:
    """Map unit-sphere points to the target: stretched along x, narrowed in y/z, pinched at x = 0."""
    x, y, z = points.T
    waist = 1.0 - 0.35 * np.exp(-((x / 0.45) ** 2))
    return np.stack([1.35 * x, 0.8 * waist * y, 0.75 * waist * z], axis=1).astype(np.float32)


def make_problem(subdivisions: int, lattice_shape: tuple[int, int, int], probe_cells: int = 4) -> ShapeProblem:
    """Build the problem: source icosphere of ``subdivisions``, a target one level finer."""
    source = geomjax.icosphere(subdivisions, dtype=np.float32)
    target = geomjax.icosphere(subdivisions + 1, dtype=np.float32)
    source_points = np.asarray(source.points)
    triangles = np.asarray(source.cells)
    target_points = peanut(np.asarray(target.points))
    target_triangles = np.asarray(target.cells)

    origin = (-1.1, -1.1, -1.1)
    extent = (2.2, 2.2, 2.2)
    # The probe box sits just inside the lattice box, so no probe vertex is rounded outside it
    # (points outside stay fixed, which would pin a tetrahedron corner and fake an inversion).
    probe = geomjax.tetrahedralized_box(
        probe_cells, probe_cells, probe_cells, origin=tuple(o + 0.01 for o in origin),
        extent=tuple(e - 0.02 for e in extent), dtype=np.float32,
    )
    return ShapeProblem(
        source_points=source_points,
        triangles=triangles,
        target_points=target_points,
        target_triangles=target_triangles,
        probe_points=np.asarray(probe.points),
        probe_tets=np.asarray(probe.cells),
        lattice_shape=tuple(lattice_shape),
        origin=origin,
        extent=extent,
        source_area=float(surface_area(source_points, triangles)),
        target_volume_ratio=float(enclosed_volume(target_points, target_triangles) / enclosed_volume(source_points, triangles)),
    )


def objective_terms(ops, lattice, source_points, triangles, target_points, target_triangles, probe_points, probe_tets, problem: ShapeProblem):
    """The weighted loss terms of ``lattice``, as a dict of scalars of the arrays' library.

    ``ops`` is ``geomjax`` or ``torch_bridge``; the arrays are that library's (same dtype).
    """
    def deform(points):
        return ops.free_form_deform_points(points, lattice, origin=problem.origin, extent=problem.extent, basis="bernstein")

    surface = deform(source_points)
    signed_distance, _, _ = ops.signed_distance_field(target_points, target_triangles, surface)
    strain = ops.simplex_strain_energy(surface, source_points, triangles)
    inversion = ops.simplex_inversion_energy(deform(probe_points), probe_points, probe_tets)
    volume = ops.closed_surface_volume_energy(surface, source_points, triangles, target_ratio=problem.target_volume_ratio)
    return {
        "sdf": (signed_distance**2).mean(),
        "strain": STRAIN_WEIGHT * strain / problem.source_area,
        "inversion": INVERSION_WEIGHT * inversion,
        "volume": VOLUME_WEIGHT * volume,
    }


def enclosed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    a, b, c = (points[triangles[:, k]].astype(np.float64) for k in range(3))
    return float(np.einsum("fi,fi->", a, np.cross(b, c)) / 6.0)


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit vertex normals: the area-weighted sum of the adjacent triangles' normals."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    face_normals = np.cross(b - a, c - a)
    normals = np.zeros_like(points)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face_normals)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def surface_area(points: np.ndarray, triangles: np.ndarray) -> float:
    a, b, c = (points[triangles[:, k]].astype(np.float64) for k in range(3))
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def distance_report(surface: np.ndarray, problem: ShapeProblem) -> dict[str, float]:
    """Two-sided surface distance, measured with geomjax's SDF: deformed -> target and back."""
    to_target, _, _ = geomjax.signed_distance_field(jnp.asarray(problem.target_points), jnp.asarray(problem.target_triangles), jnp.asarray(surface, jnp.float32))
    to_surface, _, _ = geomjax.signed_distance_field(jnp.asarray(surface, jnp.float32), jnp.asarray(problem.triangles), jnp.asarray(problem.target_points))
    to_target, to_surface = np.abs(np.asarray(to_target)), np.abs(np.asarray(to_surface))
    return {
        "mean": float(0.5 * (to_target.mean() + to_surface.mean())),
        "hausdorff": float(max(to_target.max(), to_surface.max())),
    }
