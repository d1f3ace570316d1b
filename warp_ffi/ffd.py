"""Warp kernels for lattice free-form deformation, exposed to JAX through ``jax.custom_vjp``.

Inputs arrive validated and normalised: points ``(B, N, D)`` with ``D <= 3``, lattices
``(B, n_1, ..., n_D, D)``, box vectors ``(B, D)`` (gradients already stopped). One thread per
point builds per-axis basis tables (weights and their derivatives for at most
``MAX_AXIS_NODES`` supporting nodes per axis), then loops over the tensor product of the
supporting nodes. Missing axes (``D < 3``) are padded with one node of weight one.

Kernels: a forward kernel writing the field (zero outside the box), a lattice adjoint that
scatters ``w * g`` into a zeroed buffer with atomics, and a point adjoint written per point.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import warp as wp

from ._kernels import KernelFamily

__all__ = ["free_form_deform_field", "MAX_AXIS_NODES", "BASIS_CODES"]

# Size of the per-thread basis tables: bounds the Bernstein nodes per axis (local bases use 2 or 4).
MAX_AXIS_NODES = 32
BASIS_CODES = {"bernstein": 0, "bspline": 1, "linear": 2, "cubic_hermite": 3, "quintic_hermite": 4}
_TABLE = wp.constant(MAX_AXIS_NODES)


@wp.func
def _axis_basis(kind: int, n: int, u: Any, table: Any):
    """Supporting nodes on one axis at local coordinate ``u`` in ``[0, 1]``.

    Returns ``(weights, d weights / du, first node, node count)``.
    """
    one = type(u)(1.0)
    weight = table
    slope = table
    start = int(0)
    count = int(0)
    if kind == 0:
        # Bernstein of degree n - 1 by the de Casteljau recurrence; the derivative comes from the
        # degree n - 2 basis: dB^p_i = p (B^{p-1}_{i-1} - B^{p-1}_i).
        lower = one - u
        weight[0] = one
        for k in range(1, n):
            if k == n - 1:
                degree = type(u)(float(k))
                slope[0] = -degree * weight[0]
                for i in range(1, k):
                    slope[i] = degree * (weight[i - 1] - weight[i])
                slope[k] = degree * weight[k - 1]
            weight[k] = u * weight[k - 1]
            for r in range(k - 1):
                i = k - 1 - r
                weight[i] = lower * weight[i] + u * weight[i - 1]
            weight[0] = lower * weight[0]
        count = n
    else:
        spans = n - 1
        if kind == 1:
            spans = n - 3
        scale = type(u)(float(spans))
        s = u * scale
        cell = wp.clamp(int(wp.floor(s)), 0, spans - 1)
        start = cell
        t = s - type(u)(float(cell))
        if kind == 1:
            # uniform cubic B-spline
            sixth = one / type(u)(6.0)
            v = one - t
            weight[0] = v * v * v * sixth
            weight[1] = (type(u)(3.0) * t * t * t - type(u)(6.0) * t * t + type(u)(4.0)) * sixth
            weight[2] = (type(u)(-3.0) * t * t * t + type(u)(3.0) * t * t + type(u)(3.0) * t + one) * sixth
            weight[3] = t * t * t * sixth
            half = type(u)(0.5)
            slope[0] = -half * v * v * scale
            slope[1] = (type(u)(1.5) * t * t - type(u)(2.0) * t) * scale
            slope[2] = (type(u)(-1.5) * t * t + t + half) * scale
            slope[3] = half * t * t * scale
            count = 4
        else:
            upper = t
            upper_slope = one
            if kind == 3:
                upper = t * t * (type(u)(3.0) - type(u)(2.0) * t)
                upper_slope = type(u)(6.0) * t * (one - t)
            elif kind == 4:
                upper = t * t * t * (t * (t * type(u)(6.0) - type(u)(15.0)) + type(u)(10.0))
                upper_slope = type(u)(30.0) * t * t * (t - one) * (t - one)
            weight[0] = one - upper
            weight[1] = upper
            slope[0] = -upper_slope * scale
            slope[1] = upper_slope * scale
            count = 2
    return weight, slope, start, count


@wp.func
def _point_tables(
    points: wp.array3d(dtype=Any),
    origin: wp.array2d(dtype=Any),
    extent: wp.array2d(dtype=Any),
    kind: int,
    n0: int,
    n1: int,
    n2: int,
    b: int,
    q: int,
):
    """Whether point ``(b, q)`` is inside the box, and its per-axis basis tables."""
    num_dims = points.shape[2]
    zero = points.dtype(0.0)
    one = points.dtype(1.0)
    weights = wp.matrix(shape=(3, _TABLE), dtype=points.dtype)
    slopes = wp.matrix(shape=(3, _TABLE), dtype=points.dtype)
    start = wp.vec3i(0, 0, 0)
    count = wp.vec3i(1, 1, 1)
    weights[0, 0] = one
    weights[1, 0] = one
    weights[2, 0] = one
    inside = bool(True)
    for d in range(num_dims):
        u = (points[b, q, d] - origin[b, d]) / extent[b, d]
        # NaN fails both comparisons, so NaN points are outside.
        if not (u >= zero and u <= one):
            inside = False
    if inside:
        table = wp.vector(length=_TABLE, dtype=points.dtype)
        for d in range(num_dims):
            u = (points[b, q, d] - origin[b, d]) / extent[b, d]
            n = n0
            if d == 1:
                n = n1
            elif d == 2:
                n = n2
            w, dw, s, c = _axis_basis(kind, n, u, table)
            for i in range(c):
                weights[d, i] = w[i]
                slopes[d, i] = dw[i]
            start[d] = s
            count[d] = c
    return inside, weights, slopes, start, count


@wp.kernel
def _ffd_forward_kernel(
    points: wp.array3d(dtype=Any),
    lattice: wp.array3d(dtype=Any),
    origin: wp.array2d(dtype=Any),
    extent: wp.array2d(dtype=Any),
    kind: int,
    n0: int,
    n1: int,
    n2: int,
    field: wp.array3d(dtype=Any),
):
    b, q = wp.tid()
    num_dims = points.shape[2]
    inside, weights, slopes, start, count = _point_tables(points, origin, extent, kind, n0, n1, n2, b, q)
    a0 = points.dtype(0.0)
    a1 = points.dtype(0.0)
    a2 = points.dtype(0.0)
    if inside:
        for j0 in range(count[0]):
            w0 = weights[0, j0]
            for j1 in range(count[1]):
                w01 = w0 * weights[1, j1]
                row = ((start[0] + j0) * n1 + start[1] + j1) * n2 + start[2]
                for j2 in range(count[2]):
                    w = w01 * weights[2, j2]
                    node = row + j2
                    a0 += w * lattice[b, node, 0]
                    if num_dims > 1:
                        a1 += w * lattice[b, node, 1]
                    if num_dims > 2:
                        a2 += w * lattice[b, node, 2]
    field[b, q, 0] = a0
    if num_dims > 1:
        field[b, q, 1] = a1
    if num_dims > 2:
        field[b, q, 2] = a2


@wp.kernel
def _ffd_lattice_adjoint_kernel(
    points: wp.array3d(dtype=Any),
    origin: wp.array2d(dtype=Any),
    extent: wp.array2d(dtype=Any),
    field_adj: wp.array3d(dtype=Any),
    kind: int,
    n0: int,
    n1: int,
    n2: int,
    lattice_adj: wp.array3d(dtype=Any),
):
    b, q = wp.tid()
    num_dims = points.shape[2]
    inside, weights, slopes, start, count = _point_tables(points, origin, extent, kind, n0, n1, n2, b, q)
    if inside:
        g0 = field_adj[b, q, 0]
        g1 = points.dtype(0.0)
        g2 = points.dtype(0.0)
        if num_dims > 1:
            g1 = field_adj[b, q, 1]
        if num_dims > 2:
            g2 = field_adj[b, q, 2]
        for j0 in range(count[0]):
            w0 = weights[0, j0]
            for j1 in range(count[1]):
                w01 = w0 * weights[1, j1]
                row = ((start[0] + j0) * n1 + start[1] + j1) * n2 + start[2]
                for j2 in range(count[2]):
                    w = w01 * weights[2, j2]
                    node = row + j2
                    wp.atomic_add(lattice_adj, b, node, 0, w * g0)
                    if num_dims > 1:
                        wp.atomic_add(lattice_adj, b, node, 1, w * g1)
                    if num_dims > 2:
                        wp.atomic_add(lattice_adj, b, node, 2, w * g2)


@wp.kernel
def _ffd_point_adjoint_kernel(
    points: wp.array3d(dtype=Any),
    lattice: wp.array3d(dtype=Any),
    origin: wp.array2d(dtype=Any),
    extent: wp.array2d(dtype=Any),
    field_adj: wp.array3d(dtype=Any),
    kind: int,
    n0: int,
    n1: int,
    n2: int,
    points_adj: wp.array3d(dtype=Any),
):
    b, q = wp.tid()
    num_dims = points.shape[2]
    inside, weights, slopes, start, count = _point_tables(points, origin, extent, kind, n0, n1, n2, b, q)
    s0 = points.dtype(0.0)
    s1 = points.dtype(0.0)
    s2 = points.dtype(0.0)
    if inside:
        g0 = field_adj[b, q, 0]
        g1 = points.dtype(0.0)
        g2 = points.dtype(0.0)
        if num_dims > 1:
            g1 = field_adj[b, q, 1]
        if num_dims > 2:
            g2 = field_adj[b, q, 2]
        for j0 in range(count[0]):
            w0 = weights[0, j0]
            dw0 = slopes[0, j0]
            for j1 in range(count[1]):
                w1 = weights[1, j1]
                dw1 = slopes[1, j1]
                row = ((start[0] + j0) * n1 + start[1] + j1) * n2 + start[2]
                for j2 in range(count[2]):
                    w2 = weights[2, j2]
                    node = row + j2
                    # cotangent . lattice value at this node
                    value = g0 * lattice[b, node, 0]
                    if num_dims > 1:
                        value += g1 * lattice[b, node, 1]
                    if num_dims > 2:
                        value += g2 * lattice[b, node, 2]
                    s0 += dw0 * w1 * w2 * value
                    s1 += w0 * dw1 * w2 * value
                    s2 += w0 * w1 * slopes[2, j2] * value
    points_adj[b, q, 0] = s0 / extent[b, 0]
    if num_dims > 1:
        points_adj[b, q, 1] = s1 / extent[b, 1]
    if num_dims > 2:
        points_adj[b, q, 2] = s2 / extent[b, 2]


def _array_types(T, **ndims):
    return {name: wp.array(dtype=T, ndim=ndim) for name, ndim in ndims.items()}


_SCALARS = {"kind": wp.int32, "n0": wp.int32, "n1": wp.int32, "n2": wp.int32}

_forward = KernelFamily(
    _ffd_forward_kernel,
    lambda T: {**_array_types(T, points=3, lattice=3, origin=2, extent=2, field=3), **_SCALARS},
)
_lattice_adjoint = KernelFamily(
    _ffd_lattice_adjoint_kernel,
    lambda T: {**_array_types(T, points=3, origin=2, extent=2, field_adj=3, lattice_adj=3), **_SCALARS},
    in_out_argnames=["lattice_adj"],
)
_point_adjoint = KernelFamily(
    _ffd_point_adjoint_kernel,
    lambda T: {**_array_types(T, points=3, lattice=3, origin=2, extent=2, field_adj=3, points_adj=3), **_SCALARS},
)


def _static(lattice_shape: tuple[int, ...], basis: str) -> tuple[int, int, int, int]:
    """Static kernel scalars ``(kind, n0, n1, n2)``; missing axes have one node."""
    resolution = tuple(lattice_shape[1:-1]) + (1,) * (4 - len(lattice_shape[1:]))
    return (BASIS_CODES[basis],) + resolution


def _flat(lattice: jax.Array) -> jax.Array:
    return lattice.reshape(lattice.shape[0], -1, lattice.shape[-1])


@functools.partial(jax.custom_vjp, nondiff_argnums=(4,))
def _field(points, lattice, origin, extent, basis):
    return _field_forward(points, lattice, origin, extent, basis)


def _field_forward(points, lattice, origin, extent, basis):
    num_batch, num_points, num_dims = points.shape
    if num_batch * num_points == 0:
        return jnp.zeros_like(points)
    (field,) = _forward(points.dtype)(
        points,
        _flat(lattice),
        origin,
        extent,
        *_static(lattice.shape, basis),
        launch_dims=(num_batch, num_points),
        output_dims={"field": (num_batch, num_points, num_dims)},
    )
    return field


def _field_fwd(points, lattice, origin, extent, basis):
    return _field_forward(points, lattice, origin, extent, basis), (points, lattice, origin, extent)


def _field_bwd(basis, residuals, field_adj):
    points, lattice, origin, extent = residuals
    num_batch, num_points, num_dims = points.shape
    if num_batch * num_points == 0:
        return jnp.zeros_like(points), jnp.zeros_like(lattice), jnp.zeros_like(origin), jnp.zeros_like(extent)
    static = _static(lattice.shape, basis)
    flat = _flat(lattice)
    (lattice_adj,) = _lattice_adjoint(points.dtype)(
        points,
        origin,
        extent,
        field_adj,
        *static,
        jnp.zeros_like(flat),
        launch_dims=(num_batch, num_points),
    )
    (points_adj,) = _point_adjoint(points.dtype)(
        points,
        flat,
        origin,
        extent,
        field_adj,
        *static,
        launch_dims=(num_batch, num_points),
        output_dims={"points_adj": (num_batch, num_points, num_dims)},
    )
    # origin and extent are configuration (stopped upstream): zero cotangents.
    return points_adj, lattice_adj.reshape(lattice.shape), jnp.zeros_like(origin), jnp.zeros_like(extent)


_field.defvjp(_field_fwd, _field_bwd)


def free_form_deform_field(
    points: jax.Array, lattice: jax.Array, origin: jax.Array, extent: jax.Array, *, basis: str
) -> jax.Array:
    """FFD displacement field ``(B, N, D)``: zero outside the box ``[origin, origin + extent]``.

    Args:
        points: ``(B, N, D)``, float32 or float64, ``1 <= D <= 3``.
        lattice: ``(B, n_1, ..., n_D, D)`` control displacements, same dtype.
        origin, extent: ``(B, D)`` box corners and edge lengths (not differentiated).
        basis: a key of ``BASIS_CODES``; Bernstein needs ``n_d <= MAX_AXIS_NODES``.

    Differentiable once in reverse mode (``jax.custom_vjp``) in ``points`` and ``lattice``;
    ``jit`` and ``vmap`` (sequential) compatible.
    """
    return _field(points, lattice, origin, extent, basis)

# Register every overload now so the module is built (and cached) once with one hash, instead of
# being rebuilt each time a new dtype or kernel is first used.
for _family in (_forward, _lattice_adjoint, _point_adjoint):
    for _dtype in (jnp.float32, jnp.float64):
        _family(_dtype)
del _family, _dtype
