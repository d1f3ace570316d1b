"""Real meshes: how ``sobolev_deform_points`` converges and ``remeshing`` keeps topology on public, imperfect geometry.

Data: the libigl tutorial meshes in ``../shared/meshes/`` next to the checkout (``README.md``
there; ``GEOMJAX_MESH_DIR`` overrides the folder), read with
``meshio``: eight triangle surfaces (``triangle`` cells) and two tetrahedral volumes (``.mesh``,
their ``tetra`` cells; the boundary triangles are ignored), each normalised to the unit box (minus
the bounding-box minimum, divided by the largest extent, float64); plus ``geomjax.icosphere(6)``
(40,962 vertices, the unit sphere, as in ``bench_sobolev.py``) as the reference point. Every mesh
gets the same smooth displacement ``d_k = 0.01 sin(2 pi x_k + phase_k)`` and ``length_scale=0.05``.

Section "sobolev" (table ``real_meshes``), one row per mesh:

* ``check_rel_diff``: the system ``(m̄ I + l^2 K) u = m̄ d`` assembled independently here (P1
  stiffness from the Gram formula of ``geomjax.linalg._stiffness``, in NumPy, as a scipy CSR
  matrix) and solved directly (``splu``), against geomjax's float64 ``"jax"`` solution minus the
  points: ``||u_geomjax - u_direct||_F / ||u_direct||_F``. That solution is the default call's
  when it converges (a larger budget stops at the same iteration), else a call with
  ``max_iterations=10000``.
* ``jax_f64`` .. ``warp_f32``: whether geomjax converges with its defaults (``max_iterations=128``,
  tolerance 1e-10 in float64, 1e-6 in float32), and then the best-of-``--repeat`` time of a jitted
  call (compile excluded); ``failure`` holds the first line of the ``RuntimeError`` of those that
  did not converge.
* ``iters_f64`` / ``iters_f32``: the exact number of PCG iterations geomjax needs (``"jax"``, its
  multilevel preconditioner), from its internals: ``geomjax.linalg.jacobi_pcg`` on the same
  operator, preconditioner, right-hand side, start and tolerance, 4096 iterations at most
  (``">4096"``: not converged), in one run rather than a search over ``max_iterations``.
  ``jacobi_iters_f64`` / ``jacobi_iters_f32``: the same with the Jacobi preconditioner (geomjax's
  before the multilevel one, and still its choice for traced ``cells``). The default JAX call
  picks Jacobi where its a-priori bound on these Jacobi counts is at most 96 (here
  decimated-knight, icosphere(6), and 3holes in float32) and the V-cycle elsewhere; the Warp path
  always cycles. ``final_res_f32`` is the relative true residual that float32
  solve ends with: below 1e-6 when it converged, else the float32 residual floor after 4096
  iterations. ``counts_match_public``: both counts agree with the public calls (a count <= 128
  exactly when the default ``"jax"`` call converged); in float32 the floor lies close to the
  tolerance, so rounding alone can move the outcome.
* ``scipy_pcg_f64`` / ``scipy_pcg_f32``: ``scipy.sparse.linalg.cg`` with the Jacobi preconditioner
  on the assembled matrix, ``rtol`` = geomjax's default tolerance of the dtype, from geomjax's start
  (``d``), iterations per coordinate and time (single-threaded BLAS, as in ``bench_sobolev.py``);
  ``scipy_f32_true_res``: the float64 relative residual of scipy's float32 solution (scipy stops on
  its recurrence residual). ``splu_s``: factorisation and solve of the three coordinates.

Compiling, not solving, sets the run time (about 1 s per XLA program, six or seven programs per
mesh). ``--quick``: only the meshes with fewer than 10,000 vertices, no icosphere, the ``"jax"``
path only, iterations counted to 1024 and ``--repeat 1`` (under a minute on a 2-core CPU; the full
run takes a few minutes). ``main()`` is a list of sections, each a ``*_rows(meshes, ...)``
function returning rows tagged with their ``section``, so further measurements on the same meshes
add a function and a line.

Section "remesh" (table ``real_meshes_remesh``, see :func:`remesh_rows`): the triangle surfaces
remeshed to 500 and 2000 clusters (at most half their vertices) by geomjax, its reference
algorithm and pyacvd: time, Euler characteristic and boundary edges in and out, Hausdorff
distance, smallest angles, and issue 15's targets (about 2.5 minutes).

Section "queries" (table ``real_meshes_queries``, see :func:`query_rows`): robustness and time of
the mesh queries on the eight triangle surfaces (no tetrahedra, no icosphere), one row per mesh,
query, method and dtype; geomjax runs on its default backend (``implementation=None``) in float32
and float64. ``sdf``: 20,000 points (seed 0) uniform in the bounding box grown by 10% about its
centre; ``signed_distance_field`` with the normal sign and with ``use_sign_winding_number=True``
against pysdf (``SDF``, positive inside: negated; sign from three rays' crossings, distance only
to the faces around the nearest vertex, an approximation), Open3D
(``RaycastingScene.compute_signed_distance``, sign from one ray's crossings) and libigl
(``signed_distance`` with its default sign type, which in libigl is the exact winding number, the
pseudonormal and the fast winding number), all as negative inside. Truth: the exact float64
point-triangle distance (a search over the bounding boxes of 256-face groups that skips only groups
that cannot be nearer) and the generalized winding number ``w``, brute force in float64 (Van
Oosterom-Strackee solid angles of every face). ``sign_errors`` counts the confident points
(``|w - 0.5| > 0.25`` and distance ``> 1e-3``: ``confident_points``) whose sign disagrees with
``w > 0.5``, also on camelhead and lion, which are open (one boundary loop each) so that only the
winding number defines inside; ``max_abs_error`` is the largest ``||value| - distance|`` over all
points. libigl's winding-number sign types return ``(1 - 2w)`` times the distance (a continuous
sign, by design), so on an open surface their value is not the distance. The winding numbers stay
within ``WINDING_PAIR_BUDGET`` point-face pairs per mesh (about 30 s; past it only the first points
get one): every point of the shared meshes is checked.

``rays``: 100,000 rays (seed 1) from points on a sphere of 1.1 half-diagonals about the box's centre
towards uniform points in the box, unit directions; geomjax ``ray_mesh_intersect`` against embreex
and Open3D ``RaycastingScene.cast_rays``, checked against a brute-force float64 Möller-Trumbore
(both sides, edges included) on the first 2,000 rays: ``mask_errors`` (hit or miss wrong),
``distance_errors`` (off by more than 1e-4 relative) and ``max_abs_error`` of the distance. In both
queries the queries that the methods disagree on (``disputed``, out of all of them) are checked as
well (at most 2,000 more), so that a rare error of one method is not lost outside the sample;
``checked`` counts the queries with a truth. Every method builds its search structure inside the
timed call (geomjax's BVH is built in every call too); ``time_s`` is the best of ``--repeat`` warm
calls. A peer that does not import is skipped with a note. Findings: no hit-mask or distance errors
and no disputed ray anywhere; no sign errors on the closed surfaces; on the open ones the normal
sign (geomjax's default, like libigl's pseudonormal) fails where the closest point is seen through
the hole (lion: 1,199 of 18,141 confident points) and the winding-number sign has none. About 2.5
minutes; ``--quick``: 2,000 points, 10,000 rays, 500 checked.

Usage: ``python benchmarks/bench_real_meshes.py [--quick] [--repeat R] [--sections sobolev remesh queries]``
"""

