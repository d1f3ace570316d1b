"""Warp kernels for lattice free-form deformation, exposed to JAX through ``jax.custom_vjp``.

Inputs arrive validated and normalised: points ``(B, N, D)``, lattices ``(B, n_1, ..., n_D, D)``,
box vectors ``(B, D)`` (gradients already stopped). One thread per point.

Two kernel sets compute the same sums:

* the *fixed* kernels (``D <= 3``, at most ``MAX_AXIS_NODES`` Bernstein nodes per axis, which is
  every common lattice): per-axis basis tables (weights and their derivatives) in registers,
  then nested loops over the tensor product of the supporting nodes; missing axes are padded
  with one node of weight one;
* the *general* kernels (any ``D``, any node count), in ``_ffd_general.py``: a Warp module of
  their own, built only when a lattice needs them, so the common kernels' first build stays
  small.

Kernels: the lattice map (the field, zero outside the box) and its transpose in one kernel (the
lattice adjoint, which scatters ``w * g`` into a zeroed buffer with atomics), and a point
adjoint written per point.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax
import jax.numpy as jnp

from ._ffd_basis import BASIS_CODES, Batched, PerDesign, axis_basis, kernel_types
from ._wrap import KernelFamily, with_adjoint
from ._wrap import warp as wp

__all__ = ["free_form_deform_field", "MAX_AXIS_NODES", "MAX_FIXED_DIMS", "BASIS_CODES"]

# Size of the per-thread basis tables: bounds the Bernstein nodes per axis (local bases use 2 or 4).
MAX_AXIS_NODES = 32
MAX_FIXED_DIMS = 3  # the fixed kernels' axes; more take the general kernels (_ffd_general.py)
_TABLE = wp.constant(MAX_AXIS_NODES)


@wp.func
@no_type_check
def _point_tables(
    points: wp.array3d(dtype=Any), origin: wp.array2d(dtype=Any), extent: wp.array2d(dtype=Any), kind: int, n0: int, n1: int,
    n2: int, b: int, q: int,
):  # fmt: skip
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
            w, dw, s, c = axis_basis(kind, n, u, table)
            for i in range(c):
                weights[d, i] = w[i]
                slopes[d, i] = dw[i]
            start[d] = s
            count[d] = c
    return inside, weights, slopes, start, count


@wp.func
@no_type_check
def _row_vector(values: wp.array3d(dtype=Any), b: int, i: int, num_dims: int):
    """Row ``values[b, i]`` as a 3-vector (missing components zero)."""
    v = wp.vector(length=3, dtype=values.dtype)
    for d in range(num_dims):
        v[d] = values[b, i, d]
    return v


@wp.kernel
@no_type_check
def _ffd_kernel(
    points: Batched, values: Batched, origin: PerDesign, extent: PerDesign, kind: int, n0: int, n1: int, n2: int, transpose: int,
    out: Batched,
):  # fmt: skip
    """The lattice map at point ``(b, q)`` and its transpose, which the lattice adjoint is.

    ``transpose == 0``: ``out[b, q] = sum_node w_node values[b, node]`` (the field from the
    lattice; zero outside the box). ``transpose == 1``: ``out[b, node] += w_node values[b, q]``
    (the lattice cotangent from the field's, scattered with atomics into a zeroed buffer).
    """
    b, q = wp.tid()
    num_dims = points.shape[2]
    inside, weights, slopes, start, count = _point_tables(points, origin, extent, kind, n0, n1, n2, b, q)
    field = wp.vector(length=3, dtype=points.dtype)
    g = wp.vector(length=3, dtype=points.dtype)
    if inside and transpose != 0:
        g = _row_vector(values, b, q, num_dims)
    if inside:
        for j0 in range(count[0]):
            w0 = weights[0, j0]
            for j1 in range(count[1]):
                w01 = w0 * weights[1, j1]
                row = ((start[0] + j0) * n1 + start[1] + j1) * n2 + start[2]
                for j2 in range(count[2]):
                    w = w01 * weights[2, j2]
                    if transpose == 0:
                        field += w * _row_vector(values, b, row + j2, num_dims)
                    else:
                        for d in range(num_dims):
                            wp.atomic_add(out, b, row + j2, d, w * g[d])
    if transpose == 0:
        for d in range(num_dims):
            out[b, q, d] = field[d]


@wp.kernel
@no_type_check
def _ffd_point_adjoint_kernel(
    points: Batched, lattice: Batched, origin: PerDesign, extent: PerDesign, field_adj: Batched, kind: int, n0: int, n1: int,
    n2: int, points_adj: Batched,
):  # fmt: skip
    b, q = wp.tid()
    num_dims = points.shape[2]
    inside, weights, slopes, start, count = _point_tables(points, origin, extent, kind, n0, n1, n2, b, q)
    gradient = wp.vector(length=3, dtype=points.dtype)
    if inside:
        g = _row_vector(field_adj, b, q, num_dims)
        for j0 in range(count[0]):
            w0 = weights[0, j0]
            dw0 = slopes[0, j0]
            for j1 in range(count[1]):
                w1 = weights[1, j1]
                dw1 = slopes[1, j1]
                row = ((start[0] + j0) * n1 + start[1] + j1) * n2 + start[2]
                for j2 in range(count[2]):
                    w2 = weights[2, j2]
                    # cotangent . lattice value at this node
                    value = wp.dot(g, _row_vector(lattice, b, row + j2, num_dims))
                    gradient += value * wp.vector(dw0 * w1 * w2, w0 * dw1 * w2, w0 * w1 * slopes[2, j2])
    for d in range(num_dims):
        points_adj[b, q, d] = gradient[d] / extent[b, d]


# Every overload is registered now, so the module is built (and cached) once.
_lattice_map = KernelFamily(_ffd_kernel, kernel_types, outputs=("out",))
_lattice_map_transpose = KernelFamily(_ffd_kernel, kernel_types, outputs=("out",), accumulate=("out",))
_point_adjoint = KernelFamily(_ffd_point_adjoint_kernel, kernel_types, outputs=("points_adj",))


def _needs_general(lattice_shape: tuple[int, ...], basis: str) -> bool:
    """Whether the fixed kernels cannot take this lattice (more than 3 axes, or more Bernstein
    nodes on an axis than their tables hold)."""
    resolution = lattice_shape[1:-1]
    return len(resolution) > MAX_FIXED_DIMS or (basis == "bernstein" and max(resolution) > MAX_AXIS_NODES)


def _static(lattice_shape: tuple[int, ...], basis: str) -> tuple[int, int, int, int]:
    """Static kernel scalars ``(kind, n0, n1, n2)``; missing axes have one node."""
    n0, n1, n2 = tuple(lattice_shape[1:-1]) + (1,) * (4 - len(lattice_shape[1:]))
    return BASIS_CODES[basis], n0, n1, n2


def _flat(lattice: jax.Array) -> jax.Array:
    return lattice.reshape(lattice.shape[0], -1, lattice.shape[-1])


def _field_forward(points, lattice, origin, extent, basis):
    num_batch, num_points = points.shape[:2]
    if num_batch * num_points == 0:
        return jnp.zeros_like(points), ()
    launch = (num_batch, num_points)
    if _needs_general(lattice.shape, basis):
        from ._ffd_general import general_field

        return general_field(points, _flat(lattice), origin, extent, lattice.shape, basis), ()
    static = _static(lattice.shape, basis)
    (field,) = _lattice_map(points.dtype)(points, _flat(lattice), origin, extent, *static, 0, launch=launch, shapes={"out": points.shape})
    return field, ()


def _field_adjoint(args, saved, field_adj):
    points, lattice, origin, extent, basis = args
    num_batch, num_points = points.shape[:2]
    if num_batch * num_points == 0:
        return jnp.zeros_like(points), jnp.zeros_like(lattice)
    flat, launch = _flat(lattice), (num_batch, num_points)
    if _needs_general(lattice.shape, basis):
        from ._ffd_general import general_field_adjoint

        points_adj, lattice_adj = general_field_adjoint(points, flat, origin, extent, field_adj, lattice.shape, basis)
        return points_adj, lattice_adj.reshape(lattice.shape)
    static = _static(lattice.shape, basis)
    (lattice_adj,) = _lattice_map_transpose(points.dtype)(points, field_adj, origin, extent, *static, 1, launch=launch, shapes={"out": flat.shape})
    (points_adj,) = _point_adjoint(points.dtype)(points, flat, origin, extent, field_adj, *static, launch=launch, shapes={"points_adj": points.shape})
    return points_adj, lattice_adj.reshape(lattice.shape)


# origin and extent are configuration (stopped upstream): zero cotangents.
_field = with_adjoint(_field_forward, _field_adjoint, static_argnums=(4,), constant_argnums=(2, 3))


def free_form_deform_field(points: jax.Array, lattice: jax.Array, origin: jax.Array, extent: jax.Array, *, basis: str) -> jax.Array:
    """FFD displacement field ``(B, N, D)``: zero outside the box ``[origin, origin + extent]``.

    Args:
        points: ``(B, N, D)``, float32 or float64, ``D >= 1``.
        lattice: ``(B, n_1, ..., n_D, D)`` control displacements, same dtype.
        origin, extent: ``(B, D)`` box corners and edge lengths (not differentiated).
        basis: a key of ``BASIS_CODES``. ``D > 3`` or more than ``MAX_AXIS_NODES`` Bernstein
            nodes on an axis take the general kernels (``_ffd_general.py``), which also
            allocate ``2 B N D max(n_d)`` scratch values (``4`` instead of ``max(n_d)`` for a
            local basis).

    Differentiable once in reverse mode (``jax.custom_vjp``) in ``points`` and ``lattice``;
    ``jit`` and ``vmap`` (sequential) compatible.
    """
    return _field(points, lattice, origin, extent, basis)
