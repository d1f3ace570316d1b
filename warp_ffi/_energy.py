"""Warp functions shared by the energy kernels: cell loading, Gram-Schmidt, gradient scatter.

Conventions of every energy kernel (``measure``, ``strain``, ``bending``, ``volume``):

* Coordinates arrive flattened over the batch, ``(B*N,)`` arrays of 3-vectors (``D < 3`` is
  zero-padded by the caller), so ``points[b * num_points + i]`` is vertex ``i`` of design ``b``.
* Topology is ``(M, K)`` int32. int64 indices outside ``[0, N)`` are mapped to ``-1`` before
  narrowing (they could otherwise wrap into range); the kernels check every index against
  ``[0, N)`` before reading, so no kernel ever reads out of bounds.
* Launches are ``(B, items)`` with a trailing ``offset`` input added to the item index, so a CPU
  launch is split over the cores (chunked, balanced kernel families); adjoint kernels accumulate
  into per-thread buffers with plain ``atomic_add``.
* A primitive with an out-of-range index, non-finite coordinates or degenerate reference geometry
  is invalid: the forward kernel writes NaN and the adjoint kernel skips it (no gradient), the
  same rule as the JAX implementation in ``geomjax.energy``.

The functions below follow the JAX code step by step (same sort, same consecutive edges, same
Gram-Schmidt order; products with reciprocals where JAX divides), so both backends agree to
rounding.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax
import jax.numpy as jnp

from ._wrap import KernelFamily, with_adjoint
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

_NO_VERTEX = wp.constant(2147483647)  # sorts after every real index

# The energy kernels' argument types (float types resolved per overload).
Coordinates: Any = wp.array(dtype=Any)  # (B*N,) 3-vectors: points, reference points, their cotangents
PerItem: Any = wp.array(dtype=Any)  # (B*M,) one value per primitive (cell, face, hinge) and design
Topology: Any = wp.array2d(dtype=wp.int32)  # (M, K) vertex indices


@wp.func
@no_type_check
def _ordered(a: wp.int32, b: wp.int32):
    return wp.min(a, b), wp.max(a, b)


@wp.func
@no_type_check
def sorted_cell(cells: wp.array2d(dtype=wp.int32), c: int, num_points: int):
    """Vertex indices of cell ``c`` sorted ascending (missing slots last) and whether all are in range."""
    num_vertices = cells.shape[1]
    i0 = cells[c, 0]
    i1 = cells[c, 1]
    i2 = wp.int32(_NO_VERTEX)
    i3 = wp.int32(_NO_VERTEX)
    if num_vertices > 2:
        i2 = cells[c, 2]
    if num_vertices > 3:
        i3 = cells[c, 3]
    i0, i1 = _ordered(i0, i1)
    i2, i3 = _ordered(i2, i3)
    i0, i2 = _ordered(i0, i2)
    i1, i3 = _ordered(i1, i3)
    i1, i2 = _ordered(i1, i2)
    v = wp.vec4i(i0, i1, i2, i3)
    return v, i0 >= 0 and v[num_vertices - 1] < num_points


@wp.func
@no_type_check
def cell_edges(points: wp.array(dtype=Any), base: int, v: wp.vec4i, m: int):
    """Consecutive edges ``x_{k+1} - x_k`` of a sorted cell (unused edges are zero)."""
    x0 = points[base + v[0]]
    x1 = points[base + v[1]]
    e0 = x1 - x0
    e1 = x0 - x0
    e2 = x0 - x0
    if m > 1:
        x2 = points[base + v[2]]
        e1 = x2 - x1
        if m > 2:
            e2 = points[base + v[3]] - x2
    return e0, e1, e2


@wp.func
@no_type_check
def finite(x: Any):
    """``wp.isfinite`` for a scalar: ``x * 0`` is zero for finite ``x`` and NaN otherwise.

    On CPU this is several times cheaper than ``wp.isfinite`` (which costs more than the rest of
    a face-volume kernel); Warp compiles without fast-math, so the product is never folded.
    """
    zero = type(x)(0.0)
    return x * zero == zero


@wp.func
@no_type_check
def finite3(a: Any, b: Any, c: Any):
    """Whether every component of three vectors is finite (see :func:`finite`)."""
    zero = type(a[0])(0.0)
    probe = a * zero + b * zero + c * zero
    return probe[0] + probe[1] + probe[2] == zero


@wp.func
@no_type_check
def load_cell(points: Coordinates, reference: Coordinates, cells: Topology, b: int, c: int, num_points: int):
    """Cell ``c`` of design ``b``: sorted vertices, current and reference edges, and whether all
    its indices are in range and its coordinates finite (edges are zero when not in range)."""
    m = cells.shape[1] - 1
    v, in_range = sorted_cell(cells, c, num_points)
    zero = points[0] - points[0]
    e0 = zero
    e1 = zero
    e2 = zero
    a0 = zero
    a1 = zero
    a2 = zero
    usable = False
    if in_range:
        base = b * num_points
        e0, e1, e2 = cell_edges(points, base, v, m)
        a0, a1, a2 = cell_edges(reference, base, v, m)
        usable = finite3(e0, e1, e2) and finite3(a0, a1, a2)
    return v, usable, e0, e1, e2, a0, a1, a2


@wp.func
@no_type_check
def unit_or_same(v: Any, norm: Any):
    """``v / |v|``; a zero-length ``v`` is returned unchanged (the JAX path divides by one)."""
    if norm > type(norm)(0.0):
        # One division and three products: divisions dominate these kernels' arithmetic.
        return v * (type(norm)(1.0) / norm)
    return v


@wp.func
@no_type_check
def gram_schmidt(e0: Any, e1: Any, e2: Any, m: int):
    """Modified Gram-Schmidt of the first ``m`` edges: ``(q0, q1, q2, r00, r01, r02, r11, r12, r22)``.

    Unused frame vectors are zero and unused diagonal entries one, so ``r00 * r11 * r22`` is the
    product of the ``m`` orthogonalised norms.
    """
    r00 = wp.length(e0)
    one = type(r00)(1.0)
    zero = type(r00)(0.0)
    q0 = unit_or_same(e0, r00)
    q1 = e0 - e0
    q2 = e0 - e0
    r01 = zero
    r02 = zero
    r12 = zero
    r11 = one
    r22 = one
    if m > 1:
        r01 = wp.dot(q0, e1)
        v1 = e1 - r01 * q0
        r11 = wp.length(v1)
        q1 = unit_or_same(v1, r11)
    if m > 2:
        r02 = wp.dot(q0, e2)
        v2 = e2 - r02 * q0
        r12 = wp.dot(q1, v2)
        v2 = v2 - r12 * q1
        r22 = wp.length(v2)
        q2 = unit_or_same(v2, r22)
    return q0, q1, q2, r00, r01, r02, r11, r12, r22


@wp.func
@no_type_check
def factorial(m: int, like: Any):
    """``m!`` for ``m <= 3`` in the scalar type of ``like``."""
    if m == 3:
        return type(like)(6.0)
    if m == 2:
        return type(like)(2.0)
    return type(like)(1.0)


@wp.func
@no_type_check
def scatter_edge_gradients(grad: wp.array(dtype=Any), base: int, v: wp.vec4i, m: int, g0: Any, g1: Any, g2: Any):
    """Add the gradient of consecutive edges ``g_k`` to the cell's vertices (unused ``g`` are zero)."""
    wp.atomic_sub(grad, base + v[0], g0)
    wp.atomic_add(grad, base + v[1], g0 - g1)
    if m > 1:
        wp.atomic_add(grad, base + v[2], g1 - g2)
        if m > 2:
            wp.atomic_add(grad, base + v[3], g2)