from __future__ import annotations

import argparse
import functools
import importlib
import inspect
import math
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

# scipy's CG does level-1 BLAS on vectors of at most 43k entries: threads gain nothing there and
# lose badly on a busy 2-core machine (see bench_sobolev.py), so the baseline gets its best setting.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax
import jax.numpy as jnp
import meshio
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import cg, splu
from scipy.spatial import cKDTree

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _harness import best_time, best_times_interleaved, block, report

jax.config.update("jax_enable_x64", True)

from geomjax import documented_errors, icosphere, sobolev_deform_points
from geomjax.deform.sobolev import DEFAULT_TOLERANCE
from geomjax.linalg import (
    CellStiffness,
    HelmholtzOperator,
    MultilevelPreconditioner,
    RowStiffness,
    aggregation_hierarchy,
    jacobi_pcg,
    row_pattern,
    simplex_stiffness,
    uniform_lumped_mass,
)

# The shared mesh folder sits beside the checkout (``<checkout>/../shared/meshes``).
MESH_DIR = Path(os.environ.get("GEOMJAX_MESH_DIR", Path(__file__).resolve().parents[2] / "shared" / "meshes"))
MESH_FILES = [
    "decimated-knight.off",
    "fertility.off",
    "3holes.off",
    "screwdriver.off",
    "lion.off",
    "camelhead.off",
    "bumpy-cube.obj",
    "armadillo.obj",
    "octopus-low.mesh",
    "hand.mesh",
]
QUICK_MAX_VERTICES = 10_000
LENGTH_SCALE = 0.05
AMPLITUDE = 0.01
PHASES = np.array([0.0, 2.0, 4.0])  # fixed, so every mesh (and every run) gets the same field
MAX_COUNTED_ITERATIONS = 4096
# --quick counts to 1024 only: the stalled float32 solves would spend ~6 s of its minute running
# into a floor that CG reaches long before (the full run shows the floor after 4096).
QUICK_MAX_COUNTED_ITERATIONS = 1024
CHECK_ITERATIONS = 10_000
DTYPES = {"f64": np.float64, "f32": np.float32}
DEFAULT_MAX_ITERATIONS = inspect.signature(sobolev_deform_points).parameters["max_iterations"].default


class RealMesh(NamedTuple):
    name: str
    points: np.ndarray  # (N, 3) float64
    cells: np.ndarray  # (C, V) int32
    kind: str  # "tri" or "tet"


def load_meshes(quick: bool) -> list[RealMesh]:
    """The meshes of ``MESH_DIR`` (normalised to the unit box) and, unless ``quick``, icosphere(6)."""
    meshes = []
    for file in MESH_FILES:
        mesh = meshio.read(MESH_DIR / file)
        if quick and len(mesh.points) >= QUICK_MAX_VERTICES:
            continue
        # The Medit files also carry their boundary triangles; the volume is the tetrahedra.
        cell_type = "tetra" if file.endswith(".mesh") else "triangle"
        cells = np.concatenate([block.data for block in mesh.cells if block.type == cell_type]).astype(np.int32)
        points = np.asarray(mesh.points, np.float64)  # the .mesh files store float32
        points = points - points.min(axis=0)
        points = points / points.max()
        meshes.append(RealMesh(file, points, cells, "tet" if cell_type == "tetra" else "tri"))
    if not quick:
        sphere = icosphere(6, dtype=jnp.float64)
        meshes.append(RealMesh("icosphere(6)", np.asarray(sphere.points), np.asarray(sphere.cells, np.int32), "tri"))
    return sorted(meshes, key=lambda mesh: len(mesh.points))


def smooth_displacement(points: np.ndarray) -> np.ndarray:
    return AMPLITUDE * np.sin(2 * np.pi * points + PHASES)


def worst_cell_quality(points: np.ndarray, cells: np.ndarray) -> float:
    """Smallest ``measure / measure of the regular simplex with the cell's RMS edge length`` (1: regular, 0: flat)."""
    m = cells.shape[1] - 1
    corners = points[cells]
    i, j = np.triu_indices(m + 1, 1)
    rms_edge = np.sqrt(np.mean(np.sum((corners[:, i] - corners[:, j]) ** 2, axis=-1), axis=1))
    regular = math.sqrt(m + 1) / (math.factorial(m) * 2 ** (m / 2)) * rms_edge**m
    return float(np.min(_measures(points, cells) / regular))


