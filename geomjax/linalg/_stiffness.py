"""P1 stiffness of simplicial meshes: per-cell local matrices and matrix-free products.

A cell with vertices ``x_0 .. x_m`` (``m = V - 1`` <= ``D``) has edge matrix ``E`` (rows
``x_i - x_0``), Gram matrix ``G = E E^T``, measure ``|c| = sqrt(det G) / m!`` and local stiffness
``|c| Ĝ G^-1 Ĝ^T`` with ``Ĝ = [-1 ... -1; I_m]`` (barycentric gradients in edge coordinates).
This works for embedded manifolds (curves in 2D/3D, surfaces in 3D) as well as for full-dimensional
cells.

Local rows sum to zero, so products are evaluated in *difference form*,
``(K x)_i = sum_j K_ij (x_j - x_i)`` over off-diagonal entries only. That makes constants exact
null vectors (a constant field is reproduced bit for bit) and keeps the rounding error of ``K x``
proportional to the variation of ``x`` rather than to its size, which is what lets a float32
solve reach a 1e-6 relative *true* residual. The diagonal (for Jacobi) is ``-sum_j K_ij``.

Two products, both differentiable in the local matrices:

* :class:`RowStiffness`: the operator assembled into padded rows ("ELL" format) from a
  :class:`RowPattern` computed once on the host from concrete ``cells``. The product is ``W``
  gathers of the neighbour values (``W`` = most neighbours of a vertex) and no scatter; on CPU it
  is several times faster than a scatter-based product and faster than scipy's CSR product.
* :class:`CellStiffness`: per-cell products scattered with ``segment_sum``; needs no host
  pattern, so it is the one used when ``cells`` is traced (e.g. a ``jit`` argument).
"""

from __future__ import annotations

import collections
import hashlib
import math
import threading
from collections.abc import Callable
from typing import NamedTuple, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._validate import as_jax_array

_T = TypeVar("_T")

__all__ = [
    "TopologyCache",
    "simplex_stiffness",
    "off_diagonal_pairs",
    "off_diagonal_entries",
    "RowPattern",
    "row_pattern",
    "RowStiffness",
    "CellStiffness",
    "referenced_vertices",
]


