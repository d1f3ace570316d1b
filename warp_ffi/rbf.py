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
keeps the accumulators in registers) and per dtype (float32 and float64, via ``KernelFamily``).
Only first-order reverse mode is supported (no ``jvp``), as in the reference's Warp backend.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import warp as wp

from ._kernels import KernelFamily

__all__ = ["thin_plate_spline_field"]

# Queries summed by one thread of the control and affine adjoint kernels.
_SLICE = 256


@functools.cache
def _kernels(num_dims: int):
    """The four kernel families for ``num_dims`` coordinates."""
    D = num_dims

    @wp.kernel(enable_backward=False, module="unique")
    def field_kernel(
        points: wp.array3d(dtype=Any),
        controls: wp.array3d(dtype=Any),
        weights: wp.array3d(dtype=Any),
        constant: wp.array2d(dtype=Any),
        linear: wp.array3d(dtype=Any),
        field: wp.array3d(dtype=Any),
    ):
        b, i = wp.tid()
        x = wp.vector(dtype=points.dtype, length=wp.static(D))
        for k in range(wp.static(D)):
            x[k] = points[b, i, k]
        acc = wp.vector(dtype=points.dtype, length=wp.static(D))
        for d in range(wp.static(D)):
            value = constant[b, d]
            for k in range(wp.static(D)):
                value += x[k] * linear[b, k, d]
            acc[d] = value
        for j in range(controls.shape[1]):
            s = points.dtype(0.0)
            for k in range(wp.static(D)):
                t = x[k] - controls[b, j, k]
                s += t * t
            if s > points.dtype(0.0):
                phi = points.dtype(0.5) * s * wp.log(s)
                for d in range(wp.static(D)):
                    acc[d] += phi * weights[b, j, d]
        for d in range(wp.static(D)):
            field[b, i, d] = acc[d]

    @wp.kernel(enable_backward=False, module="unique")
    def points_adjoint_kernel(
        points: wp.array3d(dtype=Any),
        controls: wp.array3d(dtype=Any),
        weights: wp.array3d(dtype=Any),
        linear: wp.array3d(dtype=Any),
        field_grad: wp.array3d(dtype=Any),
        points_grad: wp.array3d(dtype=Any),
    ):
        b, i = wp.tid()
        x = wp.vector(dtype=points.dtype, length=wp.static(D))
        g = wp.vector(dtype=points.dtype, length=wp.static(D))
        for k in range(wp.static(D)):
            x[k] = points[b, i, k]
            g[k] = field_grad[b, i, k]
        acc = wp.vector(dtype=points.dtype, length=wp.static(D))
        for k in range(wp.static(D)):
            value = points.dtype(0.0)
            for d in range(wp.static(D)):
                value += linear[b, k, d] * g[d]
            acc[k] = value
        for j in range(controls.shape[1]):
            diff = wp.vector(dtype=points.dtype, length=wp.static(D))
            s = points.dtype(0.0)
            for k in range(wp.static(D)):
                diff[k] = x[k] - controls[b, j, k]
                s += diff[k] * diff[k]
            if s > points.dtype(0.0):
                gw = points.dtype(0.0)
                for d in range(wp.static(D)):
                    gw += g[d] * weights[b, j, d]
                # d phi / d x = 2 phi'(s) (x - c) = (log s + 1)(x - c)
                coefficient = (wp.log(s) + points.dtype(1.0)) * gw
                for k in range(wp.static(D)):
                    acc[k] += coefficient * diff[k]
        for k in range(wp.static(D)):
            points_grad[b, i, k] = acc[k]

    @wp.kernel(enable_backward=False, module="unique")
    def controls_adjoint_kernel(
        points: wp.array3d(dtype=Any),
        controls: wp.array3d(dtype=Any),
        weights: wp.array3d(dtype=Any),
        field_grad: wp.array3d(dtype=Any),
        controls_grad: wp.array3d(dtype=Any),
        weights_grad: wp.array3d(dtype=Any),
    ):
        b, j, part = wp.tid()
        c = wp.vector(dtype=points.dtype, length=wp.static(D))
        w = wp.vector(dtype=points.dtype, length=wp.static(D))
        for k in range(wp.static(D)):
            c[k] = controls[b, j, k]
            w[k] = weights[b, j, k]
        c_bar = wp.vector(dtype=points.dtype, length=wp.static(D))
        w_bar = wp.vector(dtype=points.dtype, length=wp.static(D))
        start = part * wp.static(_SLICE)
        stop = wp.min(start + wp.static(_SLICE), points.shape[1])
        for i in range(start, stop):
            diff = wp.vector(dtype=points.dtype, length=wp.static(D))
            s = points.dtype(0.0)
            for k in range(wp.static(D)):
                diff[k] = points[b, i, k] - c[k]
                s += diff[k] * diff[k]
            if s > points.dtype(0.0):
                log_s = wp.log(s)
                phi = points.dtype(0.5) * s * log_s
                gw = points.dtype(0.0)
                for d in range(wp.static(D)):
                    g = field_grad[b, i, d]
                    w_bar[d] += phi * g
                    gw += g * w[d]
                coefficient = (log_s + points.dtype(1.0)) * gw
                for k in range(wp.static(D)):
                    c_bar[k] -= coefficient * diff[k]
        for k in range(wp.static(D)):
            wp.atomic_add(controls_grad, b, j, k, c_bar[k])
            wp.atomic_add(weights_grad, b, j, k, w_bar[k])

    @wp.kernel(enable_backward=False, module="unique")
    def affine_adjoint_kernel(
        points: wp.array3d(dtype=Any),
        field_grad: wp.array3d(dtype=Any),
        constant_grad: wp.array2d(dtype=Any),
        linear_grad: wp.array3d(dtype=Any),
    ):
        b, part = wp.tid()
        a_bar = wp.vector(dtype=points.dtype, length=wp.static(D))
        l_bar = wp.matrix(dtype=points.dtype, shape=(wp.static(D), wp.static(D)))
        start = part * wp.static(_SLICE)
        stop = wp.min(start + wp.static(_SLICE), points.shape[1])
        for i in range(start, stop):
            for d in range(wp.static(D)):
                g = field_grad[b, i, d]
                a_bar[d] += g
                for k in range(wp.static(D)):
                    l_bar[k, d] += points[b, i, k] * g
        for d in range(wp.static(D)):
            wp.atomic_add(constant_grad, b, d, a_bar[d])
            for k in range(wp.static(D)):
                wp.atomic_add(linear_grad, b, k, d, l_bar[k, d])

    a3 = lambda T: wp.array3d(dtype=T)  # noqa: E731
    a2 = lambda T: wp.array2d(dtype=T)  # noqa: E731
    return {
        "field": KernelFamily(
            field_kernel,
            lambda T: {"points": a3(T), "controls": a3(T), "weights": a3(T), "constant": a2(T), "linear": a3(T), "field": a3(T)},
        ),
        "points_adjoint": KernelFamily(
            points_adjoint_kernel,
            lambda T: {"points": a3(T), "controls": a3(T), "weights": a3(T), "linear": a3(T), "field_grad": a3(T), "points_grad": a3(T)},
        ),
        "controls_adjoint": KernelFamily(
            controls_adjoint_kernel,
            lambda T: {
                "points": a3(T), "controls": a3(T), "weights": a3(T), "field_grad": a3(T),
                "controls_grad": a3(T), "weights_grad": a3(T),
            },
            num_outputs=2,
            in_out_argnames=["controls_grad", "weights_grad"],
        ),
        "affine_adjoint": KernelFamily(
            affine_adjoint_kernel,
            lambda T: {"points": a3(T), "field_grad": a3(T), "constant_grad": a2(T), "linear_grad": a3(T)},
            num_outputs=2,
            in_out_argnames=["constant_grad", "linear_grad"],
        ),
    }


