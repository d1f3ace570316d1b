"""P1 stiffness products for the Sobolev filter as Warp kernels: deterministic vertex gathers.

Inputs arrive validated (no checks here): cells ``(C, V)`` int32 with indices in ``[0, N)``,
per-cell off-diagonal stiffness entries ``(C, V (V - 1))`` in row-major ``(a, b), a != b`` order,
blocks ``(N, D)`` of one float dtype.

The local matrices are assembled in JAX (so the geometry stays differentiable there); Warp only
does the bilinear product that dominates a conjugate-gradient solve,

    (K x)_i = sum over cells c with local vertex a at i, of sum_{b != a} K_c[a, b] (x_{c_b} - x_i),

in the difference form that makes constants exact null vectors. Each vertex *gathers* from its
incident ``(cell, local index)`` slots (a CSR incidence built once per solve: a serial counting
sort in Warp on CPU, ``argsort`` on GPU), so there are no atomics and results are bitwise
deterministic. CPU launches are split over the cores (``launch_in_chunks``). Nothing here is
differentiated: the solve-level ``custom_vjp`` in ``geomjax.deform.sobolev`` applies the implicit
adjoint with these same products.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from ._kernels import WARP_SCALAR, launch_in_chunks
from ._kernels import warp as wp

__all__ = ["vertex_incidence", "stiffness_product", "stiffness_diagonal"]


@wp.kernel(enable_backward=False)
def _counting_sort_kernel(
    cells: wp.array(dtype=wp.int32),
    num_points: wp.int32,
    offsets: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    cursor: wp.array(dtype=wp.int32),
):
    """One thread: stable counting sort of the flattened cell slots by vertex."""
    for v in range(num_points + 1):
        offsets[v] = 0
    for s in range(cells.shape[0]):
        offsets[cells[s] + 1] += 1
    for v in range(num_points):
        offsets[v + 1] += offsets[v]
        cursor[v] = offsets[v]
    for s in range(cells.shape[0]):
        v = cells[s]
        order[cursor[v]] = s
        cursor[v] += 1


@wp.kernel(enable_backward=False)
def _product_kernel(
    x: wp.array(dtype=Any),
    off_diagonal: wp.array(dtype=Any),
    cells: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    num_cell_points: wp.int32,
    offset: wp.int32,
    y: wp.array(dtype=Any),
):
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
def _diagonal_kernel(
    off_diagonal: wp.array(dtype=Any),
    offsets: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    num_cell_points: wp.int32,
    offset: wp.int32,
    diagonal: wp.array(dtype=Any),
):
    _, t = wp.tid()
    i = t + offset
    total = diagonal.dtype(0.0)
    others = num_cell_points - 1
    for k in range(offsets[i], offsets[i + 1]):
        entries = order[k] * others
        for s in range(others):
            total -= off_diagonal[entries + s]
    diagonal[i] = total


_INDEX = wp.array(dtype=wp.int32)


@functools.cache
def _counting_sort():
    return wp.jax_kernel(_counting_sort_kernel, num_outputs=3, vmap_method="sequential")


def vertex_incidence(cells: jax.Array, num_points: int) -> tuple[jax.Array, jax.Array]:
    """CSR incidence of the flattened cell slots ``c * V + a`` by vertex ``cells[c, a]``.

    Returns ``(offsets (N + 1,), order (C * V,))``, both int32: the slots of vertex ``i`` are
    ``order[offsets[i]:offsets[i + 1]]``, in increasing order. Not differentiable (topology).
    """
    flat = cells.reshape(-1).astype(jnp.int32)
    if jax.default_backend() != "cpu":
        order = jnp.argsort(flat, stable=True).astype(jnp.int32)
        offsets = jnp.searchsorted(flat[order], jnp.arange(num_points + 1, dtype=jnp.int32)).astype(jnp.int32)
        return offsets, order
    offsets, order, _ = _counting_sort()(
        flat, num_points, launch_dims=(1,),
        output_dims={"offsets": (num_points + 1,), "order": flat.shape, "cursor": (max(num_points, 1),)},
    )  # fmt: skip
    return offsets, order


@functools.cache
def _product_callable(dtype, dim: int, num_cell_points: int):
    scalar = WARP_SCALAR[jnp.dtype(dtype)]
    vector = wp.array(dtype=wp.types.vector(dim, scalar))
    types = {"x": vector, "off_diagonal": wp.array(dtype=scalar), "cells": _INDEX, "offsets": _INDEX, "order": _INDEX}
    kernel = wp.overload(_product_kernel, {**types, "num_cell_points": wp.int32, "offset": wp.int32, "y": vector})

    def product(x, off_diagonal, cells, offsets, order, y):
        launch_in_chunks(kernel, 1, x.shape[0], [x, off_diagonal, cells, offsets, order, num_cell_points], [y])

    product.__annotations__ = {**types, "y": vector}
    product.__module__ = __name__
    return wp.jax_callable(product, num_outputs=1, vmap_method="sequential")


@functools.cache
def _diagonal_callable(dtype, num_cell_points: int):
    scalar = WARP_SCALAR[jnp.dtype(dtype)]
    types = {"off_diagonal": wp.array(dtype=scalar), "offsets": _INDEX, "order": _INDEX}
    kernel = wp.overload(
        _diagonal_kernel, {**types, "num_cell_points": wp.int32, "offset": wp.int32, "diagonal": wp.array(dtype=scalar)}
    )

    def diagonal_of(off_diagonal, offsets, order, diagonal):
        launch_in_chunks(kernel, 1, diagonal.shape[0], [off_diagonal, offsets, order, num_cell_points], [diagonal])

    diagonal_of.__annotations__ = {**types, "diagonal": wp.array(dtype=scalar)}
    diagonal_of.__module__ = __name__
    return wp.jax_callable(diagonal_of, num_outputs=1, vmap_method="sequential")


def stiffness_product(
    x: jax.Array, off_diagonal: jax.Array, cells: jax.Array, offsets: jax.Array, order: jax.Array
) -> jax.Array:
    """``K x`` for ``x`` ``(N, D)``, entries ``(C, V (V - 1))``, cells ``(C, V)`` and the incidence."""
    (y,) = _product_callable(x.dtype, x.shape[-1], cells.shape[-1])(
        x, off_diagonal.reshape(-1), cells.reshape(-1), offsets, order, output_dims={"y": x.shape[:1]}
    )
    return y


def stiffness_diagonal(off_diagonal: jax.Array, cells: jax.Array, offsets: jax.Array, order: jax.Array) -> jax.Array:
    """``diag(K)`` ``(N,)``: minus the row sums of the off-diagonal entries (``cells`` gives ``V``)."""
    num_points = offsets.shape[0] - 1
    (diagonal,) = _diagonal_callable(off_diagonal.dtype, cells.shape[-1])(
        off_diagonal.reshape(-1), offsets, order, output_dims={"diagonal": (num_points,)}
    )
    return diagonal
