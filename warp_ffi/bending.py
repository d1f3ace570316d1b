"""Discrete hinge bending energy on Warp, with a closed-form adjoint.

Hinge ``(i, j, k, l)``: faces ``(i, j, k)`` and ``(j, i, l)`` share the edge ``e = x_j - x_i``;
with ``a = x_k - x_i`` and ``b = x_l - x_j``, ``n_L = e x a`` and ``n_R = (-e) x b``. The three
vectors are divided by their (non-differentiated) largest magnitude ``s`` first, separately for
the current and the reference hinge; every quantity below is invariant under that scale.

Term ``k0 wrap(theta - theta0)^2 / 2`` with the signed dihedral
``theta = atan2(e^ . (n^_L x n^_R), n^_L . n^_R)``, ``wrap`` to ``(-pi, pi]`` and the reference
stiffness ``k0 = l0^2 / (A0_L + A0_R) = 2 |e0|^2 / (|n0_L| + |n0_R|)``.

Adjoint (positions in scaled units, divided by ``s`` at the end): the classic dihedral gradient
``dtheta/dx_k = -|e| n_L / |n_L|^2``, ``dtheta/dx_l = -|e| n_R / |n_R|^2`` and, with the edge
coordinates ``alpha_k = a.e / |e|^2``, ``alpha_l = (b + e).e / |e|^2`` of the opposite vertices,
``dtheta/dx_i = -(1 - alpha_k) dtheta/dx_k - (1 - alpha_l) dtheta/dx_l`` and
``dtheta/dx_j = -alpha_k dtheta/dx_k - alpha_l dtheta/dx_l``; ``dk0`` follows from
``d|n| = n^ . dn``.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax

from . import _energy
from ._energy import Coordinates, PerItem, Topology, finite3
from ._search import max_abs
from ._wrap import scalars, vectors
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["surface_bending_terms"]


@wp.func
@no_type_check
def _hinge_vectors(points: wp.array(dtype=Any), base: int, i: int, j: int, k: int, l: int):
    """``(e, a, b)`` of a hinge divided by their largest magnitude ``s``, and ``s`` (one if zero)."""
    xi = points[base + i]
    xj = points[base + j]
    e = xj - xi
    a = points[base + k] - xi
    b = points[base + l] - xj
    s = wp.max(wp.max(max_abs(e), max_abs(a)), max_abs(b))
    if not (s > type(s)(0.0)):
        s = type(s)(1.0)
    return e / s, a / s, b / s, s


@wp.func
@no_type_check
def _dihedral(e: Any, n_left: Any, n_right: Any):
    e_hat = e / wp.length(e)
    left = n_left / wp.length(n_left)
    right = n_right / wp.length(n_right)
    return wp.atan2(wp.dot(e_hat, wp.cross(left, right)), wp.dot(left, right))


@wp.func
@no_type_check
def _state(points: wp.array(dtype=Any), reference: wp.array(dtype=Any), hinges: wp.array2d(dtype=wp.int32), b: int, h: int, num_points: int):
    """Scaled hinge vectors and normals (current, reference) and whether the hinge is valid."""
    i = hinges[h, 0]
    j = hinges[h, 1]
    k = hinges[h, 2]
    l = hinges[h, 3]
    in_range = wp.min(wp.min(i, j), wp.min(k, l)) >= 0 and wp.max(wp.max(i, j), wp.max(k, l)) < num_points
    if not in_range:
        i = 0
        j = 0
        k = 0
        l = 0
    base = b * num_points
    e, a, c, s = _hinge_vectors(points, base, i, j, k, l)
    e0, a0, c0, s0 = _hinge_vectors(reference, base, i, j, k, l)
    n_left = wp.cross(e, a)
    n_right = wp.cross(-e, c)
    n0_left = wp.cross(e0, a0)
    n0_right = wp.cross(-e0, c0)
    nil = type(s)(0.0)
    usable = in_range and finite3(e, a, c) and finite3(e0, a0, c0)
    valid = usable and wp.dot(e0, e0) > nil and wp.dot(n0_left, n0_left) > nil and wp.dot(n0_right, n0_right) > nil
    valid = valid and wp.dot(n_left, n_left) > nil and wp.dot(n_right, n_right) > nil
    return valid, i, j, k, l, e, a, c, s, n_left, n_right, e0, a0, c0, s0, n0_left, n0_right


@wp.func
@no_type_check
def _wrapped_difference(theta: Any, theta0: Any):
    delta = theta - theta0
    return wp.atan2(wp.sin(delta), wp.cos(delta))


@wp.func
@no_type_check
def _stiffness(e0: Any, n0_left: Any, n0_right: Any):
    return type(e0[0])(2.0) * wp.dot(e0, e0) / (wp.length(n0_left) + wp.length(n0_right))


@wp.func
@no_type_check
def _dihedral_gradient(e: Any, a: Any, c: Any, n_left: Any, n_right: Any):
    """``dtheta / dx`` for the four hinge vertices, in scaled units."""
    edge_sq = wp.dot(e, e)
    edge = wp.sqrt(edge_sq)
    g_k = -edge / wp.dot(n_left, n_left) * n_left
    g_l = -edge / wp.dot(n_right, n_right) * n_right
    alpha_k = wp.dot(a, e) / edge_sq
    alpha_l = wp.dot(c + e, e) / edge_sq
    one = type(edge)(1.0)
    g_i = -(one - alpha_k) * g_k - (one - alpha_l) * g_l
    g_j = -alpha_k * g_k - alpha_l * g_l
    return g_i, g_j, g_k, g_l


@wp.kernel
@no_type_check
def _forward_kernel(
    points: Coordinates, reference: Coordinates, hinges: Topology, num_points: int, offset: int, energy: PerItem,
):  # fmt: skip
    b, t = wp.tid()
    h = t + offset
    out = b * hinges.shape[0] + h
    valid, i, j, k, l, e, a, c, s, n_left, n_right, e0, a0, c0, s0, n0_left, n0_right = _state(points, reference, hinges, b, h, num_points)
    if not valid:
        energy[out] = energy.dtype(wp.nan)
        return
    delta = _wrapped_difference(_dihedral(e, n_left, n_right), _dihedral(e0, n0_left, n0_right))
    energy[out] = energy.dtype(0.5) * _stiffness(e0, n0_left, n0_right) * delta * delta


@wp.kernel
@no_type_check
def _adjoint_kernel(
    points: Coordinates, reference: Coordinates, hinges: Topology, energy_bar: PerItem, num_points: int, offset: int,
    points_bar: Coordinates, reference_bar: Coordinates,
):  # fmt: skip
    b, t = wp.tid()
    h = t + offset
    valid, i, j, k, l, e, a, c, s, n_left, n_right, e0, a0, c0, s0, n0_left, n0_right = _state(points, reference, hinges, b, h, num_points)
    if not valid:
        return
    g = energy_bar[b * hinges.shape[0] + h]
    stiffness = _stiffness(e0, n0_left, n0_right)
    delta = _wrapped_difference(_dihedral(e, n_left, n_right), _dihedral(e0, n0_left, n0_right))
    g_theta = g * stiffness * delta
    base = b * num_points

    scale = g_theta / s
    g_i, g_j, g_k, g_l = _dihedral_gradient(e, a, c, n_left, n_right)
    wp.atomic_add(points_bar, base + i, scale * g_i)
    wp.atomic_add(points_bar, base + j, scale * g_j)
    wp.atomic_add(points_bar, base + k, scale * g_k)
    wp.atomic_add(points_bar, base + l, scale * g_l)

    # Reference: theta0 enters with the opposite sign, the stiffness through |e0|^2 and the areas.
    scale = -g_theta / s0
    g_i, g_j, g_k, g_l = _dihedral_gradient(e0, a0, c0, n0_left, n0_right)
    left_norm = wp.length(n0_left)
    right_norm = wp.length(n0_right)
    area = left_norm + right_norm
    g_stiffness = g * type(g)(0.5) * delta * delta / s0
    d_area = type(g)(-2.0) * wp.dot(e0, e0) / (area * area)
    left_hat = n0_left / left_norm
    right_hat = n0_right / right_norm
    d_e = type(g)(4.0) / area * e0 + d_area * (wp.cross(a0, left_hat) - wp.cross(c0, right_hat))
    d_a = d_area * wp.cross(left_hat, e0)
    d_c = d_area * wp.cross(e0, right_hat)
    wp.atomic_add(reference_bar, base + i, scale * g_i - g_stiffness * (d_e + d_a))
    wp.atomic_add(reference_bar, base + j, scale * g_j + g_stiffness * (d_e - d_c))
    wp.atomic_add(reference_bar, base + k, scale * g_k + g_stiffness * d_a)
    wp.atomic_add(reference_bar, base + l, scale * g_l + g_stiffness * d_c)


def _types(s):
    return {name: vectors(s) for name in ("points", "reference", *_energy.GRADIENT_NAMES)} | {"energy": scalars(s), "energy_bar": scalars(s)}


_terms = _energy.per_item_terms(
    _energy.energy_family(_forward_kernel, _types, outputs=("energy",)),
    _energy.energy_family(_adjoint_kernel, _types, outputs=_energy.GRADIENT_NAMES, accumulate=_energy.GRADIENT_NAMES),
)


@jax.jit
def surface_bending_terms(points: jax.Array, reference_points: jax.Array, hinges: jax.Array) -> jax.Array:
    """Per-hinge bending energies ``(B, H)`` on ``(B, N, 3)`` points.

    NaN for invalid hinges (out-of-range index, non-finite coordinates, a degenerate reference
    edge or reference/current triangle), which pass no gradient back. Differentiable once in
    reverse mode in both coordinate arrays; ``jit`` and ``vmap`` (sequential) compatible.
    Requires ``B, N, H > 0``.
    """
    num_batch = points.shape[0]
    (energy,) = _terms(*_energy.kernel_inputs(points, reference_points, hinges), (), num_batch, ())
    return energy.reshape(num_batch, -1)