def _num_slices(num_points: int) -> int:
    return -(-num_points // _SLICE)


@jax.custom_vjp
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


def _field(points, controls, weights, constant, linear):
    batch, num_points, num_dims = points.shape
    if batch == 0 or num_points == 0:
        return jnp.zeros(points.shape, points.dtype)
    (field,) = _kernels(num_dims)["field"](points.dtype)(
        points, controls, weights, constant, linear, launch_dims=(batch, num_points), output_dims={"field": points.shape}
    )
    return field


def _field_fwd(points, controls, weights, constant, linear):
    return _field(points, controls, weights, constant, linear), (points, controls, weights, linear)


def _field_bwd(residuals, field_grad):
    points, controls, weights, linear = residuals
    batch, num_points, num_dims = points.shape
    num_controls = controls.shape[1]
    dtype = points.dtype
    controls_grad = jnp.zeros(controls.shape, dtype)
    weights_grad = jnp.zeros(weights.shape, dtype)
    constant_grad = jnp.zeros((batch, num_dims), dtype)
    linear_grad = jnp.zeros(linear.shape, dtype)
    if batch == 0 or num_points == 0:
        return jnp.zeros(points.shape, dtype), controls_grad, weights_grad, constant_grad, linear_grad
    kernels = _kernels(num_dims)
    field_grad = field_grad.astype(dtype)
    (points_grad,) = kernels["points_adjoint"](dtype)(
        points, controls, weights, linear, field_grad,
        launch_dims=(batch, num_points), output_dims={"points_grad": points.shape},
    )
    slices = _num_slices(num_points)
    if num_controls:
        controls_grad, weights_grad = kernels["controls_adjoint"](dtype)(
            points, controls, weights, field_grad, controls_grad, weights_grad,
            launch_dims=(batch, num_controls, slices),
        )
    constant_grad, linear_grad = kernels["affine_adjoint"](dtype)(
        points, field_grad, constant_grad, linear_grad, launch_dims=(batch, slices)
    )
    return points_grad, controls_grad, weights_grad, constant_grad, linear_grad


thin_plate_spline_field.defvjp(_field_fwd, _field_bwd)
