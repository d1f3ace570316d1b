"""Pieces shared by the six deformation energies (pure JAX).

Invalid primitives. The tensor functionals never inspect index values (that would sync the
device). A cell, hinge or face is *invalid* when one of its indices is out of range, one of its
coordinates (current or reference) is not finite, or its reference geometry is degenerate. JAX
gathers clamp silently, so validity is an explicit mask: invalid primitives are gathered from
vertex 0, their coordinates are replaced by a harmless canonical primitive, and their term is
set to NaN with ``where``. An invalid term is therefore NaN and contributes exactly zero to every
gradient, on the JAX and on the Warp path alike; no NaN or infinity reaches the gradients of the
valid terms.

Simplex cells are sorted by vertex index (a compare-exchange network, elementwise and cheap)
before their consecutive edges ``x_{k+1} - x_k`` are formed, so a result does not depend on how
the caller ordered the vertices of a cell: the same permutation applies to the current and the
reference cell, which leaves signed measure ratios unchanged.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._dispatch import Implementation, platform_of, select_implementation
from .._points import add_batch_axis
from .._sharding import map_local_shards
from .._validate import check_choice, check_coordinates, check_same_shape, check_topology

# The calling convention all six energies share (the reference API's): current and rest points of
# one shape, shared integer topology, the op's options, ``reduction`` and ``implementation``.
Points = Float[Array, "*batch num_points num_dims"]
SurfacePoints = Float[Array, "*batch num_points 3"]
Cells = Int[Array, "num_cells simplex_vertices"]
Triangles = Int[Array, "num_triangles 3"]
Hinges = Int[Array, "num_hinges 4"]
Energy = Float[Array, "..."]

REDUCTIONS = ("none", "sum", "mean")
SIMPLEX_VERTICES = (2, 3, 4)  # edges, triangles, tetrahedra
WARP_MAX_DIMS = 3

# Compare-exchange pairs sorting 2, 3 or 4 values.
_SORTING_NETWORKS = {2: ((0, 1),), 3: ((0, 1), (1, 2), (0, 1)), 4: ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2))}


# ---------------------------------------------------------------------------------------------
# Validation and dispatch.


def check_energy_inputs(points, reference_points, topology, *, topology_name: str, vertices_per_row):
    """Check coordinates, their reference and the shared topology.

    Returns ``(points, reference_points, topology, batched)`` with the coordinates as
    ``(B, N, D)`` arrays (a batch axis of one added to unbatched input).
    """
    points, batched = check_coordinates("points", points)
    reference_points = check_same_shape("points", points, "reference_points", reference_points)
    topology = check_topology(topology_name, topology, points, vertices_per_row=vertices_per_row)
    return add_batch_axis(points, batched), add_batch_axis(reference_points, batched), topology, batched


def check_reduction(reduction) -> str:
    return check_choice("reduction", reduction, REDUCTIONS)


def simplex_dimension(op_name: str, cells: jax.Array, num_dims: int) -> int:
    """``m`` of ``(M, m + 1)`` cells; an m-simplex needs at least ``m`` coordinates."""
    m = cells.shape[1] - 1
    if num_dims < m:
        raise ValueError(f"{op_name}: cells with {m + 1} vertices are {m}-simplices and need points with D >= {m} coordinates, got D={num_dims}")
    return m


def require_three_dims(op_name: str, points: jax.Array) -> None:
    if points.shape[-1] != 3:
        raise ValueError(f"{op_name} needs points with D = 3 coordinates, got D={points.shape[-1]}")


def select_energy_backend(op_name: str, implementation, points: jax.Array) -> Implementation:
    """Resolve ``implementation``; Warp kernels handle ``D <= 3`` only.

    ``None`` falls back to JAX for ``D > 3``; an explicit ``"warp"`` with ``D > 3`` is a
    ``ValueError``.
    """
    num_dims = points.shape[-1]
    unsupported = f"supports D <= {WARP_MAX_DIMS} coordinates, got D={num_dims}" if num_dims > WARP_MAX_DIMS else None
    return select_implementation(op_name, implementation, platform=platform_of(points), warp_unsupported=unsupported)


# ---------------------------------------------------------------------------------------------
# Reductions.


def reduce_terms(terms: jax.Array, reduction: str) -> jax.Array:
    """``"none"``: ``terms``; ``"sum"``: their sum; ``"mean"``: sum over ``max(count, 1)``.

    Empty ``terms`` reduce to an exact zero, so an energy over no primitives is neutral.
    """
    if reduction == "none":
        return terms
    total = jnp.sum(terms)
    if reduction == "sum":
        return total
    return total / max(terms.size, 1)


def nan_terms(shape: tuple[int, ...], dtype) -> jax.Array:
    """Terms of primitives that cannot be evaluated at all (no points to gather from)."""
    return jnp.full(shape, jnp.nan, dtype)


# ---------------------------------------------------------------------------------------------
# Gathers.


def sort_cell_vertices(cells: jax.Array) -> list[jax.Array]:
    """The columns of ``(M, K)`` cells, sorted ascending within each row."""
    columns = [cells[:, k] for k in range(cells.shape[1])]
    for i, j in _SORTING_NETWORKS[len(columns)]:
        columns[i], columns[j] = jnp.minimum(columns[i], columns[j]), jnp.maximum(columns[i], columns[j])
    return columns


def gather_vertices(points: jax.Array, columns: list[jax.Array]) -> tuple[list[jax.Array], jax.Array]:
    """Gather ``(B, M, D)`` vertex coordinates for index columns ``(M,)``.

    Returns the gathered arrays and the ``(M,)`` mask of rows whose indices are all in range;
    out-of-range indices are gathered from vertex 0 (the row is invalid anyway).
    """
    num_points = points.shape[1]
    in_range = [(c >= 0) & (c < num_points) for c in columns]
    gathered = [points.at[:, jnp.where(ok, c, 0)].get(mode="promise_in_bounds") for c, ok in zip(columns, in_range, strict=True)]
    return gathered, jnp.all(jnp.stack(in_range), axis=0)


def all_finite(vectors: list[jax.Array]) -> jax.Array:
    """Whether every component of every ``(..., D)`` vector is finite: shape ``(...)``."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(v), axis=-1) for v in vectors]), axis=0)


