"""St. Venant-Kirchhoff strain energy of edges, triangles and tetrahedra in any dimension."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .._errors import raises_documented_errors
from .._points import remove_batch_axis
from .._validate import check_real_scalar
from ._simplex import (
    SIMPLEX_VERTICES,
    Cells,
    Energy,
    Points,
    check_energy_inputs,
    check_reduction,
    dot,
    gram_schmidt,
    reduce_terms,
    row_terms,
    select_energy_backend,
    simplex_dimension,
    simplex_edges,
)

__all__ = ["simplex_strain_energy"]


@raises_documented_errors
def simplex_strain_energy(
    points: Points,
    reference_points: Points,
    cells: Cells,
    *,
    lame_lambda: float = 1.0,
    shear_modulus: float = 1.0,
    reduction: str = "sum",
    implementation: str | None = None,
) -> Energy:
    r"""Reference-integrated St. Venant-Kirchhoff energy of every simplex.

    For a cell with consecutive edges ``E`` (rows ``x_{k+1} - x_k`` after sorting the cell's
    vertex indices) and reference edges ``E_0``, the reduced QR ``E_0^T = Q R`` (modified
    Gram-Schmidt) gives an orthonormal intrinsic frame; ``F = E^T R^{-1}``, ``C = F^T F``,
    ``eps = (C - I) / 2`` and ``V_0 = |prod diag R| / m!``. Each term is::

        V_0 [mu |eps|_F^2 + (lambda / 2) tr(eps)^2]
          = V_0 [mu |dev eps|^2 + (lambda / 2 + mu / m) tr(eps)^2],

    evaluated in the second form, which stays non-negative for admissible negative ``lambda``.
    Rigid motions and reflections give zero (the energy is reflection-blind: add
    :func:`~geomjax.simplex_inversion_energy` where orientation matters).

    Args:
        points: current coordinates ``(N, D)`` or aligned batched ``(B, N, D)``, float32/float64.
        reference_points: rest coordinates, exactly the shape, dtype and device of ``points``.
        cells: shared ``(M, m + 1)`` int32/int64 connectivity with ``m`` in 1, 2, 3 and
            ``D >= m`` (edges, triangles, tetrahedra, possibly embedded). Values are not checked:
            they must be distinct, in-range indices (see below).
        lame_lambda: first Lame parameter; finite, may be negative as long as
            ``lame_lambda + 2 * shear_modulus / m >= 0``.
        shear_modulus: non-negative shear modulus ``mu``.
        reduction: ``"none"`` (one term per cell, ``(M,)`` or ``(B, M)``), ``"sum"`` (the
            integrated total over every batch item and cell) or ``"mean"`` (sum over
            ``max(count, 1)``). No cells give ``0`` for ``"sum"`` and ``"mean"``.
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``. Warp handles
            ``D <= 3``. ``None`` picks Warp on CPU for ``D <= 3`` when warp-lang is installed, else
            ``"jax"`` (also on GPU, not yet measured): the Warp path avoids JAX's vertex-gradient
            scatter-add, which dominates on CPU (``benchmarks/bench_energy.py``).

    Returns:
        Per-cell terms or a scalar according to ``reduction``, dtype of ``points``.

    Invalid cells give NaN terms that pass no gradient back: an out-of-range index, non-finite
    coordinates, or a degenerate reference cell (a zero diagonal entry of ``R``); with no points
    every term is NaN. Invalid rest geometry is thus visible to an optimizer, never regularised.

    Raises:
        TypeError: non-float coordinates, mismatched dtypes, non-integer ``cells``, a ``bool``
            or non-real modulus.
        ValueError: bad shapes, ``D < m``, a non-finite modulus, ``shear_modulus < 0``, a
            negative ``lame_lambda + 2 * shear_modulus / m`` or a ``lame_lambda / 2 +
            shear_modulus / m`` beyond the dtype's range ("must be finite"), an unknown ``reduction``,
            ``implementation="warp"`` with ``D > 3``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiable in ``points`` and ``reference_points`` (connectivity is discrete), to any
    order on the JAX path (Hessian-vector products); see the README's "Backends and transforms" for what each backend differentiates and
    "Sharding" for designs split over devices (the Warp kernel runs shard by shard).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import simplex_strain_energy
        >>> rest = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        >>> stretched = rest * jnp.array([1.1, 1.0])
        >>> cells = jnp.array([[0, 1, 2]])
        >>> energy = simplex_strain_energy(stretched, rest, cells, lame_lambda=1.0, shear_modulus=1.0, implementation="jax")
        >>> eps = (1.1**2 - 1) / 2  # V_0 [mu eps^2 + (lambda / 2) eps^2] with V_0 = 1/2
        >>> print(np.round(float(energy), 6), np.round(0.5 * 1.5 * eps**2, 6))
        0.008269 0.008269
    """
    points, reference_points, cells, batched = check_energy_inputs(points, reference_points, cells, topology_name="cells", vertices_per_row=SIMPLEX_VERTICES)
    m = simplex_dimension("simplex_strain_energy", cells, points.shape[-1])
    lame_lambda = check_real_scalar("lame_lambda", lame_lambda, points.dtype)
    shear_modulus = check_real_scalar("shear_modulus", shear_modulus, points.dtype, nonnegative=True)
    bulk_term = lame_lambda / 2 + shear_modulus / m
    if not abs(bulk_term) <= float(jnp.finfo(points.dtype).max):  # inf, or beyond the dtype
        # Each modulus is representable, but the kernels' bulk coefficient would overflow to inf.
        raise ValueError(
            f"lame_lambda / 2 + shear_modulus / simplex_dimension must be finite in {jnp.dtype(points.dtype)}, got "
            f"{lame_lambda} / 2 + {shear_modulus} / {m} = {bulk_term}"
        )
    if bulk_term < 0:
        # 2 * bulk_term is the quoted combination; formed from the halves it cannot overflow
        # where 2 * shear_modulus would (a modulus near the float max).
        combination = 2 * bulk_term if abs(bulk_term) <= float(jnp.finfo(points.dtype).max) / 2 else f"{bulk_term} * 2"
        raise ValueError(
            f"lame_lambda + 2 * shear_modulus / simplex_dimension must be nonnegative, got {lame_lambda} + 2 * {shear_modulus} / {m} = {combination}"
        )
    check_reduction(reduction)
    backend = select_energy_backend("simplex_strain_energy", implementation, points)

    def warp_terms(p, r, c):
        from warp_ffi.strain import simplex_strain_terms

        return simplex_strain_terms(p, r, c, shear_modulus=shear_modulus, bulk_term=bulk_term)

    def jax_terms(p, r, c):
        return strain_terms(p, r, c, shear_modulus, bulk_term)

    terms = row_terms(points, reference_points, cells, backend, warp_terms, jax_terms)
    return reduce_terms(remove_batch_axis(terms, batched), reduction)


@jax.jit
def strain_terms(points: jax.Array, reference_points: jax.Array, cells: jax.Array, shear_modulus: float, bulk_term: float) -> jax.Array:
    """Per-cell energies ``(B, M)`` for ``(B, N, D)`` points (the JAX specification).

    ``bulk_term`` is ``lambda / 2 + mu / m``. Invalid cells are NaN with no gradient: their
    ``R`` is replaced by the identity before the triangular solve, so nothing non-finite is
    ever differentiated.
    """
    strain, reference_measure, valid = green_strains(points, reference_points, cells)
    m = max(i for i, _ in strain) + 1
    trace = _trace(strain, m)
    mean = trace / m
    deviatoric = jnp.square(strain[0, 0] - mean)
    for i in range(1, m):
        deviatoric = deviatoric + jnp.square(strain[i, i] - mean)
    if m > 1:
        shear = sum(jnp.square(strain[i, j]) for i in range(m) for j in range(i + 1, m))
        deviatoric = deviatoric + 2 * shear
    density = shear_modulus * deviatoric + bulk_term * jnp.square(trace)
    return jnp.where(valid, reference_measure * density, jnp.nan)


def strain_residuals(points: jax.Array, reference_points: jax.Array, cells: jax.Array, shear_modulus: float, bulk_term: float):
    """Each cell's term of :func:`simplex_strain_energy` as a sum of squares: ``(residuals (B, M, R), valid (B, M))``.

    ``sum_k residuals[..., k]^2`` is the cell's energy for Python reals ``shear_modulus >= 0`` and
    ``bulk_term = lambda / 2 + mu / m >= 0``: ``sqrt(V_0 mu)`` times the deviatoric diagonal
    strains, ``sqrt(2 V_0 mu)`` times the off-diagonal ones and ``sqrt(V_0 bulk_term)`` times the
    trace (``R = m (m + 1) / 2 + 1``). They are linear in the strain, as a Gauss-Newton solver
    needs (the square root of the energy is not differentiable at the rest shape). Invalid cells
    get the residuals of an identity frame and ``valid`` false.
    """
    strain, reference_measure, valid = green_strains(points, reference_points, cells)
    m = max(i for i, _ in strain) + 1
    trace = _trace(strain, m)
    root_measure = jnp.sqrt(jnp.where(valid, reference_measure, 1))
    shear, bulk = root_measure * math.sqrt(shear_modulus), root_measure * math.sqrt(bulk_term)
    parts = [shear * (strain[i, i] - trace / m) for i in range(m)]
    parts += [math.sqrt(2) * shear * strain[i, j] for i in range(m) for j in range(i + 1, m)]
    parts.append(bulk * trace)
    return jnp.stack(parts, axis=-1), valid


def _trace(strain: dict, m: int) -> jax.Array:
    trace = strain[0, 0]
    for i in range(1, m):
        trace = trace + strain[i, i]
    return trace


def green_strains(points: jax.Array, reference_points: jax.Array, cells: jax.Array):
    """Per cell, the Green strain in the reference cell's intrinsic frame.

    Returns ``(strain, V_0, valid)``: ``strain[i, j]`` (``i <= j < m``) arrays ``(B, M)`` of
    ``eps = (F^T F - I) / 2`` with ``F = E^T R^{-1}`` (``E_0^T = Q R`` by modified Gram-Schmidt),
    the reference measure ``V_0 = |prod diag R| / m!`` and whether the cell is valid (finite, with
    a non-degenerate reference; an invalid cell's ``R`` is the identity, so nothing non-finite is
    differentiated).
    """
    edges, reference_edges, usable = simplex_edges(points, reference_points, cells)
    m = len(edges)
    _, r = gram_schmidt(reference_edges)
    reference_measure = r[0, 0]
    for k in range(1, m):
        reference_measure = reference_measure * r[k, k]
    reference_measure = reference_measure / math.factorial(m)
    valid = usable & jnp.isfinite(reference_measure)
    for (i, j), value in r.items():
        valid = valid & ((value > 0) if i == j else jnp.isfinite(value))
    r = {(i, j): jnp.where(valid, value, 1 if i == j else 0) for (i, j), value in r.items()}

    # F = E^T R^-1: column k is (e_k - sum_{j<k} r_jk f_j) / r_kk.
    columns: list[jax.Array] = []
    for k, v in enumerate(edges):
        for j in range(k):
            v = v - r[j, k][..., None] * columns[j]
        columns.append(v / r[k, k][..., None])
    cauchy_green = {(i, j): dot(columns[i], columns[j]) for i in range(m) for j in range(i, m)}
    strain = {(i, j): (c - 1) / 2 if i == j else c / 2 for (i, j), c in cauchy_green.items()}
    return strain, reference_measure, valid
