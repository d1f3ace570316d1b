"""P1 stiffness products for the Sobolev filter as Warp kernels: deterministic vertex gathers.

Inputs arrive validated (no checks here): cells ``(C, V)`` int32 with indices in ``[0, N)``,
per-cell off-diagonal stiffness entries ``(C, V (V - 1))`` in row-major ``(a, b), a != b`` order,
blocks ``(N, D)`` of one float dtype.

The local matrices are assembled in JAX (so the geometry stays differentiable there); Warp only
does the bilinear product that dominates a conjugate-gradient solve,

    (K x)_i = sum over cells c with local vertex a at i, of sum_{b != a} K_c[a, b] (x_{c_b} - x_i),

in the difference form that makes constants exact null vectors. Each vertex *gathers* from its
incident ``(cell, local index)`` slots (a CSR incidence built once per solve by
``_grid.counting_sort``), so there are no atomics and results are bitwise deterministic. CPU
launches are split over the cores (chunked kernel families). Nothing here is differentiated: the
solve-level ``custom_vjp`` in ``geomjax.deform.sobolev`` applies the implicit adjoint with these
same products.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax
import jax.numpy as jnp

from ._grid import counting_sort
from ._wrap import KernelFamily, scalars, vectors
from ._wrap import warp as wp

__all__ = ["vertex_incidence", "stiffness_product", "stiffness_diagonal"]


@wp.kernel(enable_backward=False)
@no_type_check
def _product_kernel(
    x: wp.array(dtype=Any), off_diagonal: wp.array(dtype=Any), cells: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32), num_cell_points: wp.int32, offset: wp.int32, y: wp.array(dtype=Any),
):  # fmt: skip
    _, t = wp.tid()
    i = t + offset
    xi = x[i]
    total = y.dtype()
    others = num_cell_points - 1
    for k in range(offsets[i], offsets[i + 1]):
        slot = order[k]  # c * V + a
        first = (slot // num_cell_points) * num_cell_points
        a = slot - first
        entries = slot * others  # row a of cell c in the (C, V (V - 1)) entries
        for s in range(others):
            b = s
            if s >= a:
                b = s + 1
            total += off_diagonal[entries + s] * (x[cells[first + b]] - xi)
    y[i] = total


@wp.kernel(enable_backward=False)
@no_type_check
def _diagonal_kernel(
    off_diagonal: wp.array(dtype=Any), offsets: wp.array(dtype=wp.int32), order: wp.array(dtype=wp.int32),
    num_cell_points: wp.int32, offset: wp.int32, diagonal: wp.array(dtype=Any),
):  # fmt: skip
    _, t = wp.tid()
    i = t + offset
    total = diagonal.dtype(0.0)
    others = num_cell_points - 1
    for k in range(offsets[i], offsets[i + 1]):
        entries = order[k] * others
        for s in range(others):
            total -= off_diagonal[entries + s]
    diagonal[i] = total


def _types(s, dim: int = 1) -> dict:
    return {"x": vectors(s, dim), "y": vectors(s, dim), "off_diagonal": scalars(s), "diagonal": scalars(s)}


_product = KernelFamily(_product_kernel, _types, outputs=("y",), chunked=True, variants=((3,),))
_diagonal = KernelFamily(_diagonal_kernel, _types, outputs=("diagonal",), chunked=True)


def vertex_incidence(cells: jax.Array, num_points: int) -> tuple[jax.Array, jax.Array]:
    """CSR incidence of the flattened cell slots ``c * V + a`` by vertex ``cells[c, a]``.

    Returns ``(offsets (N + 1,), order (C * V,))``, both int32: the slots of vertex ``i`` are
    ``order[offsets[i]:offsets[i + 1]]``, in increasing order. Not differentiable (topology).
    """
    offsets, order = counting_sort(cells.reshape(1, -1).astype(jnp.int32), num_points)
    return offsets[0], order[0]


def stiffness_product(x: jax.Array, off_diagonal: jax.Array, cells: jax.Array, offsets: jax.Array, order: jax.Array) -> jax.Array:
    """``K x`` for ``x`` ``(N, D)``, entries ``(C, V (V - 1))``, cells ``(C, V)`` and the incidence."""
    num_points, dim = x.shape
    (y,) = _product(x.dtype, dim)(
        x, off_diagonal.reshape(-1), cells.reshape(-1), offsets, order, cells.shape[-1], launch=(1, num_points), shapes={"y": (num_points,)}
    )
    return y


def stiffness_diagonal(off_diagonal: jax.Array, cells: jax.Array, offsets: jax.Array, order: jax.Array) -> jax.Array:
    """``diag(K)`` ``(N,)``: minus the row sums of the off-diagonal entries (``cells`` gives ``V``)."""
    num_points = offsets.shape[0] - 1
    (diagonal,) = _diagonal(off_diagonal.dtype)(
        off_diagonal.reshape(-1), offsets, order, cells.shape[-1], launch=(1, num_points), shapes={"diagonal": (num_points,)}
    )
    return diagonal