def off_diagonal_pairs(num_cell_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Local ``(a, b)`` index pairs with ``a != b``, row-major: ``V (V - 1)`` of them."""
    a, b = np.nonzero(~np.eye(num_cell_points, dtype=bool))
    return a, b


def off_diagonal_entries(local_stiffness: Float[Array, "... C V V"]) -> Float[Array, "... C P"]:
    """The ``V (V - 1)`` off-diagonal entries of each local matrix, in :func:`off_diagonal_pairs` order."""
    a, b = off_diagonal_pairs(local_stiffness.shape[-1])
    return local_stiffness[..., a, b]


def _determinant_and_adjugate(gram: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``det`` and adjugate of symmetric ``(..., m, m)`` Gram matrices; explicit up to ``m = 3``."""
    m = gram.shape[-1]
    if m == 1:
        return gram[..., 0, 0], jnp.ones_like(gram)
    if m == 2:
        g00, g01, g11 = gram[..., 0, 0], gram[..., 0, 1], gram[..., 1, 1]
        adjugate = jnp.stack([jnp.stack([g11, -g01], -1), jnp.stack([-g01, g00], -1)], -2)
        return g00 * g11 - g01 * g01, adjugate
    if m == 3:
        g = gram
        c00 = g[..., 1, 1] * g[..., 2, 2] - g[..., 1, 2] * g[..., 2, 1]
        c01 = g[..., 1, 2] * g[..., 2, 0] - g[..., 1, 0] * g[..., 2, 2]
        c02 = g[..., 1, 0] * g[..., 2, 1] - g[..., 1, 1] * g[..., 2, 0]
        c11 = g[..., 0, 0] * g[..., 2, 2] - g[..., 0, 2] * g[..., 2, 0]
        c12 = g[..., 0, 2] * g[..., 1, 0] - g[..., 0, 0] * g[..., 1, 2]
        c22 = g[..., 0, 0] * g[..., 1, 1] - g[..., 0, 1] * g[..., 1, 0]
        det = g[..., 0, 0] * c00 + g[..., 0, 1] * c01 + g[..., 0, 2] * c02
        adjugate = jnp.stack([jnp.stack([c00, c01, c02], -1), jnp.stack([c01, c11, c12], -1), jnp.stack([c02, c12, c22], -1)], -2)
        return det, adjugate
    det = jnp.linalg.det(gram)
    return det, jnp.linalg.inv(gram) * det[..., None, None]


def _gram(edges: jax.Array) -> jax.Array:
    return jnp.einsum("cid,cjd->cij", edges, edges)


def simplex_stiffness(points: Float[Array, "N D"], cells: Int[Array, "C V"]) -> tuple[Float[Array, "C V V"], Float[Array, " C"], Float[Array, " C"]]:
    """Local P1 stiffness matrices, measures and Gram determinants of every cell.

    Returns ``(local_stiffness, measures, gram_determinants)``. A cell is valid when its Gram
    determinant is finite and strictly positive. Invalid cells get zero stiffness and measure,
    computed from a substituted identity Gram matrix (double ``where``), so no NaN reaches values
    or gradients; callers reject them. Differentiable in ``points`` (any order); indices must
    already be in range.
    """
    m = cells.shape[-1] - 1
    corners = points[cells]  # (C, V, D)
    edges = corners[:, 1:, :] - corners[:, :1, :]
    det, _ = _determinant_and_adjugate(_gram(jax.lax.stop_gradient(edges)))
    valid = jnp.isfinite(det) & (det > 0)
    # Both wheres matter: the first keeps NaN coordinates out of the Gram cotangent, the second
    # keeps the inverse finite.
    gram = _gram(jnp.where(valid[:, None, None], edges, 0))
    safe_gram = jnp.where(valid[:, None, None], gram, jnp.eye(m, dtype=points.dtype))
    safe_det, adjugate = _determinant_and_adjugate(safe_gram)
    inverse = adjugate / safe_det[:, None, None]
    measure = jnp.where(valid, jnp.sqrt(safe_det) / math.factorial(m), 0)
    # Ĝ H Ĝ^T for H = G^-1: the first row/column carries the negated row/column sums of H.
    column_sums = jnp.sum(inverse, axis=1)  # (C, m); H is symmetric
    total = jnp.sum(column_sums, axis=1)
    first_row = jnp.concatenate([total[:, None], -column_sums], axis=1)  # (C, V)
    rest = jnp.concatenate([-column_sums[:, :, None], inverse], axis=2)  # (C, m, V)
    local = jnp.concatenate([first_row[:, None, :], rest], axis=1) * measure[:, None, None]
    return local, measure, det


def referenced_vertices(cells: Int[Array, "C V"], num_points: int) -> Bool[Array, " N"]:
    """Which vertices some cell references (traced-friendly: one scatter)."""
    return jnp.zeros((num_points,), bool).at[cells.reshape(-1)].set(True)


# ---------------------------------------------------------------------------------------------
# Padded-row ("ELL") pattern, computed on the host from concrete cells and cached.


class RowPattern(NamedTuple):
    """Padded rows of the stiffness sparsity pattern (off-diagonal entries only).

    Attributes:
        neighbours: ``(N, W)`` int32; row ``i`` lists the vertices sharing a cell with ``i``,
            padded with ``i`` itself (a padded slot has coefficient zero and contributes
            ``0 * (x_i - x_i)``). ``W >= 1``.
        entry_slots: ``(C * V * (V - 1),)`` int32 position, in the flattened ``(N * W)``
            coefficients, of every off-diagonal local entry (in :func:`off_diagonal_pairs` order).
        referenced: ``(N,)`` bool, the vertices referenced by at least one cell.
    """

    neighbours: Int[Array, "N W"]
    entry_slots: Int[Array, " E"]
    referenced: Bool[Array, " N"]


class TopologyCache:
    """The last few structures built on the host from a mesh's index array, keyed on its contents
    (thread-safe), so that repeated calls on one topology build them once."""

    def __init__(self, size: int = 8):
        self._entries: collections.OrderedDict = collections.OrderedDict()
        self._size = size
        self._lock = threading.Lock()

    def get(self, index_array: np.ndarray, build: Callable[[], _T], *extra_key) -> _T:
        """The cached value for ``(index_array's contents, *extra_key)``, else ``build()``."""
        array = np.ascontiguousarray(index_array)
        key = (*extra_key, array.shape, array.dtype.str, hashlib.blake2b(array.tobytes(), digest_size=16).digest())
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                return self._entries[key]
        value = build()
        with self._lock:
            self._entries[key] = value
            while len(self._entries) > self._size:
                self._entries.popitem(last=False)
        return value


_PATTERNS = TopologyCache()
# Padding may cost at most this factor over the number of stored entries; wider patterns (a vertex
# shared by a huge fan of cells) use the per-cell product instead.
_MAX_PADDING_FACTOR = 4


def row_pattern(cells: np.ndarray, num_points: int) -> RowPattern | None:
    """The :class:`RowPattern` (device arrays) of concrete in-range ``cells``, ``None`` when padding
    would be wasteful.

    Results are cached on the cell contents (a few of the most recent topologies), so repeated
    eager calls on one mesh pay for the pattern once.
    """
    cells = np.asarray(cells)

    def build() -> RowPattern | None:
        host_pattern = _build_row_pattern(cells.astype(np.int64), num_points)
        if host_pattern is None:
            return None
        # Kept on the device, so repeated eager calls do not copy the pattern again (concrete
        # arrays even when first built while tracing, so the cache never holds a tracer).
        with jax.ensure_compile_time_eval():
            return RowPattern(*(as_jax_array(a) for a in host_pattern))

    return _PATTERNS.get(cells, build, num_points)


def _build_row_pattern(cells: np.ndarray, num_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The :class:`RowPattern` fields as host arrays, in field order; ``None`` when padding would be wasteful."""
    a, b = off_diagonal_pairs(cells.shape[1])
    rows = cells[:, a].reshape(-1)
    columns = cells[:, b].reshape(-1)
    unique_keys, entry_to_unique = np.unique(rows * num_points + columns, return_inverse=True)
    unique_rows = unique_keys // num_points
    counts = np.bincount(unique_rows, minlength=num_points)
    width = max(int(counts.max(initial=0)), 1)
    if num_points * width > _MAX_PADDING_FACTOR * max(unique_keys.size, num_points):
        return None
    row_starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    unique_slots = unique_rows * width + (np.arange(unique_keys.size) - row_starts[unique_rows])
    neighbours = np.repeat(np.arange(num_points, dtype=np.int32), width)
    neighbours[unique_slots] = (unique_keys % num_points).astype(np.int32)
    referenced = np.bincount(cells.reshape(-1), minlength=num_points) > 0
    return neighbours.reshape(num_points, width), unique_slots[entry_to_unique.reshape(-1)].astype(np.int32), referenced


# ---------------------------------------------------------------------------------------------
# Matrix-free products ``x -> K x`` on ``(N, D)`` blocks.


class RowStiffness(eqx.Module):
    """The stiffness operator in padded rows: ``(K x)_i = sum_k coefficients[i, k] (x[n_ik] - x_i)``."""

    coefficients: Float[Array, "N W"]
    neighbours: Int[Array, "N W"]

    @classmethod
    def assemble(cls, local_stiffness: Float[Array, "C V V"], pattern: RowPattern) -> RowStiffness:
        """Sum the local off-diagonal entries into the pattern's slots (one scatter per assembly)."""
        num_points, width = pattern.neighbours.shape
        entries = off_diagonal_entries(local_stiffness).reshape(-1)
        coefficients = jax.ops.segment_sum(entries, pattern.entry_slots, num_segments=num_points * width)
        return cls(coefficients.reshape(num_points, width), jnp.asarray(pattern.neighbours))

    def __call__(self, x: Float[Array, "N D"]) -> Float[Array, "N D"]:
        # Unrolled over the (small, static) width: W plain gathers fuse into one loop, where a
        # (N, W, D) gather followed by a reduction is several times slower on CPU.
        total = jnp.zeros_like(x)
        for k in range(self.neighbours.shape[1]):
            total = total + self.coefficients[:, k, None] * (x[self.neighbours[:, k]] - x)
        return total

    def diagonal(self) -> Float[Array, " N"]:
        return -jnp.sum(self.coefficients, axis=1)


class CellStiffness(eqx.Module):
    """The stiffness operator as per-cell products scattered to the vertices (traced ``cells``)."""

    off_diagonal: Float[Array, "C P"]
    cells: Int[Array, "C V"]
    num_points: int = eqx.field(static=True)

    @classmethod
    def assemble(cls, local_stiffness: Float[Array, "C V V"], cells: Int[Array, "C V"], num_points: int) -> CellStiffness:
        return cls(off_diagonal_entries(local_stiffness), cells, num_points)

    def __call__(self, x: Float[Array, "N D"]) -> Float[Array, "N D"]:
        num_cell_points = self.cells.shape[1]
        _, b = off_diagonal_pairs(num_cell_points)
        corners = x[self.cells]  # (C, V, D): one gather, differences taken per cell
        differences = corners[:, b.reshape(num_cell_points, -1)] - corners[:, :, None]  # (C, V, V - 1, D)
        weights = self.off_diagonal.reshape(-1, num_cell_points, num_cell_points - 1)
        per_corner = jnp.einsum("cas,casd->cad", weights, differences)
        return jax.ops.segment_sum(per_corner.reshape(-1, x.shape[-1]), self.cells.reshape(-1), num_segments=self.num_points)

    def diagonal(self) -> Float[Array, " N"]:
        num_cell_points = self.cells.shape[1]
        row_sums = jnp.sum(self.off_diagonal.reshape(-1, num_cell_points, num_cell_points - 1), axis=-1)
        return -jax.ops.segment_sum(row_sums.reshape(-1), self.cells.reshape(-1), num_segments=self.num_points)