def keep_or(mask: jax.Array, vectors: list[jax.Array], canonical: list[jax.Array]) -> list[jax.Array]:
    """``vectors`` where ``mask`` holds, else the matching canonical vectors."""
    return [jnp.where(mask[..., None], v, c) for v, c in zip(vectors, canonical, strict=True)]


def unit_vectors(count: int, num_dims: int, dtype) -> list[jax.Array]:
    """The first ``count`` standard basis vectors of ``R^num_dims`` (a canonical valid simplex)."""
    return [jnp.zeros(num_dims, dtype).at[k].set(1) for k in range(count)]


def simplex_edges(points: jax.Array, reference_points: jax.Array, cells: jax.Array):
    """Consecutive edges of the vertex-sorted cells, current and reference.

    Returns ``(edges, reference_edges, usable)``: two lists of ``m`` arrays ``(B, M, D)`` and the
    ``(B, M)`` mask of cells whose indices are in range and whose edges are all finite. Unusable
    cells get the unit simplex's edges, so everything computed from them stays finite.
    """
    columns = sort_cell_vertices(cells)
    current, in_range = gather_vertices(points, columns)
    reference, _ = gather_vertices(reference_points, columns)
    edges = [b - a for a, b in zip(current[:-1], current[1:])]
    reference_edges = [b - a for a, b in zip(reference[:-1], reference[1:])]
    usable = in_range & all_finite(edges) & all_finite(reference_edges)
    canonical = unit_vectors(len(edges), points.shape[-1], points.dtype)
    return keep_or(usable, edges, canonical), keep_or(usable, reference_edges, canonical), usable


# ---------------------------------------------------------------------------------------------
# Geometry of one simplex (vectorised over leading axes).


def dot(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.sum(a * b, axis=-1)


def cross(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.stack(
        [a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2], a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1
    )


def safe_norm(v: jax.Array) -> jax.Array:
    """Euclidean norm over the last axis, an exact zero with a zero (sub)gradient at ``v = 0``."""
    squared = dot(v, v)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1)), 0)


