"""Per-simplex measure (length, area, volume) penalty relative to the rest geometry."""

from __future__ import annotations

import jax.numpy as jnp

from .._errors import raises_documented_errors
from .._points import remove_batch_axis
from .._validate import check_real_scalar
from ._simplex import (
    SIMPLEX_VERTICES,
    Cells,
    Energy,
    Points,
    cell_measures,
    check_energy_inputs,
    check_reduction,
    reduce_terms,
    select_energy_backend,
    simplex_dimension,
)

__all__ = ["simplex_measure_energy"]


@raises_documented_errors
def simplex_measure_energy(
    points: Points, reference_points: Points, cells: Cells, *, target_ratio: float = 1.0, reduction: str = "sum", implementation: str | None = None
) -> Energy:
    r"""Penalise each simplex's measure change relative to its rest measure.

    Each term is ``(1/2) V_0 (q - q_*)^2`` with ``q_* = target_ratio``. For full-dimensional
    cells (``m = D``) ``q = det E / det E_0`` is signed (consecutive edges of the vertex-sorted
    cell, explicit determinants), so a reflected cell has ``q = -1`` and does not satisfy the
    target, and ``V_0 = |det E_0| / m!``. For embedded cells (``m < D``) ``q`` is the unsigned
    ratio of intrinsic measures, each the product of the modified Gram-Schmidt norms of the
    edges divided by ``m!`` (norms, not Gram determinants); at an exact collapse of the current
    cell its subgradient is zero, so this term alone cannot reopen a collapsed embedded cell.

    Args:
        points: current coordinates ``(N, D)`` or aligned batched ``(B, N, D)``, float32/float64.
        reference_points: rest coordinates, exactly the shape, dtype and device of ``points``.
        cells: shared ``(M, m + 1)`` int32/int64 edges, triangles or tetrahedra, ``D >= m``.
            Values are not checked: they must be distinct, in-range indices (see below).
        target_ratio: strictly positive target ``q_*`` (finite, not underflowing the dtype).
        reduction: ``"none"`` (``(M,)`` or ``(B, M)``), ``"sum"`` or ``"mean"`` (sum over
            ``max(count, 1)``). No cells give ``0`` for ``"sum"`` and ``"mean"``.
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``. Warp handles
            ``D <= 3``. ``None`` picks Warp on CPU for ``D <= 3`` when warp-lang is installed, else
            ``"jax"`` (also on GPU, not yet measured); ``benchmarks/bench_energy.py`` measures it.

    Returns:
        Per-cell terms or a scalar according to ``reduction``, dtype of ``points``.

    Invalid cells give NaN terms that pass no gradient back: an out-of-range index, non-finite
    coordinates, or a zero or non-finite reference measure; with no points every term is NaN.

    Raises:
        TypeError: non-float coordinates, mismatched dtypes, non-integer ``cells``, a ``bool``
            or non-real ``target_ratio``.
        ValueError: bad shapes, ``D < m``, a ``target_ratio`` that is not finite, not positive
            or underflows, an unknown ``reduction``, ``implementation="warp"`` with ``D > 3``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiable in ``points`` and ``reference_points`` (any order on the JAX path);
    see the README's "Backends and transforms" for what each backend differentiates and
    "Sharding" for designs split over devices (the Warp kernel runs shard by shard).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import simplex_measure_energy
        >>> rest = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
        >>> cells = jnp.array([[0, 1, 2], [1, 3, 2]])
        >>> current = rest.at[3].set(jnp.array([0.0, 0.0]))  # second cell reflected onto the first
        >>> terms = simplex_measure_energy(current, rest, cells, reduction="none", implementation="jax")
        >>> print(np.round(np.asarray(terms), 6))
        [0. 1.]
    """
    points, reference_points, cells, batched = check_energy_inputs(points, reference_points, cells, topology_name="cells", vertices_per_row=SIMPLEX_VERTICES)
    simplex_dimension("simplex_measure_energy", cells, points.shape[-1])
    target_ratio = check_real_scalar("target_ratio", target_ratio, points.dtype, positive=True)
    check_reduction(reduction)
    backend = select_energy_backend("simplex_measure_energy", implementation, points)

    measure, reference_measure = cell_measures(points, reference_points, cells, backend)
    terms = jnp.abs(reference_measure) * jnp.square(measure / reference_measure - target_ratio) / 2
    return reduce_terms(remove_batch_axis(terms, batched), reduction)
