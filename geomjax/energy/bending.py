"""Reference-relative discrete bending energy over triangle hinges."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._errors import raises_documented_errors
from .._points import remove_batch_axis
from ._simplex import (
    Energy,
    Hinges,
    SurfacePoints,
    all_finite,
    check_energy_inputs,
    check_reduction,
    cross,
    dot,
    gather_vertices,
    keep_or,
    reduce_terms,
    require_three_dims,
    row_terms,
    select_energy_backend,
)

__all__ = ["surface_bending_energy"]


@raises_documented_errors
def surface_bending_energy(
    points: SurfacePoints, reference_points: SurfacePoints, hinges: Hinges, *, reduction: str = "sum", implementation: str | None = None
) -> Energy:
    r"""Discrete bending energy of triangle hinges relative to their rest dihedral angles.

    A hinge row ``(i, j, k, l)`` denotes the consistently oriented faces ``(i, j, k)`` and
    ``(j, i, l)`` sharing the edge ``e = x_j - x_i``. With ``n_L = e x (x_k - x_i)`` and
    ``n_R = (-e) x (x_l - x_j)``, the signed dihedral angle is
    ``theta = atan2(e^ . (n^_L x n^_R), n^_L . n^_R)`` (zero for a flat hinge) and each term is::

        (1/2) l_0^2 / (A_{0,L} + A_{0,R}) * wrap(theta - theta_0)^2,

    with ``wrap`` to ``(-pi, pi]`` through ``atan2(sin, cos)`` (a hinge folded through ``+-pi``
    costs a small energy, not ``~2 pi^2``), the rest edge length ``l_0`` and rest face areas
    ``A_0 = |n_0| / 2``. Each hinge's vectors are first divided by their largest magnitude (not
    differentiated), so very large or small coordinates neither overflow nor underflow. This is
    a geometric thin-shell regulariser: no thickness or material constants.

    Args:
        points: current coordinates ``(N, 3)`` or aligned batched ``(B, N, 3)``, float32/float64.
        reference_points: rest coordinates, exactly the shape, dtype and device of ``points``.
        hinges: shared ``(H, 4)`` int32/int64 interior hinges, built once from fixed topology
            (unique triangles, at most two per edge, boundary edges omitted). Values are not
            checked: they must be distinct, in-range indices (see below).
        reduction: ``"none"`` (``(H,)`` or ``(B, H)``), ``"sum"`` or ``"mean"`` (sum over
            ``max(count, 1)``). No hinges give ``0`` for ``"sum"`` and ``"mean"``.
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``. ``None`` picks
            Warp on CPU when warp-lang is installed, else ``"jax"`` (also on GPU, where it is not yet
            measured); ``benchmarks/bench_energy.py`` holds the figures.

    Returns:
        Per-hinge terms or a scalar according to ``reduction``, dtype of ``points``.

    Invalid hinges give NaN terms that pass no gradient back: an out-of-range index, non-finite
    coordinates, a zero-length reference edge or a degenerate (zero-area) reference or current
    triangle; with no points every term is NaN.

    Raises:
        TypeError: non-float coordinates, mismatched dtypes, non-integer ``hinges``.
        ValueError: bad shapes (``hinges`` not ``(H, 4)``, ``D != 3``), an unknown ``reduction``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiable in ``points`` and ``reference_points`` except at the branch cut of the
    wrapped angle; the Warp adjoint is closed-form. See the README's "Backends and transforms"
    for what each backend differentiates and "Sharding" for designs split over devices (the
    Warp kernel runs shard by shard).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import surface_bending_energy
        >>> rest = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, -1.0, 0.0]])
        >>> folded = rest.at[3, 2].set(1.0)  # lift the right wing by 45 degrees
        >>> hinges = jnp.array([[0, 1, 2, 3]])
        >>> energy = surface_bending_energy(folded, rest, hinges, implementation="jax")
        >>> print(np.round(float(energy), 6), np.round(np.pi**2 / 32, 6))
        0.308425 0.308425
    """
    points, reference_points, hinges, batched = check_energy_inputs(points, reference_points, hinges, topology_name="hinges", vertices_per_row=(4,))
    require_three_dims("surface_bending_energy", points)
    check_reduction(reduction)
    backend = select_energy_backend("surface_bending_energy", implementation, points)

    terms = row_terms(points, reference_points, hinges, backend, _warp_bending_terms, bending_terms)
    return reduce_terms(remove_batch_axis(terms, batched), reduction)


def _warp_bending_terms(points, reference_points, hinges):
    from warp_ffi.bending import surface_bending_terms

    return surface_bending_terms(points, reference_points, hinges)


def _hinge_vectors(vertices: list[jax.Array]) -> list[jax.Array]:
    """``(e, a, b) = (x_j - x_i, x_k - x_i, x_l - x_j)``."""
    xi, xj, xk, xl = vertices
    return [xj - xi, xk - xi, xl - xj]


def _scaled(vectors: list[jax.Array]) -> list[jax.Array]:
    """Divide a hinge's vectors by their largest magnitude (not differentiated; one if zero)."""
    scale = jax.lax.stop_gradient(jnp.max(jnp.stack([jnp.max(jnp.abs(v), axis=-1) for v in vectors]), axis=0))
    scale = jnp.where(scale > 0, scale, 1)[..., None]
    return [v / scale for v in vectors]