# ---------------------------------------------------------------------------------------------
# JAX side.


def energy_family(kernel, types, *, outputs, accumulate=()) -> KernelFamily:
    """A chunked family over ``(B, items)`` whose items all cost about the same (one chunk per thread)."""
    return KernelFamily(kernel, types, outputs=outputs, accumulate=accumulate, chunked=True, balanced=True)


GRADIENT_NAMES = ("points_bar", "reference_bar")


def per_item_terms(forward: KernelFamily, adjoint: KernelFamily):
    """The differentiable ``terms(points, reference, topology, extras, num_batch, statics)``.

    ``forward`` computes per-item outputs ``(B*M,)`` from the flat coordinates ``(B*N, 3)``,
    the ``(M, K)`` topology, the ``extras`` arrays (not differentiated), ``N`` and the static
    scalars ``statics``; ``adjoint`` takes the same inputs with the outputs' cotangents after
    ``extras`` and scatters ``points_bar`` and ``reference_bar``.
    """

    def run_forward(points, reference, topology, extras, num_batch, statics):
        num_points, num_items = points.shape[0] // num_batch, topology.shape[0]
        shapes = dict.fromkeys(forward.outputs, (num_batch * num_items,))
        call = forward(points.dtype)
        outputs = call(points, reference, topology, *extras, num_points, *statics, launch=(num_batch, num_items), shapes=shapes)
        return outputs, ()

    def run_adjoint(args, saved, cotangents):
        points, reference, topology, extras, num_batch, statics = args
        num_points, num_items = points.shape[0] // num_batch, topology.shape[0]
        shapes = dict.fromkeys(GRADIENT_NAMES, points.shape[:1])
        call = adjoint(points.dtype)
        return call(points, reference, topology, *extras, *cotangents, num_points, *statics, launch=(num_batch, num_items), shapes=shapes)

    return with_adjoint(run_forward, run_adjoint, static_argnums=(4, 5), constant_argnums=(2, 3))


KERNEL_DIMS = 3


def flat_vectors(points: jax.Array) -> jax.Array:
    """``(B, N, D)`` -> ``(B*N, 3)``, zero-padding ``D < 3``."""
    num_dims = points.shape[-1]
    if num_dims < KERNEL_DIMS:
        points = jnp.pad(points, [(0, 0), (0, 0), (0, KERNEL_DIMS - num_dims)])
    return points.reshape(-1, KERNEL_DIMS)


def kernel_inputs(points: jax.Array, reference_points: jax.Array, topology: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(B, N, D)`` coordinates and ``(M, K)`` topology as the kernels take them (see the module docstring)."""
    return flat_vectors(points), flat_vectors(reference_points), kernel_indices(topology, points.shape[1])


def kernel_indices(topology: jax.Array, num_points: int) -> jax.Array:
    """int32 topology for the kernels.

    int64 indices outside ``[0, N)`` become ``-1`` before narrowing, so none wraps into range;
    int32 indices pass unchanged (the kernels check the range themselves).
    """
    if topology.dtype == jnp.int32:
        return topology
    in_range = (topology >= 0) & (topology < num_points)
    return jnp.where(in_range, topology, -1).astype(jnp.int32)
