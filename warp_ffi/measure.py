"""Per-cell simplex measures on Warp (measure, total measure and inversion energies).

``simplex_measures(points, reference_points, cells)`` returns the current and reference measure
of every cell, ``(B, M)`` each: the signed ``det E / m!`` for full-dimensional cells (``m = D``)
and the unsigned Gram-Schmidt measure ``r00 r11 r22 / m!`` for embedded ones, NaN for invalid
cells (see ``_energy``). The energies are cheap elementwise functions of these two numbers and
stay in JAX; the kernels do the gathers and, in the adjoint, the scatter-add of vertex gradients
that dominates the JAX path's time.

Adjoint: ``d det / d e_k`` are cofactors (``e1 x e2`` etc.); for the embedded measure
``d V / d E = adj(R) Q^T / m!`` (rows are edges), a polynomial in ``R`` with no division, which
is zero at an exact collapse like the JAX path's safe norm.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from ._energy import (
    cell_edges,
    factorial,
    finite,
    finite3,
    flat_vectors,
    gram_schmidt,
    kernel_indices,
    launch,
    scatter_edge_gradients,
    sorted_cell,
)
from ._kernels import WARP_SCALAR
from ._kernels import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["simplex_measures"]


@wp.func
def _measure(e0: Any, e1: Any, e2: Any, m: int, num_dims: int):
    """Signed ``det / m!`` when ``m = D``, else the unsigned Gram-Schmidt measure."""
    if m == num_dims:
        det = e0[0]
        if m == 2:
            det = e0[0] * e1[1] - e0[1] * e1[0]
        elif m == 3:
            det = wp.dot(e0, wp.cross(e1, e2))
        return det / factorial(m, det)
    q0, q1, q2, r00, r01, r02, r11, r12, r22 = gram_schmidt(e0, e1, e2, m)
    return r00 * r11 * r22 / factorial(m, r00)


@wp.func
def _measure_gradient(e0: Any, e1: Any, e2: Any, m: int, num_dims: int):
    """``d measure / d e_k`` for ``k < 3`` (unused entries zero)."""
    zero = e0 - e0
    if m == num_dims:
        s = type(e0[0])(1.0) / factorial(m, e0[0])
        if m == 1:
            g = zero
            g[0] = s
            return g, zero, zero
        if m == 2:
            g0 = zero
            g1 = zero
            g0[0] = e1[1] * s
            g0[1] = -e1[0] * s
            g1[0] = -e0[1] * s
            g1[1] = e0[0] * s
            return g0, g1, zero
        return wp.cross(e1, e2) * s, wp.cross(e2, e0) * s, wp.cross(e0, e1) * s
    q0, q1, q2, r00, r01, r02, r11, r12, r22 = gram_schmidt(e0, e1, e2, m)
    if m == 1:
        return q0, zero, zero
    if m == 2:
        half = type(r00)(0.5)
        return (r11 * q0 - r01 * q1) * half, (r00 * q1) * half, zero
    sixth = type(r00)(1.0) / type(r00)(6.0)
    g0 = (r11 * r22) * q0 - (r01 * r22) * q1 + (r01 * r12 - r02 * r11) * q2
    g1 = (r00 * r22) * q1 - (r00 * r12) * q2
    g2 = (r00 * r11) * q2
    return g0 * sixth, g1 * sixth, g2 * sixth


@wp.func
def _load(points: wp.array(dtype=Any), reference: wp.array(dtype=Any), cells: wp.array2d(dtype=wp.int32), b: int, c: int, num_points: int):
    """Sorted vertices, both edge sets and whether the cell is usable (indices, finiteness)."""
    m = cells.shape[1] - 1
    v, in_range = sorted_cell(cells, c, num_points)
    zero = points[0] - points[0]
    e0 = zero
    e1 = zero
    e2 = zero
    a0 = zero
    a1 = zero
    a2 = zero
    usable = False
    if in_range:
        base = b * num_points
        e0, e1, e2 = cell_edges(points, base, v, m)
        a0, a1, a2 = cell_edges(reference, base, v, m)
        usable = finite3(e0, e1, e2) and finite3(a0, a1, a2)
    return v, usable, e0, e1, e2, a0, a1, a2


@wp.kernel
def _forward_kernel(
    points: wp.array(dtype=Any),
    reference: wp.array(dtype=Any),
    cells: wp.array2d(dtype=wp.int32),
    num_points: int,
    num_dims: int,
    offset: int,
    measure: wp.array(dtype=Any),
    reference_measure: wp.array(dtype=Any),
):
    b, t = wp.tid()
    c = t + offset
    num_cells = cells.shape[0]
    if c >= num_cells:
        return
    out = b * num_cells + c
    m = cells.shape[1] - 1
    nan = measure.dtype(wp.nan)
    v, usable, e0, e1, e2, a0, a1, a2 = _load(points, reference, cells, b, c, num_points)
    if not usable:
        measure[out] = nan
        reference_measure[out] = nan
        return
    rest = _measure(a0, a1, a2, m, num_dims)
    if rest == measure.dtype(0.0) or not finite(rest):
        measure[out] = nan
        reference_measure[out] = nan
        return
    measure[out] = _measure(e0, e1, e2, m, num_dims)
    reference_measure[out] = rest


@wp.kernel
def _adjoint_kernel(
    points: wp.array(dtype=Any),
    reference: wp.array(dtype=Any),
    cells: wp.array2d(dtype=wp.int32),
    measure_bar: wp.array(dtype=Any),
    reference_measure_bar: wp.array(dtype=Any),
    num_points: int,
    num_dims: int,
    offset: int,
    points_bar: wp.array(dtype=Any),
    reference_bar: wp.array(dtype=Any),
):
    b, t = wp.tid()
    c = t + offset
    num_cells = cells.shape[0]
    if c >= num_cells:
        return
    out = b * num_cells + c
    m = cells.shape[1] - 1
    v, usable, e0, e1, e2, a0, a1, a2 = _load(points, reference, cells, b, c, num_points)
    if not usable:
        return
    rest = _measure(a0, a1, a2, m, num_dims)
    if rest == measure_bar.dtype(0.0) or not finite(rest):
        return
    base = b * num_points
    g = measure_bar[out]
    g0, g1, g2 = _measure_gradient(e0, e1, e2, m, num_dims)
    scatter_edge_gradients(points_bar, base, v, m, g * g0, g * g1, g * g2)
    g = reference_measure_bar[out]
    g0, g1, g2 = _measure_gradient(a0, a1, a2, m, num_dims)
    scatter_edge_gradients(reference_bar, base, v, m, g * g0, g * g1, g * g2)


@functools.cache
def _callables(dtype):
    """``(forward, adjoint)`` JAX callables for one float dtype."""
    scalar = WARP_SCALAR[jnp.dtype(dtype)]
    vectors = wp.array(dtype=wp.types.vector(3, scalar))
    reals = wp.array(dtype=scalar)
    cells_type = wp.array2d(dtype=wp.int32)
    forward_kernel = wp.overload(_forward_kernel, [vectors, vectors, cells_type, int, int, int, reals, reals])
    adjoint_kernel = wp.overload(_adjoint_kernel, [vectors, vectors, cells_type, reals, reals, int, int, int, vectors, vectors])

    def forward(points, reference, cells, num_dims, measure, reference_measure):
        num_batch = measure.shape[0] // cells.shape[0]
        num_points = points.shape[0] // num_batch
        launch(forward_kernel, num_batch, cells.shape[0], [points, reference, cells, num_points, num_dims], [measure, reference_measure])

    def adjoint(points, reference, cells, measure_bar, reference_measure_bar, num_dims, points_bar, reference_bar):
        num_batch = measure_bar.shape[0] // cells.shape[0]
        num_points = points.shape[0] // num_batch
        inputs = [points, reference, cells, measure_bar, reference_measure_bar, num_points, num_dims]
        launch(adjoint_kernel, num_batch, cells.shape[0], inputs, [points_bar, reference_bar], accumulated=(0, 1))

    forward.__annotations__ = dict(points=vectors, reference=vectors, cells=cells_type, num_dims=int, measure=reals, reference_measure=reals)
    adjoint.__annotations__ = dict(
        points=vectors, reference=vectors, cells=cells_type, measure_bar=reals, reference_measure_bar=reals, num_dims=int,
        points_bar=vectors, reference_bar=vectors,
    )  # fmt: skip
    return (
        wp.jax_callable(forward, num_outputs=2, vmap_method="sequential"),
        wp.jax_callable(adjoint, num_outputs=2, vmap_method="sequential"),
    )


# Register both overloads now: a new overload after the module is built forces a rebuild.
for _dtype in WARP_SCALAR:
    _callables(_dtype)


@jax.jit
def simplex_measures(points: jax.Array, reference_points: jax.Array, cells: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Current and reference measures ``(B, M)`` of ``(M, m + 1)`` cells on ``(B, N, D <= 3)`` points.

    NaN for invalid cells, which pass no gradient back. Differentiable once in reverse mode in
    both coordinate arrays; ``jit`` and ``vmap`` (sequential) compatible. Requires ``B, N, M > 0``.
    """
    num_batch, num_points, num_dims = points.shape
    indices = kernel_indices(cells, num_points)
    measure, reference_measure = _measures(flat_vectors(points), flat_vectors(reference_points), indices, num_batch, num_dims)
    return measure.reshape(num_batch, -1), reference_measure.reshape(num_batch, -1)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def _measures(points, reference, cells, num_batch, num_dims):
    return _measures_fwd(points, reference, cells, num_batch, num_dims)[0]


def _measures_fwd(points, reference, cells, num_batch, num_dims):
    forward, _ = _callables(points.dtype)
    size = (num_batch * cells.shape[0],)
    outputs = forward(points, reference, cells, num_dims, output_dims={"measure": size, "reference_measure": size})
    return tuple(outputs), (points, reference, cells)


def _measures_bwd(num_batch, num_dims, residuals, cotangents):
    points, reference, cells = residuals
    _, adjoint = _callables(points.dtype)
    dims = {"points_bar": points.shape[:1], "reference_bar": points.shape[:1]}
    points_bar, reference_bar = adjoint(points, reference, cells, *cotangents, num_dims, output_dims=dims)
    return points_bar, reference_bar, None


_measures.defvjp(_measures_fwd, _measures_bwd)
