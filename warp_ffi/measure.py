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

from typing import Any, no_type_check

import jax

from . import _energy
from ._energy import Coordinates, PerItem, Topology, factorial, finite, gram_schmidt, load_cell, scatter_edge_gradients
from ._wrap import scalars, vectors
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["simplex_measures"]


@wp.func
@no_type_check
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
@no_type_check
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
@no_type_check
def _cell(points: Coordinates, reference: Coordinates, cells: Topology, b: int, c: int, num_points: int, num_dims: int):
    """The cell's state (``load_cell``) and reference measure; valid when usable with a finite, nonzero reference."""
    v, usable, e0, e1, e2, a0, a1, a2 = load_cell(points, reference, cells, b, c, num_points)
    rest = e0[0] - e0[0]
    if usable:
        rest = _measure(a0, a1, a2, cells.shape[1] - 1, num_dims)
    valid = usable and rest != type(rest)(0.0) and finite(rest)
    return valid, v, e0, e1, e2, a0, a1, a2, rest


@wp.kernel
@no_type_check
def _forward_kernel(
    points: Coordinates, reference: Coordinates, cells: Topology, num_points: int, num_dims: int, offset: int, measure: PerItem,
    reference_measure: PerItem,
):  # fmt: skip
    b, t = wp.tid()
    c = t + offset
    out = b * cells.shape[0] + c
    valid, v, e0, e1, e2, a0, a1, a2, rest = _cell(points, reference, cells, b, c, num_points, num_dims)
    if valid:
        measure[out] = _measure(e0, e1, e2, cells.shape[1] - 1, num_dims)
        reference_measure[out] = rest
    else:
        measure[out] = measure.dtype(wp.nan)
        reference_measure[out] = measure.dtype(wp.nan)


@wp.kernel
@no_type_check
def _adjoint_kernel(
    points: Coordinates, reference: Coordinates, cells: Topology, measure_bar: PerItem, reference_measure_bar: PerItem,
    num_points: int, num_dims: int, offset: int, points_bar: Coordinates, reference_bar: Coordinates,
):  # fmt: skip
    b, t = wp.tid()
    c = t + offset
    out = b * cells.shape[0] + c
    valid, v, e0, e1, e2, a0, a1, a2, rest = _cell(points, reference, cells, b, c, num_points, num_dims)
    if not valid:
        return
    m = cells.shape[1] - 1
    base = b * num_points
    g = measure_bar[out]
    g0, g1, g2 = _measure_gradient(e0, e1, e2, m, num_dims)
    scatter_edge_gradients(points_bar, base, v, m, g * g0, g * g1, g * g2)
    g = reference_measure_bar[out]
    g0, g1, g2 = _measure_gradient(a0, a1, a2, m, num_dims)
    scatter_edge_gradients(reference_bar, base, v, m, g * g0, g * g1, g * g2)


def _types(s):
    return {name: vectors(s) for name in ("points", "reference", *_energy.GRADIENT_NAMES)} | {
        name: scalars(s) for name in ("measure", "reference_measure", "measure_bar", "reference_measure_bar")
    }


_measures = _energy.per_item_terms(
    _energy.energy_family(_forward_kernel, _types, outputs=("measure", "reference_measure")),
    _energy.energy_family(_adjoint_kernel, _types, outputs=_energy.GRADIENT_NAMES, accumulate=_energy.GRADIENT_NAMES),
)


@jax.jit
def simplex_measures(points: jax.Array, reference_points: jax.Array, cells: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Current and reference measures ``(B, M)`` of ``(M, m + 1)`` cells on ``(B, N, D <= 3)`` points.

    NaN for invalid cells, which pass no gradient back. Differentiable once in reverse mode in
    both coordinate arrays; ``jit`` and ``vmap`` (sequential) compatible. Requires ``B, N, M > 0``.
    """
    num_batch, _, num_dims = points.shape
    measure, reference_measure = _measures(*_energy.kernel_inputs(points, reference_points, cells), (), num_batch, (num_dims,))
    return measure.reshape(num_batch, -1), reference_measure.reshape(num_batch, -1)