def _normalized(v: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(v / |v|, |v|^2)``; a zero ``v`` stays zero and differentiates finitely."""
    squared = dot(v, v)
    positive = squared > 0
    norm = jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1)), 1)
    return v / norm[..., None], squared


def _hinge_geometry(vectors: list[jax.Array]):
    """``(e^ . (n^_L x n^_R), n^_L . n^_R, |e|^2, |n_L|^2, |n_R|^2)`` of scaled hinge vectors."""
    e, a, b = vectors
    e_hat, edge_sq = _normalized(e)
    left, left_sq = _normalized(cross(e, a))
    right, right_sq = _normalized(cross(-e, b))
    return dot(e_hat, cross(left, right)), dot(left, right), edge_sq, left_sq, right_sq


@jax.jit
def bending_terms(points: jax.Array, reference_points: jax.Array, hinges: jax.Array) -> jax.Array:
    """Per-hinge energies ``(B, H)`` for ``(B, N, 3)`` points (the JAX specification)."""
    delta, stiffness, valid = _angle_changes(points, reference_points, hinges)
    return jnp.where(valid, stiffness * jnp.square(delta) / 2, jnp.nan)


def bending_residuals(points: jax.Array, reference_points: jax.Array, hinges: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each hinge's term of :func:`surface_bending_energy` as a square: ``(residuals (B, H), valid (B, H))``.

    ``residuals^2`` is the hinge's energy: ``sqrt(l_0^2 / (A_{0,L} + A_{0,R})) wrap(theta -
    theta_0)``, linear in the angle change, as a Gauss-Newton solver needs (the square root of
    the energy is not differentiable at the rest shape). Invalid hinges give 0 and ``valid``
    false.
    """
    delta, stiffness, valid = _angle_changes(points, reference_points, hinges)
    # The stiffness of an invalid hinge may be anything: it is replaced before the square root.
    return jnp.where(valid, jnp.sqrt(jnp.where(valid, stiffness, 2) / 2) * delta, 0), valid


def _angle_changes(points: jax.Array, reference_points: jax.Array, hinges: jax.Array):
    """Per hinge ``(wrap(theta - theta_0), 2 l_0^2 / (|n_{0,L}| + |n_{0,R}|), valid)``, each ``(B, H)``."""
    columns = [hinges[:, k] for k in range(4)]
    current, in_range = gather_vertices(points, columns)
    reference, _ = gather_vertices(reference_points, columns)
    current, reference = _hinge_vectors(current), _hinge_vectors(reference)
    usable = in_range & all_finite(current) & all_finite(reference)
    # A flat unit hinge stands in for unusable ones, so nothing non-finite is differentiated.
    canonical = [jnp.asarray(v, points.dtype) for v in ((1, 0, 0), (0, 1, 0), (0, -1, 0))]
    current = _scaled(keep_or(usable, current, canonical))
    reference = _scaled(keep_or(usable, reference, canonical))

    sin_like, cos_like, _, left_sq, right_sq = _hinge_geometry(current)
    sin0_like, cos0_like, edge0_sq, left0_sq, right0_sq = _hinge_geometry(reference)
    valid = usable & (edge0_sq > 0) & (left0_sq > 0) & (right0_sq > 0) & (left_sq > 0) & (right_sq > 0)

    theta = jnp.arctan2(jnp.where(valid, sin_like, 0), jnp.where(valid, cos_like, 1))
    theta0 = jnp.arctan2(jnp.where(valid, sin0_like, 0), jnp.where(valid, cos0_like, 1))
    delta = theta - theta0
    delta = jnp.arctan2(jnp.sin(delta), jnp.cos(delta))
    # A0_L + A0_R = (|n0_L| + |n0_R|) / 2
    one = jnp.ones((), points.dtype)
    area_sum = jnp.sqrt(jnp.where(valid, left0_sq, one)) + jnp.sqrt(jnp.where(valid, right0_sq, one))
    stiffness = 2 * edge0_sq / area_sum
    return delta, stiffness, valid
