"""Warp FFD kernels for any lattice: any number of axes, any number of nodes per axis.

The fixed kernels of :mod:`warp_ffi.ffd` hold their per-axis basis tables in registers, sized
for ``D <= 3`` and at most ``MAX_AXIS_NODES`` Bernstein nodes per axis. These kernels compute the
same sums for the other lattices: the tables live in scratch buffers ``(B, N, D * width)`` that
the call allocates (extra FFI outputs, dropped), and one loop runs over the tensor product of
the supporting nodes, each node's lattice row and weight decoded from its flat index (last axis
fastest). A Warp module of its own, imported by :mod:`warp_ffi.ffd` only when a lattice needs
it, so the common kernels' first build does not pay for these.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax
import jax.numpy as jnp

from ._ffd_basis import BASIS_CODES, Batched, PerDesign, axis_basis, kernel_types
from ._wrap import KernelFamily
from ._wrap import warp as wp

__all__ = ["general_field", "general_field_adjoint"]

LOCAL_SUPPORT = 4  # the most nodes a local basis (B-spline, linear, Hermite) supports per axis
_LOCAL_TABLE = wp.constant(LOCAL_SUPPORT)


@wp.func
@no_type_check
def _general_tables(
    points: wp.array3d(dtype=Any), origin: wp.array2d(dtype=Any), extent: wp.array2d(dtype=Any), nodes: wp.array(dtype=wp.int32),
    kind: int, width: int, b: int, q: int, weights: wp.array3d(dtype=Any), slopes: wp.array3d(dtype=Any),
    starts: wp.array3d(dtype=wp.int32), counts: wp.array3d(dtype=wp.int32),
):  # fmt: skip
    """Whether point ``(b, q)`` is inside the box; if so its per-axis basis tables are written to
    ``weights[b, q, d * width + i]``, ``slopes[...]``, ``starts[b, q, d]`` and ``counts[b, q, d]``."""
    num_dims = points.shape[2]
    zero = points.dtype(0.0)
    one = points.dtype(1.0)
    inside = bool(True)
    for d in range(num_dims):
        u = (points[b, q, d] - origin[b, d]) / extent[b, d]
        if not (u >= zero and u <= one):  # NaN fails both: NaN points are outside
            inside = False
    if inside:
        table = wp.vector(length=_LOCAL_TABLE, dtype=points.dtype)
        for d in range(num_dims):
            u = (points[b, q, d] - origin[b, d]) / extent[b, d]
            n = nodes[d]
            base = d * width
            if kind == 0:
                # The fixed kernels' de Casteljau recurrence (see axis_basis), in the scratch rows.
                lower = one - u
                weights[b, q, base] = one
                for k in range(1, n):
                    if k == n - 1:
                        degree = points.dtype(k)
                        slopes[b, q, base] = -degree * weights[b, q, base]
                        for i in range(1, k):
                            slopes[b, q, base + i] = degree * (weights[b, q, base + i - 1] - weights[b, q, base + i])
                        slopes[b, q, base + k] = degree * weights[b, q, base + k - 1]
                    weights[b, q, base + k] = u * weights[b, q, base + k - 1]
                    for r in range(k - 1):
                        i = k - 1 - r
                        weights[b, q, base + i] = lower * weights[b, q, base + i] + u * weights[b, q, base + i - 1]
                    weights[b, q, base] = lower * weights[b, q, base]
                starts[b, q, d] = 0
                counts[b, q, d] = n
            else:
                w, dw, s, c = axis_basis(kind, n, u, table)  # a local basis: its support fits the table
                for i in range(c):
                    weights[b, q, base + i] = w[i]
                    slopes[b, q, base + i] = dw[i]
                starts[b, q, d] = s
                counts[b, q, d] = c
    return inside


@wp.func
@no_type_check
def _supported_nodes(counts: wp.array3d(dtype=wp.int32), b: int, q: int):
    """The number of lattice nodes supporting point ``(b, q)``: the product of its axis counts."""
    total = int(1)
    for d in range(counts.shape[2]):
        total *= counts[b, q, d]
    return total


@wp.func
@no_type_check
def _node_row(
    t: int, nodes: wp.array(dtype=wp.int32), starts: wp.array3d(dtype=wp.int32), counts: wp.array3d(dtype=wp.int32), b: int, q: int
):  # fmt: skip
    """The lattice row of the ``t``-th supporting node of point ``(b, q)`` (last axis fastest)."""
    rest = int(t)
    row = int(0)
    stride = int(1)
    num_dims = counts.shape[2]
    for r in range(num_dims):
        d = num_dims - 1 - r
        j = rest % counts[b, q, d]
        rest = rest // counts[b, q, d]
        row += (starts[b, q, d] + j) * stride
        stride *= nodes[d]
    return row


@wp.func
@no_type_check
def _node_weight(
    t: int, derivative_axis: int, weights: wp.array3d(dtype=Any), slopes: wp.array3d(dtype=Any), counts: wp.array3d(dtype=wp.int32),
    width: int, b: int, q: int,
):  # fmt: skip
    """The tensor-product weight of the ``t``-th supporting node of point ``(b, q)``, with the
    derivative's table on ``derivative_axis`` (``-1``: the weight itself)."""
    rest = int(t)
    weight = weights.dtype(1.0)
    num_dims = counts.shape[2]
    for r in range(num_dims):
        d = num_dims - 1 - r
        j = rest % counts[b, q, d]
        rest = rest // counts[b, q, d]
        if d == derivative_axis:
            weight *= slopes[b, q, d * width + j]
        else:
            weight *= weights[b, q, d * width + j]
    return weight


