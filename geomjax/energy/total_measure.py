"""Penalty on the change of the total simplex measure (local redistribution allowed)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._errors import raises_documented_errors
from .._points import remove_batch_axis
from .._validate import check_real_scalar
from . import _simplex as simplex
from ._simplex import Cells, Energy, Points

__all__ = ["total_measure_energy"]


@raises_documented_errors
def total_measure_energy(
    points: Points, reference_points: Points, cells: Cells, *, target_ratio: float = 1.0, reduction: str = "sum", implementation: str | None = None
) -> Energy:
    r"""Penalise the change of the total measure of a simplex set, one term per batch item.

    With the per-cell rest measures ``V_{0,i}`` and ratios ``q_i`` of
    :func:`~geomjax.simplex_measure_energy` (signed for full-dimensional cells, unsigned for
    embedded ones), ``V_{0,tot} = sum_i V_{0,i}``, ``V = sum_i V_{0,i} q_i`` and each term is::

        (1/2) V_{0,tot} (V / V_{0,tot} - q_*)^2.

    Cells may expand and contract as long as the aggregate stays at the target; local
    inversions can cancel in the sum, so combine this with strain and inversion terms where
    local validity matters.

    Args:
        points: current coordinates ``(N, D)`` or aligned batched ``(B, N, D)``, float32/float64.
        reference_points: rest coordinates, exactly the shape, dtype and device of ``points``.
        cells: non-empty shared ``(M, m + 1)`` int32/int64 edges, triangles or tetrahedra,
            ``D >= m``. Values are not checked: they must be distinct, in-range indices.
        target_ratio: strictly positive target ``q_*`` (finite, not underflowing the dtype).
        reduction: ``"none"`` (a scalar for unbatched input, ``(B,)`` for batched), ``"sum"``
            or ``"mean"`` over the batch.
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``. Warp handles
            ``D <= 3``. ``None`` picks Warp on CPU for ``D <= 3`` when warp-lang is installed, else
            ``"jax"`` (also on GPU, not yet measured), as for :func:`~geomjax.simplex_measure_energy`.

    Returns:
        One term per batch item or a scalar according to ``reduction``, dtype of ``points``.

    A batch item's term is NaN, and passes no gradient back, when one of its cells is invalid
    (out-of-range index, non-finite coordinates, zero or non-finite reference measure) or
    ``V_{0,tot}`` is not positive and finite; with no points it is NaN.

    Raises:
        TypeError: non-float coordinates, mismatched dtypes, non-integer ``cells``, a ``bool``
            or non-real ``target_ratio``.
        ValueError: bad shapes, empty ``cells``, ``D < m``, a ``target_ratio`` that is not
            finite, not positive or underflows, an unknown ``reduction``,
            ``implementation="warp"`` with ``D > 3``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiable in ``points`` and ``reference_points`` through the summed measures;
    see the README's "Backends and transforms" for what each backend differentiates and
    "Sharding" for designs split over devices (the Warp kernel runs shard by shard).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import total_measure_energy
        >>> rest = jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.5, 0.5]])
        >>> cells = jnp.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        >>> shifted = rest.at[4].set(jnp.array([0.3, 0.6]))  # area moves between the cells
        >>> print(np.round(float(total_measure_energy(shifted, rest, cells, implementation="jax")), 6))
        0.0
        >>> print(np.round(float(total_measure_energy(1.1 * rest, rest, cells, implementation="jax")), 6))
        0.02205
    """
    points, reference_points, cells, batched = simplex.check_energy_inputs(
        points, reference_points, cells, topology_name="cells", vertices_per_row=simplex.SIMPLEX_VERTICES
    )
    simplex.simplex_dimension("total_measure_energy", cells, points.shape[-1])
    if cells.shape[0] == 0:
        raise ValueError("total_measure_energy needs at least one cell, got cells of shape (0, K)")
    target_ratio = check_real_scalar("target_ratio", target_ratio, points.dtype, positive=True)
    simplex.check_reduction(reduction)
    backend = simplex.select_energy_backend("total_measure_energy", implementation, points)

    measure, reference_measure = simplex.cell_measures(points, reference_points, cells, backend)
    terms = total_terms(measure, reference_measure, target_ratio)
    return simplex.reduce_terms(remove_batch_axis(terms, batched), reduction)


def total_terms(measure: jax.Array, reference_measure: jax.Array, target_ratio: float) -> jax.Array:
    """Per-batch terms ``(B,)`` from per-cell measures ``(B, M)`` (NaN for invalid cells)."""
    # V_0,i q_i = |V_0,i| V_i / V_0,i = sign(V_0,i) V_i, exactly.
    total = jnp.sum(jnp.sign(reference_measure) * measure, axis=-1)
    reference_total = jnp.sum(jnp.abs(reference_measure), axis=-1)
    valid = jnp.isfinite(total) & jnp.isfinite(reference_total) & (reference_total > 0)
    total = jnp.where(valid, total, 0)
    reference_total = jnp.where(valid, reference_total, 1)
    return jnp.where(valid, reference_total * jnp.square(total / reference_total - target_ratio) / 2, jnp.nan)
