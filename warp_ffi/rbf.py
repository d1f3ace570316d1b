"""Thin-plate-spline field evaluation as Warp kernels, differentiable through ``jax.custom_vjp``.

``thin_plate_spline_field(points, controls, weights, constant, linear)`` evaluates

    u_b(x_i) = sum_j phi(|x_i - c_bj|^2) w_bj + constant_b + x_i @ linear_b,
    phi(s) = 0.5 s log s  (phi(0) = 0),

on ``(B, N, D)`` points, streaming over the controls for each query (no ``N x C`` array). The
inputs arrive normalised (geomjax centres and scales them and fits the coefficients in JAX).
The adjoint is hand written:

* ``points``: one thread per query, ``x_bar = linear g + sum_j (log s_ij + 1) (g . w_j)(x_i - c_j)``.
* ``controls`` and ``weights``: one thread per (control, slice of queries); each thread sums its
  slice and adds it atomically, so there are few atomics per control and enough threads on GPU.
* ``constant`` and ``linear``: one thread per slice of queries, ``sum g`` and ``sum x g^T``.

Kernels are generated per coordinate count ``D`` (``wp.static`` unrolls the coordinate loops and
keeps the accumulators in registers) and per dtype (float32 and float64).
Only first-order reverse mode is supported (no ``jvp``), as in the reference's Warp backend.
"""

from __future__ import annotations

import functools
from typing import Any, no_type_check

import jax.numpy as jnp

from ._wrap import KernelFamily, with_adjoint
from ._wrap import warp as wp

__all__ = ["thin_plate_spline_field"]

# Queries summed by one thread of the control and affine adjoint kernels.
_SLICE = 256

# The kernels' argument types (float types resolved per overload).
Batched: Any = wp.array3d(dtype=Any)  # (B, N, D) points and fields, (B, C, D) controls and weights, (B, D, D) linear parts
PerDesign: Any = wp.array2d(dtype=Any)  # (B, D) constant parts


def _types(s):
    batched = ("points", "controls", "weights", "linear", "field", "field_grad", "points_grad", "controls_grad", "weights_grad")
    return {name: wp.array3d(dtype=s) for name in (*batched, "linear_grad")} | {"constant": wp.array2d(dtype=s), "constant_grad": wp.array2d(dtype=s)}


@functools.cache
def _kernels(num_dims: int) -> dict:
    """The four kernel families for ``num_dims`` coordinates."""
    D = num_dims

    @wp.func
    @no_type_check
    def row(values: wp.array3d(dtype=Any), b: int, i: int):
        """``values[b, i]`` as a ``D``-vector."""
        v = wp.vector(dtype=values.dtype, length=wp.static(D))
        for k in range(wp.static(D)):
            v[k] = values[b, i, k]
        return v

    @wp.func
    @no_type_check
    def store(values: wp.array3d(dtype=Any), b: int, i: int, v: Any):
        for k in range(wp.static(D)):
            values[b, i, k] = v[k]

    @wp.func
    @no_type_check
    def linear_map(linear: wp.array3d(dtype=Any), b: int, v: Any, start: Any, transpose: int):
        """``start + v @ linear[b]``, or ``start + linear[b] @ v`` when ``transpose``, summed in index order."""
        out = wp.vector(dtype=linear.dtype, length=wp.static(D))
        for r in range(wp.static(D)):
            value = start[r]
            for k in range(wp.static(D)):
                if transpose == 0:
                    value += v[k] * linear[b, k, r]
                else:
                    value += linear[b, r, k] * v[k]
            out[r] = value
        return out

    @wp.kernel(enable_backward=False, module="unique")
    @no_type_check
    def field_kernel(
        points: Batched, controls: Batched, weights: Batched, constant: PerDesign, linear: Batched, field: Batched,
    ):  # fmt: skip
        b, i = wp.tid()
        x = row(points, b, i)
        offset = wp.vector(dtype=points.dtype, length=wp.static(D))
        for d in range(wp.static(D)):
            offset[d] = constant[b, d]
        acc = linear_map(linear, b, x, offset, 0)
        for j in range(controls.shape[1]):
            diff = x - row(controls, b, j)
            s = wp.dot(diff, diff)
            if s > points.dtype(0.0):
                acc += points.dtype(0.5) * s * wp.log(s) * row(weights, b, j)
        store(field, b, i, acc)

    @wp.kernel(enable_backward=False, module="unique")
    @no_type_check
    def points_adjoint_kernel(
        points: Batched, controls: Batched, weights: Batched, linear: Batched, field_grad: Batched, points_grad: Batched,
    ):  # fmt: skip
        b, i = wp.tid()
        x = row(points, b, i)
        g = row(field_grad, b, i)
        acc = linear_map(linear, b, g, wp.vector(dtype=points.dtype, length=wp.static(D)), 1)
        for j in range(controls.shape[1]):
            diff = x - row(controls, b, j)
            s = wp.dot(diff, diff)
            if s > points.dtype(0.0):
                # d phi / d x = 2 phi'(s) (x - c) = (log s + 1)(x - c)
                acc += (wp.log(s) + points.dtype(1.0)) * wp.dot(g, row(weights, b, j)) * diff
        store(points_grad, b, i, acc)

    @wp.kernel(enable_backward=False, module="unique")
    @no_type_check
    def controls_adjoint_kernel(
        points: Batched, controls: Batched, weights: Batched, field_grad: Batched, controls_grad: Batched, weights_grad: Batched,
    ):  # fmt: skip
        b, j, part = wp.tid()
        c = row(controls, b, j)
        w = row(weights, b, j)
        c_bar = wp.vector(dtype=points.dtype, length=wp.static(D))
        w_bar = wp.vector(dtype=points.dtype, length=wp.static(D))
        start = part * wp.static(_SLICE)
        for i in range(start, wp.min(start + wp.static(_SLICE), points.shape[1])):
            diff = row(points, b, i) - c
            s = wp.dot(diff, diff)
            if s > points.dtype(0.0):
                log_s = wp.log(s)
                g = row(field_grad, b, i)
                w_bar += points.dtype(0.5) * s * log_s * g
                c_bar -= (log_s + points.dtype(1.0)) * wp.dot(g, w) * diff
        for k in range(wp.static(D)):
            wp.atomic_add(controls_grad, b, j, k, c_bar[k])
            wp.atomic_add(weights_grad, b, j, k, w_bar[k])

    @wp.kernel(enable_backward=False, module="unique")
    @no_type_check
    def affine_adjoint_kernel(
        points: Batched, field_grad: Batched, constant_grad: PerDesign, linear_grad: Batched,
    ):  # fmt: skip
        b, part = wp.tid()
        a_bar = wp.vector(dtype=points.dtype, length=wp.static(D))
        l_bar = wp.matrix(dtype=points.dtype, shape=(wp.static(D), wp.static(D)))
        start = part * wp.static(_SLICE)
        for i in range(start, wp.min(start + wp.static(_SLICE), points.shape[1])):
            for d in range(wp.static(D)):
                g = field_grad[b, i, d]
                a_bar[d] += g
                for k in range(wp.static(D)):
                    l_bar[k, d] += points[b, i, k] * g
        for d in range(wp.static(D)):
            wp.atomic_add(constant_grad, b, d, a_bar[d])
            for k in range(wp.static(D)):
                wp.atomic_add(linear_grad, b, k, d, l_bar[k, d])

    scattered = ("controls_grad", "weights_grad", "constant_grad", "linear_grad")
    return {
        "field": KernelFamily(field_kernel, _types, outputs=("field",)),
        "points_adjoint": KernelFamily(points_adjoint_kernel, _types, outputs=("points_grad",)),
        # These two scatter per-slice sums with atomics into zeroed buffers.
        "controls_adjoint": KernelFamily(controls_adjoint_kernel, _types, outputs=scattered[:2], accumulate=scattered[:2]),
        "affine_adjoint": KernelFamily(affine_adjoint_kernel, _types, outputs=scattered[2:], accumulate=scattered[2:]),
    }