@wp.kernel
@no_type_check
def _ffd_general_kernel(
    points: Batched, values: Batched, origin: PerDesign, extent: PerDesign, nodes: wp.array(dtype=wp.int32), kind: int, width: int,
    transpose: int, out: Batched, weights: Batched, slopes: Batched, starts: wp.array3d(dtype=wp.int32),
    counts: wp.array3d(dtype=wp.int32),
):  # fmt: skip
    """``_ffd_kernel`` for any dimension and node count (``out`` first among the outputs: the
    FFI takes the transpose's in/out buffer before the scratch outputs)."""
    b, q = wp.tid()
    num_dims = points.shape[2]
    inside = _general_tables(points, origin, extent, nodes, kind, width, b, q, weights, slopes, starts, counts)
    if transpose == 0:
        for d in range(num_dims):
            out[b, q, d] = points.dtype(0.0)
    if inside:
        for t in range(_supported_nodes(counts, b, q)):
            row = _node_row(t, nodes, starts, counts, b, q)
            w = _node_weight(t, -1, weights, slopes, counts, width, b, q)
            for d in range(num_dims):
                if transpose == 0:
                    out[b, q, d] = out[b, q, d] + w * values[b, row, d]
                else:
                    wp.atomic_add(out, b, row, d, w * values[b, q, d])


@wp.kernel
@no_type_check
def _ffd_general_point_adjoint_kernel(
    points: Batched, lattice: Batched, origin: PerDesign, extent: PerDesign, field_adj: Batched, nodes: wp.array(dtype=wp.int32),
    kind: int, width: int, points_adj: Batched, weights: Batched, slopes: Batched, starts: wp.array3d(dtype=wp.int32),
    counts: wp.array3d(dtype=wp.int32),
):  # fmt: skip
    """``_ffd_point_adjoint_kernel`` for any dimension and node count."""
    b, q = wp.tid()
    num_dims = points.shape[2]
    inside = _general_tables(points, origin, extent, nodes, kind, width, b, q, weights, slopes, starts, counts)
    for d in range(num_dims):
        points_adj[b, q, d] = points.dtype(0.0)
    if inside:
        for t in range(_supported_nodes(counts, b, q)):
            row = _node_row(t, nodes, starts, counts, b, q)
            value = points.dtype(0.0)  # cotangent . lattice value at this node
            for d in range(num_dims):
                value += field_adj[b, q, d] * lattice[b, row, d]
            for e in range(num_dims):
                points_adj[b, q, e] = points_adj[b, q, e] + value * _node_weight(t, e, weights, slopes, counts, width, b, q)
    for d in range(num_dims):
        points_adj[b, q, d] = points_adj[b, q, d] / extent[b, d]


_SCRATCH = ("weights", "slopes", "starts", "counts")
_general_map = KernelFamily(_ffd_general_kernel, kernel_types, outputs=("out", *_SCRATCH))
_general_map_transpose = KernelFamily(_ffd_general_kernel, kernel_types, outputs=("out", *_SCRATCH), accumulate=("out",))
_general_point_adjoint = KernelFamily(_ffd_general_point_adjoint_kernel, kernel_types, outputs=("points_adj", *_SCRATCH))


def _general_static(lattice_shape: tuple[int, ...], basis: str) -> tuple:
    """The general kernels' ``(nodes, kind, width)``: the nodes per axis (an int32 array), the
    basis code and the scratch table width per axis."""
    resolution = lattice_shape[1:-1]
    width = max(resolution) if basis == "bernstein" else LOCAL_SUPPORT
    return jnp.asarray(resolution, jnp.int32), BASIS_CODES[basis], width


def _scratch_shapes(points_shape: tuple[int, ...], width: int) -> dict:
    num_batch, num_points, num_dims = points_shape
    tables, indices = (num_batch, num_points, num_dims * width), (num_batch, num_points, num_dims)
    return {"weights": tables, "slopes": tables, "starts": indices, "counts": indices}


def general_field(points: jax.Array, lattice: jax.Array, origin: jax.Array, extent: jax.Array, lattice_shape: tuple, basis: str) -> jax.Array:
    """The field ``(B, N, D)`` of a flattened lattice ``(B, nodes, D)`` of shape ``lattice_shape``."""
    nodes, kind, width = _general_static(lattice_shape, basis)
    shapes = {**_scratch_shapes(points.shape, width), "out": points.shape}
    field, *_ = _general_map(points.dtype)(points, lattice, origin, extent, nodes, kind, width, 0, launch=points.shape[:2], shapes=shapes)
    return field


def general_field_adjoint(points, lattice, origin, extent, field_adj, lattice_shape: tuple, basis: str) -> tuple[jax.Array, jax.Array]:
    """``(points_adj (B, N, D), lattice_adj (B, nodes, D))`` for the field's cotangent ``field_adj``."""
    nodes, kind, width = _general_static(lattice_shape, basis)
    scratch, launch = _scratch_shapes(points.shape, width), points.shape[:2]
    transpose = _general_map_transpose(points.dtype)
    lattice_adj, *_ = transpose(points, field_adj, origin, extent, nodes, kind, width, 1, launch=launch, shapes={**scratch, "out": lattice.shape})
    adjoint = _general_point_adjoint(points.dtype)
    points_adj, *_ = adjoint(points, lattice, origin, extent, field_adj, nodes, kind, width, launch=launch, shapes={**scratch, "points_adj": points.shape})
    return points_adj, lattice_adj
