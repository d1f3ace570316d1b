"""Squared-hinge penalty on full-dimensional cells below a signed Jacobian threshold."""

from __future__ import annotations

import jax.numpy as jnp

from .._errors import raises_documented_errors
from .._points import remove_batch_axis
from .._validate import check_real_scalar
from ._simplex import SIMPLEX_VERTICES, Cells, Energy, Points, cell_measures, check_energy_inputs, check_reduction, reduce_terms, select_energy_backend

__all__ = ["simplex_inversion_energy"]


@raises_documented_errors
def simplex_inversion_energy(
    points: Points, reference_points: Points, cells: Cells, *, minimum_jacobian: float = 0.1, reduction: str = "sum", implementation: str | None = None
) -> Energy:
    r"""Penalise full-dimensional cells whose signed Jacobian falls below a threshold.

    Each term is ``(1/2) V_0 max(0, J_min - J)^2`` with ``J = det E / det E_0`` (consecutive
    edges of the vertex-sorted cell), ``V_0 = |det E_0| / m!`` and ``J_min = minimum_jacobian``.
    It is zero above the threshold and grows quadratically through collapse and inversion: a
    continuously differentiable squared hinge (its second derivative jumps at ``J = J_min``),
    not an infinite barrier.

    Args:
        points: current coordinates ``(N, D)`` or aligned batched ``(B, N, D)``, float32/float64.
        reference_points: rest coordinates, exactly the shape, dtype and device of ``points``.
        cells: shared full-dimensional ``(M, D + 1)`` int32/int64 connectivity: edges in 1D,
            triangles in 2D, tetrahedra in 3D. Values are not checked: they must be distinct,
            in-range indices (see below).
        minimum_jacobian: non-negative threshold ``J_min``.
        reduction: ``"none"`` (``(M,)`` or ``(B, M)``), ``"sum"`` or ``"mean"`` (sum over
            ``max(count, 1)``). No cells give ``0`` for ``"sum"`` and ``"mean"``.
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``. ``None`` picks
            Warp on CPU when warp-lang is installed (``benchmarks/bench_energy.py``), else ``"jax"``
            (also on GPU, not yet measured).

    Returns:
        Per-cell terms or a scalar according to ``reduction``, dtype of ``points``.

    Invalid cells give NaN terms that pass no gradient back: an out-of-range index, non-finite
    coordinates, or a zero or non-finite reference determinant; with no points every term is
    NaN.

    Raises:
        TypeError: non-float coordinates, mismatched dtypes, non-integer ``cells``, a ``bool``
            or non-real ``minimum_jacobian``.
        ValueError: bad shapes, embedded cells (``m != D``: the determinant is undefined), a
            negative or non-finite ``minimum_jacobian``, an unknown ``reduction``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiable in ``points`` and ``reference_points``; on the JAX path to any order (away
    from the threshold for the second); see the README's "Backends and transforms" for what each backend differentiates and
    "Sharding" for designs split over devices (the Warp kernel runs shard by shard).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import simplex_inversion_energy
        >>> rest = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        >>> cells = jnp.array([[0, 1, 2]])
        >>> flipped = rest * jnp.array([-1.0, 1.0])  # J = -1
        >>> print(np.round(float(simplex_inversion_energy(flipped, rest, cells, implementation="jax")), 6))
        0.3025
    """
    points, reference_points, cells, batched = check_energy_inputs(points, reference_points, cells, topology_name="cells", vertices_per_row=SIMPLEX_VERTICES)
    m, num_dims = cells.shape[1] - 1, points.shape[-1]
    if m != num_dims:
        raise ValueError(
            f"simplex_inversion_energy needs full-dimensional cells (m == D): cells with {m + 1} vertices "
            f"are {m}-simplices but points have D={num_dims} coordinates"
        )
    minimum_jacobian = check_real_scalar("minimum_jacobian", minimum_jacobian, points.dtype, nonnegative=True)
    check_reduction(reduction)
    backend = select_energy_backend("simplex_inversion_energy", implementation, points)

    measure, reference_measure = cell_measures(points, reference_points, cells, backend)
    # maximum (not where) keeps NaN terms NaN.
    shortfall = jnp.maximum(minimum_jacobian - measure / reference_measure, 0)
    terms = jnp.abs(reference_measure) * jnp.square(shortfall) / 2
    return reduce_terms(remove_batch_axis(terms, batched), reduction)