def _num_slices(num_points: int) -> int:
    return -(-num_points // _SLICE)


def thin_plate_spline_field(points, controls, weights, constant, linear):
    """Thin-plate-spline field on ``(B, N, D)`` points.

    Args:
        points: ``(B, N, D)`` float32/float64 query points.
        controls, weights: ``(B, C, D)`` control locations and radial coefficients.
        constant: ``(B, D)``; linear: ``(B, D, D)`` (``u += x @ linear``).

    Returns:
        ``(B, N, D)`` field values. Reverse-mode differentiable in every argument.
    """
    return _field(points, controls, weights, constant, linear)


def _field_forward(points, controls, weights, constant, linear):
    batch, num_points, num_dims = points.shape
    if batch == 0 or num_points == 0:
        return jnp.zeros(points.shape, points.dtype), ()
    (field,) = _kernels(num_dims)["field"](points.dtype)(
        points, controls, weights, constant, linear, launch=(batch, num_points), shapes={"field": points.shape}
    )
    return field, ()


def _field_adjoint(args, saved, field_grad):
    points, controls, weights, constant, linear = args
    batch, num_points, num_dims = points.shape
    num_controls = controls.shape[1]
    dtype = points.dtype
    if batch == 0 or num_points == 0:
        return jnp.zeros_like(points), jnp.zeros_like(controls), jnp.zeros_like(weights), jnp.zeros_like(constant), jnp.zeros_like(linear)
    kernels = _kernels(num_dims)
    field_grad = field_grad.astype(dtype)
    (points_grad,) = kernels["points_adjoint"](dtype)(
        points, controls, weights, linear, field_grad, launch=(batch, num_points), shapes={"points_grad": points.shape}
    )
    slices = _num_slices(num_points)
    controls_grad, weights_grad = jnp.zeros_like(controls), jnp.zeros_like(weights)
    if num_controls:
        controls_grad, weights_grad = kernels["controls_adjoint"](dtype)(
            points, controls, weights, field_grad, launch=(batch, num_controls, slices),
            shapes={"controls_grad": controls.shape, "weights_grad": weights.shape},
        )  # fmt: skip
    constant_grad, linear_grad = kernels["affine_adjoint"](dtype)(
        points, field_grad, launch=(batch, slices), shapes={"constant_grad": constant.shape, "linear_grad": linear.shape}
    )
    return points_grad, controls_grad, weights_grad, constant_grad, linear_grad


_field = with_adjoint(_field_forward, _field_adjoint)