def _measures(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    edges = points[cells[:, 1:]] - points[cells[:, :1]]
    gram = edges @ edges.transpose(0, 2, 1)
    return np.sqrt(np.linalg.det(gram)) / math.factorial(cells.shape[1] - 1)


def assemble_system(points: np.ndarray, cells: np.ndarray) -> tuple[sp.csr_matrix, float, np.ndarray]:
    """``(A, m̄, referenced)`` with ``A = m̄ I + l^2 K`` in CSR, from scratch in NumPy (no geomjax).

    ``K``: per cell, edge matrix ``E`` (rows ``x_i - x_0``), Gram ``G = E E^T``, measure
    ``sqrt(det G) / m!``, local stiffness ``|c| Ĝ G^-1 Ĝ^T`` with ``Ĝ = [-1 ... -1; I_m]``, summed
    into the global matrix. ``m̄``: mean lumped vertex mass (``|c| / (m + 1)`` from each incident
    cell) over the vertices whose mass is positive.
    """
    num_points, num_cell_points = len(points), cells.shape[1]
    m = num_cell_points - 1
    edges = points[cells[:, 1:]] - points[cells[:, :1]]  # (C, m, D)
    gram = edges @ edges.transpose(0, 2, 1)
    measure = np.sqrt(np.linalg.det(gram)) / math.factorial(m)
    g_hat = np.vstack([-np.ones((1, m)), np.eye(m)])  # (V, m): barycentric gradients in edge coordinates
    local = measure[:, None, None] * (g_hat @ np.linalg.inv(gram) @ g_hat.T)  # (C, V, V)
    rows = np.repeat(cells, num_cell_points, axis=1).reshape(-1)
    columns = np.tile(cells, (1, num_cell_points)).reshape(-1)
    stiffness = sp.csr_matrix((local.reshape(-1), (rows, columns)), shape=(num_points, num_points))
    lumped = np.bincount(cells.reshape(-1), weights=np.repeat(measure / num_cell_points, num_cell_points), minlength=num_points)
    referenced = lumped > 0
    mass = float(lumped[referenced].mean()) if referenced.any() else 1.0
    return (mass * sp.identity(num_points, format="csr") + LENGTH_SCALE**2 * stiffness).tocsr(), mass, referenced


@functools.partial(jax.jit, static_argnames=("max_steps", "multilevel"))
def _geomjax_pcg(points, displacement, cells, pattern, hierarchy, *, max_steps, multilevel):
    """geomjax's own solve (``sobolev._jax_solve``, nothing fixed) without the error check.

    Returns ``(num_steps, converged, relative true residual)``: the same operator, right-hand side,
    start and tolerance as the public call, so ``num_steps`` is the iteration count it needs, with
    its multilevel preconditioner (``multilevel``) or with Jacobi (the preconditioner before it,
    and still the one for traced cells).
    """
    local, measures, _ = simplex_stiffness(points, cells)
    preconditioner = None
    if pattern is None:  # row_pattern declined (too much padding): geomjax uses per-cell products
        stiffness = CellStiffness.assemble(local, cells, points.shape[0])
        num_referenced = jnp.sum(jnp.zeros(points.shape[0], bool).at[cells.reshape(-1)].set(True), dtype=jnp.int32)
    else:
        stiffness = RowStiffness.assemble(local, pattern)
        num_referenced = jnp.sum(pattern.referenced, dtype=jnp.int32)
    mass = uniform_lumped_mass(measures, num_referenced)
    length_scale_squared = jnp.asarray(LENGTH_SCALE**2, points.dtype)
    operator = HelmholtzOperator(stiffness, mass, length_scale_squared, None)
    if multilevel and pattern is not None:
        preconditioner = MultilevelPreconditioner.for_helmholtz(stiffness, mass, length_scale_squared, None, hierarchy)
    rhs = mass * displacement
    tolerance = jnp.asarray(DEFAULT_TOLERANCE[jnp.dtype(points.dtype)], points.dtype)
    result = jacobi_pcg(operator.mv, rhs, operator.inverse_diagonal(), displacement, rtol=tolerance, max_steps=max_steps, preconditioner=preconditioner)
    residual = jnp.linalg.norm(rhs - operator.mv(result.solution)) / jnp.linalg.norm(rhs)
    return result.num_steps, result.converged, residual


def geomjax_iterations(mesh: RealMesh, displacement: np.ndarray, dtype, max_steps: int, multilevel: bool = True) -> tuple[int | str, float]:
    """Exact iterations geomjax needs (``">max_steps"`` if it does not converge) and the final relative residual."""
    pattern = row_pattern(mesh.cells, len(mesh.points))
    hierarchy = None if pattern is None else aggregation_hierarchy(pattern)
    steps, converged, residual = _geomjax_pcg(
        jnp.asarray(mesh.points, dtype), jnp.asarray(displacement, dtype), jnp.asarray(mesh.cells), pattern, hierarchy,
        max_steps=max_steps, multilevel=multilevel,
    )  # fmt: skip
    return (int(steps) if bool(converged) else f">{max_steps}"), float(residual)


def public_call(mesh: RealMesh, displacement: np.ndarray, implementation: str, dtype, max_iterations: int | None = None):
    """A thunk that runs ``sobolev_deform_points`` jitted (defaults unless ``max_iterations``) and returns the moved points.

    It raises the op's ``RuntimeError`` when the solve does not converge: under our ``jit`` the
    failed check is JAX's runtime error, and ``documented_errors`` turns it back into the
    ``RuntimeError`` (with the op's message) that an eager call raises.
    """
    points, moved = jnp.asarray(mesh.points, dtype), jnp.asarray(displacement, dtype)
    cells = jnp.asarray(mesh.cells)  # closed over: concrete, as a user's fixed mesh (padded rows)
    options = {} if max_iterations is None else {"max_iterations": max_iterations}
    deform = jax.jit(lambda p, d: sobolev_deform_points(p, cells, d, length_scale=LENGTH_SCALE, implementation=implementation, **options))

    def call():
        with documented_errors():
            return jax.block_until_ready(deform(points, moved))

    return call


def geomjax_default(mesh: RealMesh, displacement: np.ndarray, implementation: str, dtype, repeat: int):
    """``(moved points or None, best time of the jitted call or None, first line of the RuntimeError or None)``."""
    call = public_call(mesh, displacement, implementation, dtype)
    try:
        moved = call()  # compiles
    except RuntimeError as error:
        return None, None, str(error).splitlines()[0]
    return moved, best_time(call, repeat=repeat, warmup=0), None


def scipy_pcg(matrix: sp.csr_matrix, rhs: np.ndarray, start: np.ndarray, rtol: float, repeat: int) -> tuple[str, np.ndarray, float]:
    """Jacobi-PCG per coordinate: ``(iterations per coordinate as "a/b/c", solution, best time)``."""
    preconditioner = sp.diags(1 / matrix.diagonal())
    iterations = [0] * rhs.shape[1]
    failed = []

    def solve(count: bool):
        columns = []
        for k in range(rhs.shape[1]):
            callback = (lambda _, k=k: iterations.__setitem__(k, iterations[k] + 1)) if count else None
            solution, info = cg(matrix, rhs[:, k], x0=start[:, k], rtol=rtol, M=preconditioner, callback=callback)
            if count and info != 0:
                failed.append(f"coordinate {k}: info {info}")  # > 0: not converged, < 0: breakdown
            columns.append(solution)
        return np.stack(columns, axis=1)

    solution = solve(count=True)
    text = "/".join(map(str, iterations)) + (f" (failed: {', '.join(failed)})" if failed else "")
    return text, solution, best_time(lambda: solve(count=False), repeat=repeat, warmup=0)


def sobolev_rows(meshes: list[RealMesh], repeat: int, max_counted_iterations: int, implementations: tuple[str, ...]) -> list[dict]:
    rows = []
    for mesh in meshes:
        start = time.perf_counter()
        num_points = len(mesh.points)
        displacement = smooth_displacement(mesh.points)
        matrix, mass, referenced = assemble_system(mesh.points, mesh.cells)
        quality = worst_cell_quality(mesh.points, mesh.cells)
        print(
            f"{mesh.name}: {num_points} vertices, {len(mesh.cells)} {mesh.kind} cells, {num_points - referenced.sum()} unreferenced, "
            f"worst cell quality {quality:.2g} (1 = regular simplex)",
            flush=True,
        )
        # Unreferenced vertices decouple (m̄ u = m̄ d): geomjax keeps d there, the solves run on the rest.
        inner = np.flatnonzero(referenced)
        system = matrix[inner][:, inner].tocsc()
        rhs, guess = mass * displacement[inner], displacement[inner]

        def direct(system=system, rhs=rhs):
            return splu(system).solve(rhs)

        splu_s = best_time(direct, repeat=repeat, warmup=0)
        reference = displacement.copy()
        reference[inner] = direct()

        row = {
            "section": "sobolev",
            "mesh": mesh.name,
            "vertices": num_points,
            "cells": len(mesh.cells),
            "kind": mesh.kind,
            "unreferenced": int(num_points - referenced.sum()),
            "worst_quality": quality,
            "check_rel_diff": None,  # filled in below, after the default calls it may reuse
        }
        failures: dict[str, list[str]] = {}
        outputs = {}
        for implementation in implementations:
            for label, dtype in DTYPES.items():
                case = f"{implementation}_{label}"
                outputs[case], seconds, failure = geomjax_default(mesh, displacement, implementation, dtype, repeat)
                row[case], row[f"{case}_s"] = outputs[case] is not None, seconds
                if failure is not None:
                    failures.setdefault(failure, []).append(f"{implementation} {label}")
        cases = [f"{implementation}_{label}" for implementation in implementations for label in DTYPES]
        print("  geomjax defaults: " + ", ".join(f"{case} {_converged_text(row[case], row[case + '_s'])}" for case in cases), flush=True)

        # The independent matrix against geomjax run to its tolerance. A converged default call
        # already is that solution (a larger budget stops at the same iteration, the budget only
        # caps the loop), so the max_iterations=10000 call (one more compile) runs only when the
        # default did not converge.
        moved, source = outputs["jax_f64"], "default call"
        if moved is None:
            source = f"max_iterations={CHECK_ITERATIONS}"
            try:
                moved = public_call(mesh, displacement, "jax", np.float64, CHECK_ITERATIONS)()
            except RuntimeError as error:
                print(f"  matrix check skipped: {str(error).splitlines()[0]}", flush=True)
        check = float("nan") if moved is None else float(np.linalg.norm(np.asarray(moved) - mesh.points - reference) / np.linalg.norm(reference))
        row["check_rel_diff"] = check
        print(f"  matrix check (jax f64, {source}): ||u_geomjax - u_direct|| / ||u_direct|| = {check:.1e}", flush=True)

        for label, dtype in DTYPES.items():
            row[f"iters_{label}"], row[f"final_res_{label}"] = geomjax_iterations(mesh, displacement, dtype, max_counted_iterations)
            row[f"jacobi_iters_{label}"], _ = geomjax_iterations(mesh, displacement, dtype, max_counted_iterations, multilevel=False)
        print(
            f"  geomjax iterations (exact, jax, multilevel): f64 {row['iters_f64']}, f32 {row['iters_f32']} "
            f"(final relative residual f64 {row['final_res_f64']:.1e}, f32 {row['final_res_f32']:.1e}); "
            f"with Jacobi: f64 {row['jacobi_iters_f64']}, f32 {row['jacobi_iters_f32']}",
            flush=True,
        )
        del row["final_res_f64"]  # printed; below 1e-10 whenever iters_f64 is a count
        # The counts come from a separate program: XLA may round differently there, and in float32
        # the residual floor sits near the tolerance, so check them against the public calls.
        row["counts_match_public"] = all(_within(row[f"iters_{label}"], DEFAULT_MAX_ITERATIONS) == row[f"jax_{label}"] for label in DTYPES)
        if not row["counts_match_public"]:
            print(f"  NOTE: an exact count disagrees with the public jax call's outcome at max_iterations={DEFAULT_MAX_ITERATIONS}", flush=True)

        for label, dtype in DTYPES.items():
            tolerance = DEFAULT_TOLERANCE[jnp.dtype(dtype)]
            iterations, solution, seconds = scipy_pcg(system.astype(dtype).tocsr(), rhs.astype(dtype), guess.astype(dtype), tolerance, repeat)
            row[f"scipy_pcg_{label}"] = iterations
            row[f"scipy_pcg_{label}_s"] = seconds
            if label == "f32":
                row["scipy_f32_true_res"] = float(np.linalg.norm(rhs - system @ solution.astype(np.float64)) / np.linalg.norm(rhs))
        row["splu_s"] = splu_s
        print(
            f"  scipy Jacobi-PCG iterations per coordinate: f64 {row['scipy_pcg_f64']} ({row['scipy_pcg_f64_s'] * 1e3:.1f} ms), "
            f"f32 {row['scipy_pcg_f32']} ({row['scipy_pcg_f32_s'] * 1e3:.1f} ms, true residual {row['scipy_f32_true_res']:.1e}); "
            f"splu {splu_s * 1e3:.1f} ms",
            flush=True,
        )
        row["failure"] = "; ".join(f"{', '.join(which)}: {message}" for message, which in failures.items()) or None
        rows.append(row)
        print(f"  ({time.perf_counter() - start:.1f} s)", flush=True)
    return rows


REMESH_COUNTS = (500, 2000)  # clusters; a mesh with fewer vertices than twice a count gets V // 2 instead
REMESH_TARGET_RATIO = 5.0  # issue 15: at least 5x faster than pyacvd


def remesh_rows(meshes: list[RealMesh], repeat: int) -> list[dict]:
    """Table "real_meshes_remesh": geomjax ``remeshing`` (default backend), its reference algorithm and pyacvd.

    Per triangle mesh and cluster count: best-of-``repeat`` time (the three methods take turns in
    each round, after a warm-up call each, so a slow spell of the machine hits all alike), Euler characteristic and
    boundary edges of the input and the output, edges with more than two triangles, whether
    geomjax warned (``RemeshTopologyWarning``; the reference algorithm never checks), the sampled symmetric Hausdorff distance
    (``benchmarks/_quality.py``, 100,000 probes a side) also in cluster spacings ``sqrt(A / K)``,
    and the smallest angle (minimum and mean over triangles). The geomjax row carries the time
    ratio against pyacvd and whether it meets issue 15's targets: topology kept, Hausdorff no
    worse than pyacvd's, smallest angle above 10 degrees, at least 5x faster.
    """
    import warnings

    import _quality as quality

    from geomjax import RemeshTopologyWarning, remeshing
    from geomjax.remesh.clustering import remesh_with_sources

    try:
        import pyacvd
        import pyvista
    except ImportError:
        pyacvd = None
        print("pyacvd is not installed (pip install '.[bench]'): no pyacvd rows", flush=True)
    rows = []
    for mesh in meshes:
        if mesh.kind != "tri" or mesh.name.startswith("icosphere"):
            continue
        points, cells = mesh.points, mesh.cells.astype(np.int64)
        euler, boundary, _ = _surface_topology(cells)
        for count in sorted({min(count, len(points) // 2) for count in REMESH_COUNTS}):
            spacing = math.sqrt(quality.surface_area(points, cells) / count)
            methods = {
                "geomjax": lambda: remeshing(points, cells, count),
                "geomjax reference algorithm": lambda: _result_arrays(remesh_with_sources(points, cells, count, reference=True)),
            }
            if pyacvd is not None:
                surface = pyvista.PolyData(points.copy(), np.hstack([np.full((len(cells), 1), 3), cells]).ravel())

                def acvd(surface=surface, count=count):
                    clustering = pyacvd.Clustering(surface)
                    clustering.cluster(count)
                    out = clustering.create_mesh()
                    return np.asarray(out.points), np.asarray(out.faces).reshape(-1, 4)[:, 1:]

                methods["pyacvd"] = acvd
            outputs = {}
            for method, run in methods.items():  # also the warm-up of the timing below
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    outputs[method] = (*(np.asarray(a) for a in jax.block_until_ready(run())), caught)
            # The methods take turns within each round (see best_times_interleaved): the ratio
            # to pyacvd is the figure of interest, and this machine has slow spells.
            seconds_of = best_times_interleaved({method: (lambda run=run: _quietly(run)) for method, run in methods.items()}, repeat=repeat)
            case_rows = []
            for method, (out_points, out_faces, caught) in outputs.items():
                seconds = seconds_of[method]
                out_points = out_points.astype(np.float64)
                out_euler, out_boundary, crowded = _surface_topology(out_faces)
                hausdorff = quality.hausdorff_distance(points, cells, out_points, out_faces, num_probes=100_000)
                angles = quality.triangle_quality(out_points, out_faces)
                case_rows.append({
                    "mesh": mesh.name, "clusters": count, "method": method, "time_s": seconds,
                    "vertices_out": len(out_points), "euler_in": euler, "euler_out": out_euler,
                    "boundary_in": boundary, "boundary_out": out_boundary, "crowded_edges": crowded,
                    # A string: the tables print False in bold, as a failed target.
                    "topology_warning": "yes" if any(issubclass(w.category, RemeshTopologyWarning) for w in caught) else "",
                    "hausdorff": hausdorff, "hausdorff_spacings": hausdorff / spacing,
                    "min_angle_min": angles["min_angle_deg_min"], "min_angle_mean": angles["min_angle_deg_mean"],
                })  # fmt: skip
            ours = case_rows[0]
            if pyacvd is not None:
                theirs = case_rows[-1]
                ours["speedup"] = theirs["time_s"] / ours["time_s"]
                kept = ours["euler_out"] == euler and (ours["boundary_out"] == 0) == (boundary == 0) and ours["crowded_edges"] == 0
                ours["met"] = bool(
                    kept and ours["hausdorff"] <= theirs["hausdorff"] and ours["min_angle_min"] > 10.0 and ours["speedup"] >= REMESH_TARGET_RATIO
                )
            for row in case_rows:
                print(
                    f"{mesh.name} K={count} {row['method']}: {row['time_s'] * 1e3:.0f} ms, Euler {row['euler_in']} -> {row['euler_out']}, "
                    f"boundary edges {row['boundary_in']} -> {row['boundary_out']}, Hausdorff {row['hausdorff']:.4f} "
                    f"({row['hausdorff_spacings']:.2f} spacings), smallest angle {row['min_angle_min']:.1f} deg",
                    flush=True,
                )
            rows += case_rows
    return rows


def _quietly(run):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run()


def _result_arrays(result):
    return result.vertices, result.faces


def _surface_topology(faces: np.ndarray) -> tuple[int, int, int]:
    """``(Euler characteristic, boundary edges, edges with more than two triangles)``."""
    faces = np.asarray(faces, np.int64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int(np.unique(faces).size - counts.size + len(faces)), int(np.sum(counts == 1)), int(np.sum(counts > 2))


# ---------------------------------------------------------------------------------------------
# Section "queries": signed distance and first hits against peer libraries, every answer checked
# against exact float64 answers computed here (NumPy and SciPy, no geomjax).

QUERY_POINTS = 20_000
QUERY_RAYS = 100_000
QUERY_CHECKED_RAYS = 2_000
QUICK_QUERY_COUNTS = (2_000, 10_000, 500)  # --quick: points, rays, randomly checked rays
QUERY_BOX_SCALE = 1.1  # SDF queries: uniform in the bounding box grown by 10% about its centre
RAY_SPHERE_SCALE = 1.1  # ray origins: on a sphere of 1.1 half-diagonals of the box about its centre
QUERY_SEED = 0
CONFIDENT_WINDING = 0.25  # a sign is checked only where |w - 0.5| exceeds this ...
CONFIDENT_DISTANCE = 1e-3  # ... and the point lies farther than this from the surface (unit box)
# Brute-force winding numbers cost about 15 ns per point-face pair in NumPy on 2 cores: past this
# budget (about 30 s a mesh) only the first points get one. The shared meshes stay within it (at
# most 20,000 x 86,482 pairs, armadillo), so every point is checked; larger inputs are subsampled.
WINDING_PAIR_BUDGET = 2_000_000_000
MAX_DISPUTED = 2_000  # queries the methods disagree on, checked on top of the sample (at most)
RAY_RELATIVE_TOLERANCE = 1e-4
DISTANCE_GROUP_SIZE = 256  # faces per bounding box of the exact distance search
PAIR_BLOCK = 1 << 15  # point-face pairs per NumPy block: the temporaries stay in cache


def query_rows(
    meshes: list[RealMesh], repeat: int, num_points: int = QUERY_POINTS, num_rays: int = QUERY_RAYS, num_checked_rays: int = QUERY_CHECKED_RAYS
) -> list[dict]:
    """Table "real_meshes_queries": ``signed_distance_field`` and ``ray_mesh_intersect`` against peers, checked exactly.

    Per triangle surface (no tetrahedra, no icosphere) and query, one row per method and dtype:
    the best-of-``repeat`` time of a warm call (compile excluded; every method builds its search
    structure inside the timed call, as geomjax's default backend does), its errors against the
    exact answers, and ``disputed``: how many of all the queries the methods disagree on (the
    sign; the hit or the distance). Disputed queries are checked as well as the random sample (at
    most ``MAX_DISPUTED`` more), so a rare error of one method is counted even where the sample
    misses it.
    """
    peers = {module: _optional(module) for module in ("pysdf", "igl", "open3d", "embreex")}
    rows = []
    for mesh in meshes:
        if mesh.kind != "tri" or mesh.name.startswith("icosphere"):
            continue
        start = time.perf_counter()
        rows += _sdf_rows(mesh, repeat, num_points, peers)
        rows += _ray_rows(mesh, repeat, num_rays, num_checked_rays, peers)
        print(f"  ({time.perf_counter() - start:.1f} s)", flush=True)
    intact = next((mesh for mesh in meshes if mesh.name == DAMAGED_SOURCE), None)
    if intact is not None:
        rows += _sdf_rows(damaged_copy(intact), repeat, num_points, peers, intact_cells=intact.cells)
    return rows


DAMAGED_SOURCE = "fertility.off"
DAMAGED_REMOVED, DAMAGED_FLIPPED = 0.005, 0.01  # fractions of the faces


def damaged_copy(mesh: RealMesh) -> RealMesh:
    """``mesh`` as a broken scan comes: 0.5% of its faces removed (small holes) and 1% of the rest
    with their orientation flipped, chosen with a fixed seed. Inside is still the intact solid's."""
    rng = np.random.default_rng(7)
    keep = rng.random(len(mesh.cells)) >= DAMAGED_REMOVED
    cells = mesh.cells[keep].copy()
    flip = rng.random(len(cells)) < DAMAGED_FLIPPED
    cells[flip] = cells[flip][:, ::-1]
    name = f"{mesh.name}, {DAMAGED_REMOVED:.1%} faces removed, {DAMAGED_FLIPPED:.0%} flipped"
    return RealMesh(name, mesh.points, cells, mesh.kind)


def _optional(module: str):
    """The imported module, or ``None`` after a printed note (a broken install counts as absent)."""
    try:
        return importlib.import_module(module)
    except Exception as error:  # noqa: BLE001 - Open3D without libusb raises OSError, not ImportError
        print(f"queries: {module} is not importable ({type(error).__name__}: {error}): its rows are skipped", flush=True)
        return None


def _query_row(mesh: RealMesh, query: str, method: str, dtype: str, seconds: float, **results) -> dict:
    """A row with every column of the table, ``None`` where the query has no such figure."""
    row = {"mesh": mesh.name, "query": query, "method": method, "dtype": dtype, "time_s": seconds, "checked": None}
    row |= dict.fromkeys(("confident_points", "sign_errors", "mask_errors", "distance_errors", "max_abs_error", "disputed"))
    return row | results


def _timed_methods(methods: dict, queries: tuple[np.ndarray, ...], repeat: int) -> tuple[dict, dict]:
    """Run each ``(prepare, run)`` once (compiles), then time it: ``({key: outputs as NumPy}, {key: seconds})``."""
    outputs, times = {}, {}
    for key, (prepare, run) in methods.items():
        args = prepare(*queries)  # the conversion to the method's types is not timed
        outputs[key] = jax.tree.map(np.asarray, block(run(*args)))
        times[key] = best_time(lambda run=run, args=args: run(*args), repeat=repeat, warmup=0)
    return outputs, times


def _checked_queries(sample: int, disputed: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``(checked, extra)``: the first ``sample`` queries plus the disputed ones beyond them (at
    most ``MAX_DISPUTED``, drawn at random), which get a ground truth."""
    extra = disputed[disputed >= sample]
    if len(extra) > MAX_DISPUTED:
        extra = np.sort(rng.choice(extra, MAX_DISPUTED, replace=False))
    return np.concatenate([np.arange(sample), extra]), extra


def _sdf_rows(mesh: RealMesh, repeat: int, num_points: int, peers: dict, intact_cells: np.ndarray | None = None) -> list[dict]:
    """The sdf rows of one mesh; ``intact_cells``: for a damaged copy, the cells whose winding number
    says what is inside (the surface before the damage), instead of its own."""
    rng = np.random.default_rng(QUERY_SEED)
    low, high = mesh.points.min(axis=0), mesh.points.max(axis=0)
    centre, half = (low + high) / 2, (high - low) / 2 * QUERY_BOX_SCALE
    points = centre + rng.uniform(-half, half, (num_points, 3))
    distance = exact_distances(points, mesh.points, mesh.cells)
    outputs, times = _timed_methods(_sdf_methods(mesh, peers), (points,), repeat)
    values = {key: np.asarray(value, np.float64).reshape(-1) for key, value in outputs.items()}

    # Winding numbers of the sample (all points unless the budget says otherwise) and of the points
    # whose sign the methods dispute.
    sample = min(num_points, max(1, WINDING_PAIR_BUDGET // len(mesh.cells)))
    inside = np.stack([value < 0 for value in values.values()])
    disputed = np.flatnonzero(np.any(inside != inside[:1], axis=0))
    checked, extra = _checked_queries(sample, disputed, rng)
    winding = winding_numbers(points[checked], mesh.points[mesh.cells if intact_cells is None else intact_cells])
    confident = checked[(np.abs(winding - 0.5) > CONFIDENT_WINDING) & (distance[checked] > CONFIDENT_DISTANCE)]
    truth_inside = np.zeros(num_points, bool)
    truth_inside[checked] = winding > 0.5
    print(
        f"{mesh.name} sdf: {num_points} points, winding numbers of {len(checked)} ({sample} sampled, {len(extra)} of "
        f"{len(disputed)} disputed), {len(confident)} confident ({truth_inside[confident].mean():.0%} inside)",
        flush=True,
    )
    rows = []
    for (method, dtype), value in values.items():
        # A NaN or infinite value is a wrong sign and an infinite distance error.
        wrong = ~np.isfinite(value[confident]) | ((value[confident] < 0) != truth_inside[confident])
        error = float(np.max(np.where(np.isfinite(value), np.abs(np.abs(value) - distance), np.inf)))
        seconds = times[method, dtype]
        rows.append(_query_row(
            mesh, "sdf", method, dtype, seconds, checked=len(checked), confident_points=len(confident),
            sign_errors=int(wrong.sum()), max_abs_error=error, disputed=len(disputed),
        ))  # fmt: skip
        print(f"  {method} [{dtype}]: {seconds * 1e3:.1f} ms, {wrong.sum()} sign errors, max |distance error| {error:.1e}", flush=True)
    return rows


def _sdf_methods(mesh: RealMesh, peers: dict) -> dict:
    """``(method, dtype) -> (prepare(points) -> args, run(*args) -> signed distances)``, all negative inside."""
    from geomjax import signed_distance_field

    methods = {}
    for dtype in (np.float32, np.float64):
        vertices, faces = jnp.asarray(mesh.points, dtype), jnp.asarray(mesh.cells)
        for sign, winding in (("normal", False), ("winding number", True)):
            call = jax.jit(lambda v, f, p, winding=winding: signed_distance_field(v, f, p, use_sign_winding_number=winding)[0])
            methods[f"geomjax, {sign} sign", np.dtype(dtype).name] = (
                lambda p, dtype=dtype, vertices=vertices, faces=faces: (vertices, faces, jnp.asarray(p, dtype)),
                call,
            )
    vertices32, faces32 = mesh.points.astype(np.float32), mesh.cells.astype(np.uint32)

    def as_float32(p):
        return (np.ascontiguousarray(p, np.float32),)

    if (pysdf := peers["pysdf"]) is not None:
        # pysdf is positive inside. Its sign (robust mode, the default) is the majority of three rays'
        # parities; its distance only measures the faces around the nearest vertex (approximate).
        methods["pysdf", "float32"] = (as_float32, lambda p: -pysdf.SDF(vertices32, faces32)(p).reshape(-1))
    if (o3d := peers["open3d"]) is not None:
        # Open3D is negative inside; its sign is the parity of one ray's crossings (nsamples=1).
        def open3d_sdf(p):
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(vertices32), o3d.core.Tensor(faces32))
            return scene.compute_signed_distance(o3d.core.Tensor(p)).numpy()

        methods["Open3D", "float32"] = (as_float32, open3d_sdf)
    if (igl := peers["igl"]) is not None:
        # libigl is negative inside. Its default sign type is the exact (hierarchical) winding number.
        faces64 = mesh.cells.astype(np.int64)
        for name, attribute in (
            ("libigl, default sign", "SIGNED_DISTANCE_TYPE_DEFAULT"),
            ("libigl, pseudonormal sign", "SIGNED_DISTANCE_TYPE_PSEUDONORMAL"),
            ("libigl, fast winding number sign", "SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER"),
        ):
            if hasattr(igl, attribute):
                sign_type = getattr(igl, attribute)
                methods[name, "float64"] = (
                    lambda p: (np.ascontiguousarray(p, np.float64),),
                    lambda p, sign_type=sign_type: igl.signed_distance(p, mesh.points, faces64, sign_type=sign_type)[0],
                )
    return methods


def _ray_rows(mesh: RealMesh, repeat: int, num_rays: int, num_checked: int, peers: dict) -> list[dict]:
    rng = np.random.default_rng(QUERY_SEED + 1)
    low, high = mesh.points.min(axis=0), mesh.points.max(axis=0)
    centre = (low + high) / 2
    radius = RAY_SPHERE_SCALE * np.linalg.norm(high - low) / 2
    normal = rng.normal(size=(num_rays, 3))
    origins = centre + radius * normal / np.linalg.norm(normal, axis=1, keepdims=True)
    directions = rng.uniform(low, high, (num_rays, 3)) - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    outputs, times = _timed_methods(_ray_methods(mesh, peers), (origins, directions), repeat)
    # Every method's answer as a float64 distance, +inf for a miss.
    distances = {key: np.where(np.isfinite(t) & (t < 1e30), t, np.inf).astype(np.float64).reshape(-1) for key, t in outputs.items()}

    # Rays are disputed when two methods disagree on the hit or on its distance.
    stacked = np.stack(list(distances.values()))
    hits = np.isfinite(stacked)
    nearest, farthest = np.min(np.where(hits, stacked, np.inf), axis=0), np.max(np.where(hits, stacked, -np.inf), axis=0)
    disputed = np.flatnonzero(np.any(hits != hits[:1], axis=0) | (farthest - nearest > RAY_RELATIVE_TOLERANCE * nearest))
    sample = np.arange(min(num_checked, num_rays))  # the rays are random: the first ones are a sample
    checked, extra = _checked_queries(len(sample), disputed, rng)
    truth = first_hits(origins[checked], directions[checked], mesh.points[mesh.cells])
    print(
        f"{mesh.name} rays: {num_rays} rays, {np.isfinite(truth[: len(sample)]).mean():.0%} of the sample hit; "
        f"checked {len(checked)} ({len(sample)} sampled, {len(extra)} of {len(disputed)} disputed)",
        flush=True,
    )
    rows = []
    for (method, dtype), distance in distances.items():
        ours, truth_hit = distance[checked], np.isfinite(truth)
        both = np.isfinite(ours) & truth_hit
        mask_errors = int(np.sum(np.isfinite(ours) != truth_hit))
        deviation = np.abs(ours[both] - truth[both])
        distance_errors = int(np.sum(deviation > RAY_RELATIVE_TOLERANCE * truth[both]))
        error = float(deviation.max()) if both.any() else 0.0
        seconds = times[method, dtype]
        rows.append(_query_row(
            mesh, "rays", method, dtype, seconds, checked=len(checked), mask_errors=mask_errors,
            distance_errors=distance_errors, max_abs_error=error, disputed=len(disputed),
        ))  # fmt: skip
        print(
            f"  {method} [{dtype}]: {seconds * 1e3:.1f} ms, {mask_errors} hit-mask errors, {distance_errors} distance errors, max |distance error| {error:.1e}",
            flush=True,
        )
    return rows


def _ray_methods(mesh: RealMesh, peers: dict) -> dict:
    """``(method, dtype) -> (prepare(origins, unit directions) -> args, run(*args) -> hit distances)``."""
    from geomjax import ray_mesh_intersect

    def geomjax_rays(vertices, faces, origins, directions):
        hit, distance = ray_mesh_intersect(vertices, faces, origins, directions)[:2]
        return jnp.where(hit, distance, jnp.inf)

    call = jax.jit(geomjax_rays)
    methods = {}
    for dtype in (np.float32, np.float64):
        vertices, faces = jnp.asarray(mesh.points, dtype), jnp.asarray(mesh.cells)
        methods["geomjax", np.dtype(dtype).name] = (
            lambda o, d, dtype=dtype, vertices=vertices, faces=faces: (vertices, faces, jnp.asarray(o, dtype), jnp.asarray(d, dtype)),
            call,
        )
    triangles32 = mesh.points[mesh.cells].astype(np.float32)
    vertices32, faces32 = mesh.points.astype(np.float32), mesh.cells.astype(np.uint32)
    if peers["embreex"] is not None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        def embree_rays(origins, directions):
            scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene, triangles32)
            return scene.run(origins, directions, query="DISTANCE")  # a miss: 1e37

        methods["embreex", "float32"] = (lambda o, d: (o.astype(np.float32), d.astype(np.float32)), embree_rays)
    if (o3d := peers["open3d"]) is not None:

        def open3d_rays(rays):
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(vertices32), o3d.core.Tensor(faces32))
            return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # a miss: inf

        methods["Open3D", "float32"] = (lambda o, d: (np.concatenate([o, d], axis=1).astype(np.float32),), open3d_rays)
    return methods


# Exact answers in float64 (NumPy and SciPy only).


def exact_distances(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest triangle, exact in float64 (a pruned exhaustive search).

    The faces are split into groups of at most ``DISTANCE_GROUP_SIZE`` by median cuts of their
    centroids. A point starts with the distance to its nearest mesh vertex (an upper bound) and
    measures every face of each group whose bounding box is not farther than its best distance so
    far: a group left out has no face nearer than that, so the minimum is the exact one.
    """
    triangles = vertices[faces]
    best = cKDTree(vertices[np.unique(faces)]).query(points)[0] ** 2
    for group in _face_groups(triangles.mean(axis=1)):
        group_triangles = triangles[group]
        low, high = group_triangles.min(axis=(0, 1)), group_triangles.max(axis=(0, 1))
        box_gap = np.sum((np.maximum(low - points, 0) + np.maximum(points - high, 0)) ** 2, axis=1)
        near = np.flatnonzero(box_gap <= best)
        step = max(1, PAIR_BLOCK // len(group))
        for start in range(0, len(near), step):
            block = near[start : start + step]
            best[block] = np.minimum(best[block], _squared_triangle_distances(points[block], group_triangles).min(axis=1))
    return np.sqrt(best)


def _face_groups(centroids: np.ndarray) -> list[np.ndarray]:
    """Face ids in spatially compact groups: median cuts along the longest extent (a k-d tree's leaves)."""
    pending, groups = [np.arange(len(centroids))], []
    while pending:
        ids = pending.pop()
        if len(ids) <= DISTANCE_GROUP_SIZE:
            groups.append(ids)
            continue
        along = centroids[ids, np.argmax(np.ptp(centroids[ids], axis=0))]
        ids = ids[np.argsort(along, kind="stable")]
        pending += [ids[: len(ids) // 2], ids[len(ids) // 2 :]]
    return groups


def _squared_triangle_distances(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(P, T)`` squared distances between points and triangles (degenerate triangles too).

    Where the point projects into the triangle (on the inner side of its three edges, measured
    with the in-plane edge normals), the distance is the one to the plane; elsewhere it is the
    nearest of the three edges, each a clamped segment projection. A zero-area triangle is only
    its edges.
    """
    p = points[:, None, :]
    a, b, c = triangles[None, :, 0], triangles[None, :, 1], triangles[None, :, 2]
    normal = np.cross(b - a, c - a)
    squared_area = np.sum(normal * normal, axis=-1)
    inner = squared_area > 0
    for start, edge_end in ((a, b), (b, c), (c, a)):
        inner = inner & (np.sum((p - start) * np.cross(normal, edge_end - start), axis=-1) >= 0)
    plane = np.sum((p - a) * normal, axis=-1) ** 2 / np.where(squared_area > 0, squared_area, 1.0)
    edges = np.minimum(np.minimum(_squared_segment_distances(p, a, b), _squared_segment_distances(p, b, c)), _squared_segment_distances(p, c, a))
    return np.where(inner, plane, edges)


def _squared_segment_distances(p: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    edge = end - start
    length = np.sum(edge * edge, axis=-1)
    t = np.clip(np.sum((p - start) * edge, axis=-1) / np.where(length > 0, length, 1.0), 0.0, 1.0)
    gap = p - start - t[..., None] * edge
    return np.sum(gap * gap, axis=-1)


def winding_numbers(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Generalized winding numbers, brute force over every face in float64 (Van Oosterom and Strackee).

    The solid angle of a triangle with corners ``a, b, c`` relative to the point is
    ``2 atan2(a . (b x c), |a||b||c| + (a . b)|c| + (b . c)|a| + (c . a)|b|)``; the winding number
    is their sum over ``4 pi``.
    """
    corners = [np.ascontiguousarray(triangles[:, i, k]) for i in range(3) for k in range(3)]

    def solid_angle_sums(points, faces):
        ax, ay, az, bx, by, bz, cx, cy, cz = (corner[faces] for corner in corners)
        px, py, pz = (points[:, k, None] for k in range(3))
        ax, ay, az, bx, by, bz, cx, cy, cz = ax - px, ay - py, az - pz, bx - px, by - py, bz - pz, cx - px, cy - py, cz - pz
        la, lb, lc = np.sqrt(ax * ax + ay * ay + az * az), np.sqrt(bx * bx + by * by + bz * bz), np.sqrt(cx * cx + cy * cy + cz * cz)
        det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        den = la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la + (cx * ax + cy * ay + cz * az) * lb
        return np.arctan2(det, den).sum(axis=1)

    return _pairs_in_blocks(solid_angle_sums, np.add, 0.0, points, len(triangles)) / (2 * np.pi)


def first_hits(origins: np.ndarray, directions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Distance of each ray's first hit (``+inf``: none), brute-force Möller–Trumbore in float64, both sides.

    A hit needs a ray not parallel to the plane (``det != 0``), barycentric ``u, v >= 0`` and
    ``u + v <= 1`` (edges included) and ``t > 0``; ``directions`` are unit vectors, so ``t`` is the
    distance.
    """
    a = triangles[:, 0]
    arrays = [np.ascontiguousarray(x[:, k]) for x in (a, triangles[:, 1] - a, triangles[:, 2] - a) for k in range(3)]

    def nearest_hits(rays, faces):
        ax, ay, az, e1x, e1y, e1z, e2x, e2y, e2z = (x[faces] for x in arrays)
        ox, oy, oz, dx, dy, dz = (rays[:, k, None] for k in range(6))
        px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
        det = e1x * px + e1y * py + e1z * pz
        inverse = 1.0 / np.where(det != 0, det, 1.0)
        tx, ty, tz = ox - ax, oy - ay, oz - az
        u = (tx * px + ty * py + tz * pz) * inverse
        qx, qy, qz = ty * e1z - tz * e1y, tz * e1x - tx * e1z, tx * e1y - ty * e1x
        v = (dx * qx + dy * qy + dz * qz) * inverse
        t = (e2x * qx + e2y * qy + e2z * qz) * inverse
        hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        return np.min(np.where(hit, t, np.inf), axis=1)

    return _pairs_in_blocks(nearest_hits, np.minimum, np.inf, np.concatenate([origins, directions], axis=1), len(triangles))


def _pairs_in_blocks(kernel, combine, initial: float, queries: np.ndarray, num_faces: int) -> np.ndarray:
    """``combine`` of ``kernel(query rows, face ids)`` over all faces, for every query, blockwise on all cores.

    Blocks of about ``PAIR_BLOCK`` query-face pairs keep the temporaries in cache; the queries are
    split among threads (NumPy's loops release the GIL).
    """
    face_step = min(num_faces, PAIR_BLOCK)
    query_step = max(1, PAIR_BLOCK // face_step)

    def part(first: int, last: int) -> np.ndarray:
        out = np.full(last - first, initial)
        for face in range(0, num_faces, face_step):
            faces = slice(face, face + face_step)  # a view of the face arrays, no copy
            for start in range(first, last, query_step):
                stop = min(start + query_step, last)
                out[start - first : stop - first] = combine(out[start - first : stop - first], kernel(queries[start:stop], faces))
        return out

    workers = os.cpu_count() or 1
    bounds = np.linspace(0, len(queries), workers + 1).astype(int)
    with ThreadPoolExecutor(workers) as pool:
        return np.concatenate(list(pool.map(part, bounds[:-1], bounds[1:])))


def _within(count: int | str, budget: int) -> bool:
    return isinstance(count, int) and count <= budget


def _converged_text(converged: bool, seconds: float | None) -> str:
    return f"converged ({seconds * 1e3:.1f} ms)" if converged else "NOT converged"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"meshes with < {QUICK_MAX_VERTICES:,} vertices, no icosphere(6), jax path only, counts to {QUICK_MAX_COUNTED_ITERATIONS}",
    )
    parser.add_argument("--repeat", type=int, default=None, help="best of this many timed runs (default 3, 1 with --quick)")
    sections = ("sobolev", "remesh", "queries")
    parser.add_argument("--sections", nargs="+", choices=sections, default=sections, help="the measurements to run")
    args = parser.parse_args()
    start = time.perf_counter()
    meshes = load_meshes(args.quick)
    # One section per measurement on the same meshes; each returns its rows and has its table.
    repeat = args.repeat or (1 if args.quick else 3)
    if "sobolev" in args.sections:
        rows = sobolev_rows(
            meshes,
            repeat,
            QUICK_MAX_COUNTED_ITERATIONS if args.quick else MAX_COUNTED_ITERATIONS,
            # Every program here is compiled once and run a few times, so compiling sets the time:
            # --quick leaves out the Warp path (the same PCG with Warp's stiffness product) to
            # stay under a minute.
            ("jax",) if args.quick else ("jax", "warp"),
        )
        report("real_meshes", rows)
    if "remesh" in args.sections:
        report("real_meshes_remesh", remesh_rows(meshes, repeat))
    if "queries" in args.sections:
        counts = QUICK_QUERY_COUNTS if args.quick else (QUERY_POINTS, QUERY_RAYS, QUERY_CHECKED_RAYS)
        report("real_meshes_queries", query_rows(meshes, repeat, *counts))
    print(f"total {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