def gram_schmidt(edges: list[jax.Array]):
    """Modified Gram-Schmidt of ``m`` edge arrays ``(..., D)``: the reduced QR of ``[e_0 ... e_{m-1}]``.

    Returns ``(frame, r)``: the orthonormal vectors ``q_k`` (zero where an edge is dependent on the
    previous ones) and the upper-triangular ``R`` as a dict ``{(i, j): (...)}`` with ``i <= j``;
    ``r[k, k] >= 0`` are the norms of the orthogonalised edges.
    """
    frame: list[jax.Array] = []
    r: dict[tuple[int, int], jax.Array] = {}
    for k, v in enumerate(edges):
        for j in range(k):
            r[j, k] = dot(frame[j], v)
            v = v - r[j, k][..., None] * frame[j]
        norm = safe_norm(v)
        r[k, k] = norm
        frame.append(v / jnp.where(norm > 0, norm, 1)[..., None])
    return frame, r


def determinant(edges: list[jax.Array]) -> jax.Array:
    """Signed determinant of ``m = D <= 3`` edge vectors ``(..., D)`` (explicit formulas)."""
    if len(edges) == 1:
        return edges[0][..., 0]
    if len(edges) == 2:
        a, b = edges
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return dot(edges[0], cross(edges[1], edges[2]))


def simplex_measure(edges: list[jax.Array], num_dims: int) -> jax.Array:
    """Measure of the simplex spanned by ``m`` edges: signed ``det / m!`` when ``m = D``, else the
    unsigned intrinsic measure ``prod r_kk / m!`` (Gram-Schmidt norms, not a Gram determinant)."""
    m = len(edges)
    if m == num_dims:
        return determinant(edges) / math.factorial(m)
    _, r = gram_schmidt(edges)
    product = r[0, 0]
    for k in range(1, m):
        product = product * r[k, k]
    return product / math.factorial(m)


@jax.jit
def simplex_measures(points: jax.Array, reference_points: jax.Array, cells: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Current and reference measures ``(B, M)`` of every cell (see :func:`simplex_measure`).

    Both are NaN for invalid cells (out-of-range index, non-finite coordinates, zero or
    non-finite reference measure), and those cells pass no gradient back. The measure, signed
    for full-dimensional cells, defines the measure and inversion energies through ``q = V / V_0``.
    """
    edges, reference_edges, usable = simplex_edges(points, reference_points, cells)
    num_dims = points.shape[-1]
    measure = simplex_measure(edges, num_dims)
    reference_measure = simplex_measure(reference_edges, num_dims)
    valid = usable & (reference_measure != 0) & jnp.isfinite(reference_measure)
    return jnp.where(valid, measure, jnp.nan), jnp.where(valid, reference_measure, jnp.nan)


def row_terms(points: jax.Array, reference_points: jax.Array, topology: jax.Array, backend: Implementation, warp_terms, jax_terms, *, num_outputs: int = 1):
    """Per-row values ``(B, M)`` of ``jax_terms`` (or ``warp_terms`` on Warp) with the static edge cases.

    ``jax_terms`` and ``warp_terms`` map ``(B, N, D)`` points, their reference and the ``(M, K)``
    topology to ``num_outputs`` arrays ``(B, M)``. No rows or no batch items give zeros (so sums
    are 0); no points, with rows, give NaN everywhere, because every index is then out of range.
    """
    shape = (points.shape[0], topology.shape[0])
    if shape[0] * shape[1] == 0 or points.shape[1] == 0:
        filled = jnp.zeros(shape, points.dtype) if shape[0] * shape[1] == 0 else nan_terms(shape, points.dtype)
        return filled if num_outputs == 1 else (filled,) * num_outputs
    # Explicitly sharded designs are computed shard by shard (see _sharding), on both backends:
    # Warp's kernels need it, and the JAX terms' gradient scatters into an unsharded operand
    # otherwise, which JAX 0.12 refuses ("Use .at[...].add(out_sharding=)").
    if backend.is_warp:
        return map_local_shards(lambda p, r, t: backend.run(warp_terms, jax_terms, p, r, t), (points, reference_points, topology), (1, 1, 0), out_axes=1)
    return map_local_shards(jax_terms, (points, reference_points, topology), (1, 1, 0), out_axes=1)


def _warp_simplex_measures(points, reference_points, cells):
    from warp_ffi.measure import simplex_measures as warp_simplex_measures

    return warp_simplex_measures(points, reference_points, cells)


def cell_measures(points: jax.Array, reference_points: jax.Array, cells: jax.Array, backend: Implementation) -> tuple[jax.Array, jax.Array]:
    """:func:`simplex_measures` on the chosen backend, with the static edge cases of :func:`row_terms`."""
    return row_terms(points, reference_points, cells, backend, _warp_simplex_measures, simplex_measures, num_outputs=2)
