"""St. Venant-Kirchhoff simplex strain energy on Warp, with a hand-written adjoint.

Per cell (``m`` edges ``E``, reference edges ``E0``, rows are edges): the modified Gram-Schmidt
QR ``E0^T = Q R`` gives the intrinsic frame, ``F = E^T R^-1`` (forward substitution),
``C = F^T F``, ``eps = (C - I) / 2`` and ``W = V0 [mu |dev eps|^2 + kappa tr(eps)^2]`` with
``V0 = r00 r11 r22 / m!`` and ``kappa = lambda / 2 + mu / m``.

Adjoint. With ``S = dw/dC = mu dev eps + kappa tr(eps) I`` (a polynomial in ``C``, so ``S C`` is
symmetric):

* ``dW/dE = 2 V0 R^-1 S F^T``;
* ``W`` depends on ``E0`` only through ``G0 = E0 E0^T = R^T R``; differentiating
  ``C = R^-T G R^-1`` and ``V0`` through the Cholesky-like factor gives
  ``dW/dG0 = V0 R^-1 T R^-T / 2`` with ``T = w I - 2 S C``, hence ``dW/dE0 = V0 R^-1 T Q^T``.

Both are back substitutions with ``R``. Under differentiation the forward kernel stores them per
cell and the backward kernel scatters them, times the cotangent, to the sorted vertices.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from ._energy import (
    cell_edges,
    factorial,
    finite,
    finite3,
    flat_vectors,
    gram_schmidt,
    kernel_indices,
    launch,
    scatter_edge_gradients,
    sorted_cell,
)
from ._kernels import WARP_SCALAR
from ._kernels import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["simplex_strain_terms"]


@wp.func
def _state(points: wp.array(dtype=Any), reference: wp.array(dtype=Any), cells: wp.array2d(dtype=wp.int32), b: int, c: int, num_points: int):
    """Gather a cell, orthogonalise its reference edges and decide whether it is valid."""
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
    q0, q1, q2, r00, r01, r02, r11, r12, r22 = gram_schmidt(a0, a1, a2, m)
    rest = r00 * r11 * r22 / factorial(m, r00)
    nil = type(r00)(0.0)
    finite_entries = finite(r01) and finite(r02) and finite(r12) and finite(rest)
    positive = r00 > nil and r11 > nil and r22 > nil
    return usable and finite_entries and positive, v, e0, e1, e2, q0, q1, q2, r00, r01, r02, r11, r12, r22, rest


@wp.func
def _deformation(e0: Any, e1: Any, e2: Any, r00: Any, r01: Any, r02: Any, r11: Any, r12: Any, r22: Any, m: int):
    """Columns of ``F = E^T R^-1`` by forward substitution (unused columns zero)."""
    one = type(r00)(1.0)
    f0 = e0 * (one / r00)
    f1 = e0 - e0
    f2 = e0 - e0
    if m > 1:
        f1 = (e1 - r01 * f0) * (one / r11)
    if m > 2:
        f2 = ((e2 - r02 * f0) - r12 * f1) * (one / r22)
    return f0, f1, f2


@wp.func
def _density(f0: Any, f1: Any, f2: Any, mu: Any, kappa: Any, m: int):
    """``(w, S, C)``: energy density per reference measure, ``dw/dC`` and ``C`` (3x3, unused zero)."""
    one = type(mu)(1.0)
    half = type(mu)(0.5)
    nil = type(mu)(0.0)
    c00 = wp.dot(f0, f0)
    c01 = wp.dot(f0, f1)
    c02 = wp.dot(f0, f2)
    c11 = wp.dot(f1, f1)
    c12 = wp.dot(f1, f2)
    c22 = wp.dot(f2, f2)
    s00 = (c00 - one) * half
    s11 = nil
    s22 = nil
    if m > 1:
        s11 = (c11 - one) * half
    if m > 2:
        s22 = (c22 - one) * half
    s01 = c01 * half
    s02 = c02 * half
    s12 = c12 * half
    trace = s00 + s11 + s22
    mean = trace / type(mu)(float(m))
    d00 = s00 - mean
    d11 = nil
    d22 = nil
    if m > 1:
        d11 = s11 - mean
    if m > 2:
        d22 = s22 - mean
    deviatoric = (d00 * d00 + d11 * d11 + d22 * d22) + type(mu)(2.0) * (s01 * s01 + s02 * s02 + s12 * s12)
    w = mu * deviatoric + kappa * (trace * trace)
    volumetric = kappa * trace
    stress = wp.matrix(
        mu * d00 + volumetric, mu * s01, mu * s02,
        mu * s01, mu * d11, mu * s12,
        mu * s02, mu * s12, mu * d22,
        shape=(3, 3),
    )  # fmt: skip
    if m > 1:
        stress[1, 1] = stress[1, 1] + volumetric
    if m > 2:
        stress[2, 2] = stress[2, 2] + volumetric
    cauchy_green = wp.matrix(c00, c01, c02, c01, c11, c12, c02, c12, c22, shape=(3, 3))
    return w, stress, cauchy_green


@wp.func
def _back_substitute(y0: Any, y1: Any, y2: Any, r00: Any, r01: Any, r02: Any, r11: Any, r12: Any, r22: Any):
    """Rows of ``R^-1 Y`` for upper-triangular ``R`` (unused rows of ``Y`` are zero)."""
    one = type(r00)(1.0)
    z2 = y2 * (one / r22)
    z1 = (y1 - r12 * z2) * (one / r11)
    z0 = (y0 - r01 * z1 - r02 * z2) * (one / r00)
    return z0, z1, z2


@wp.kernel
def _forward_kernel(
    points: wp.array(dtype=Any),
    reference: wp.array(dtype=Any),
    cells: wp.array2d(dtype=wp.int32),
    moduli: wp.array(dtype=Any),
    num_points: int,
    offset: int,
    energy: wp.array(dtype=Any),
):
    b, t = wp.tid()
    c = t + offset
    num_cells = cells.shape[0]
    if c >= num_cells:
        return
    out = b * num_cells + c
    valid, v, e0, e1, e2, q0, q1, q2, r00, r01, r02, r11, r12, r22, rest = _state(points, reference, cells, b, c, num_points)
    if not valid:
        energy[out] = energy.dtype(wp.nan)
        return
    m = cells.shape[1] - 1
    f0, f1, f2 = _deformation(e0, e1, e2, r00, r01, r02, r11, r12, r22, m)
    w, stress, cauchy_green = _density(f0, f1, f2, moduli[0], moduli[1], m)
    energy[out] = rest * w


@wp.kernel
def _gradient_kernel(
    points: wp.array(dtype=Any),
    reference: wp.array(dtype=Any),
    cells: wp.array2d(dtype=wp.int32),
    moduli: wp.array(dtype=Any),
    num_points: int,
    offset: int,
    energy: wp.array(dtype=Any),
    edge_gradients: wp.array2d(dtype=Any),
    valid_cells: wp.array(dtype=wp.int32),
):
    """The energy and, for the adjoint, ``dW/dE`` (rows 0-2) and ``dW/dE0`` (rows 3-5) per cell."""
    b, t = wp.tid()
    c = t + offset
    num_cells = cells.shape[0]
    if c >= num_cells:
        return
    out = b * num_cells + c
    valid, v, e0, e1, e2, q0, q1, q2, r00, r01, r02, r11, r12, r22, rest = _state(points, reference, cells, b, c, num_points)
    if not valid:
        energy[out] = energy.dtype(wp.nan)
        valid_cells[out] = 0
        return
    valid_cells[out] = 1
    m = cells.shape[1] - 1
    f0, f1, f2 = _deformation(e0, e1, e2, r00, r01, r02, r11, r12, r22, m)
    w, stress, cauchy_green = _density(f0, f1, f2, moduli[0], moduli[1], m)
    energy[out] = rest * w

    # dW/dE = 2 V0 R^-1 S F^T
    y = stress * wp.matrix_from_rows(f0, f1, f2)
    z0, z1, z2 = _back_substitute(y[0], y[1], y[2], r00, r01, r02, r11, r12, r22)
    two = rest + rest
    edge_gradients[out, 0] = two * z0
    edge_gradients[out, 1] = two * z1
    edge_gradients[out, 2] = two * z2

    # dW/dE0 = V0 R^-1 (w I - 2 S C) Q^T, with the identity restricted to the m used rows
    one = type(w)(1.0)
    nil = type(w)(0.0)
    used = wp.matrix(one, nil, nil, nil, one, nil, nil, nil, one, shape=(3, 3))
    if m < 3:
        used[2, 2] = nil
    if m < 2:
        used[1, 1] = nil
    product = stress * cauchy_green
    tension = w * used - (product + product)
    y = tension * wp.matrix_from_rows(q0, q1, q2)
    z0, z1, z2 = _back_substitute(y[0], y[1], y[2], r00, r01, r02, r11, r12, r22)
    edge_gradients[out, 3] = rest * z0
    edge_gradients[out, 4] = rest * z1
    edge_gradients[out, 5] = rest * z2


@wp.kernel
def _scatter_kernel(
    cells: wp.array2d(dtype=wp.int32),
    edge_gradients: wp.array2d(dtype=Any),
    valid_cells: wp.array(dtype=wp.int32),
    energy_bar: wp.array(dtype=Any),
    num_points: int,
    offset: int,
    points_bar: wp.array(dtype=Any),
    reference_bar: wp.array(dtype=Any),
):
    """Vertex gradients: the stored edge gradients of valid cells times the cotangent."""
    b, t = wp.tid()
    c = t + offset
    num_cells = cells.shape[0]
    if c >= num_cells:
        return
    out = b * num_cells + c
    if valid_cells[out] == 0:
        return
    m = cells.shape[1] - 1
    v, in_range = sorted_cell(cells, c, num_points)
    g = energy_bar[out]
    base = b * num_points
    scatter_edge_gradients(points_bar, base, v, m, g * edge_gradients[out, 0], g * edge_gradients[out, 1], g * edge_gradients[out, 2])
    scatter_edge_gradients(reference_bar, base, v, m, g * edge_gradients[out, 3], g * edge_gradients[out, 4], g * edge_gradients[out, 5])


@functools.cache
def _callables(dtype):
    """``(energy, energy_and_gradients, scatter)`` JAX callables for one float dtype."""
    scalar = WARP_SCALAR[jnp.dtype(dtype)]
    vectors = wp.array(dtype=wp.types.vector(3, scalar))
    vector_table = wp.array2d(dtype=wp.types.vector(3, scalar))
    reals = wp.array(dtype=scalar)
    flags = wp.array(dtype=wp.int32)
    cells_type = wp.array2d(dtype=wp.int32)
    forward_kernel = wp.overload(_forward_kernel, [vectors, vectors, cells_type, reals, int, int, reals])
    gradient_kernel = wp.overload(_gradient_kernel, [vectors, vectors, cells_type, reals, int, int, reals, vector_table, flags])
    scatter_kernel = wp.overload(_scatter_kernel, [cells_type, vector_table, flags, reals, int, int, vectors, vectors])

    def forward(points, reference, cells, moduli, energy):
        num_batch = energy.shape[0] // cells.shape[0]
        launch(forward_kernel, num_batch, cells.shape[0], [points, reference, cells, moduli, points.shape[0] // num_batch], [energy])

    def forward_with_gradients(points, reference, cells, moduli, energy, edge_gradients, valid_cells):
        num_batch = energy.shape[0] // cells.shape[0]
        inputs = [points, reference, cells, moduli, points.shape[0] // num_batch]
        launch(gradient_kernel, num_batch, cells.shape[0], inputs, [energy, edge_gradients, valid_cells])

    def scatter(cells, edge_gradients, valid_cells, energy_bar, points_bar, reference_bar):
        num_batch = energy_bar.shape[0] // cells.shape[0]
        inputs = [cells, edge_gradients, valid_cells, energy_bar, points_bar.shape[0] // num_batch]
        launch(scatter_kernel, num_batch, cells.shape[0], inputs, [points_bar, reference_bar], accumulated=(0, 1))

    forward.__annotations__ = dict(points=vectors, reference=vectors, cells=cells_type, moduli=reals, energy=reals)
    forward_with_gradients.__annotations__ = dict(
        points=vectors, reference=vectors, cells=cells_type, moduli=reals, energy=reals, edge_gradients=vector_table,
        valid_cells=flags,
    )  # fmt: skip
    scatter.__annotations__ = dict(
        cells=cells_type, edge_gradients=vector_table, valid_cells=flags, energy_bar=reals, points_bar=vectors, reference_bar=vectors
    )
    return (
        wp.jax_callable(forward, num_outputs=1, vmap_method="sequential"),
        wp.jax_callable(forward_with_gradients, num_outputs=3, vmap_method="sequential"),
        wp.jax_callable(scatter, num_outputs=2, vmap_method="sequential"),
    )


# Register every overload now: a new overload after the module is built forces a rebuild.
for _dtype in WARP_SCALAR:
    _callables(_dtype)


@jax.jit
def simplex_strain_terms(points: jax.Array, reference_points: jax.Array, cells: jax.Array, *, shear_modulus: float, bulk_term: float) -> jax.Array:
    """Per-cell St. Venant-Kirchhoff energies ``(B, M)`` on ``(B, N, D <= 3)`` points.

    ``bulk_term`` is ``kappa = lambda / 2 + mu / m``. NaN for invalid cells (out-of-range index,
    non-finite coordinates, reference ``R`` with a zero diagonal or non-finite entries), which
    pass no gradient back. Differentiable once in reverse mode in both coordinate arrays; ``jit``
    and ``vmap`` (sequential) compatible. Requires ``B, N, M > 0``.

    Under differentiation the forward kernel also stores each cell's edge gradients (six
    3-vectors, e.g. 28 MB for 196,608 float64 tetrahedra), so the backward pass only scales
    and scatters them instead of recomputing the cell state.
    """
    num_batch, num_points, _ = points.shape
    moduli = jnp.stack([shear_modulus, bulk_term]).astype(points.dtype)
    indices = kernel_indices(cells, num_points)
    energy = _energy(flat_vectors(points), flat_vectors(reference_points), indices, moduli, num_batch, num_points)
    return energy.reshape(num_batch, -1)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5))
def _energy(points, reference, cells, moduli, num_batch, num_points):
    forward, _, _ = _callables(points.dtype)
    (energy,) = forward(points, reference, cells, moduli, output_dims={"energy": (num_batch * cells.shape[0],)})
    return energy


def _energy_fwd(points, reference, cells, moduli, num_batch, num_points):
    _, forward_with_gradients, _ = _callables(points.dtype)
    size = num_batch * cells.shape[0]
    dims = {"energy": (size,), "edge_gradients": (size, 6), "valid_cells": (size,)}
    energy, edge_gradients, valid_cells = forward_with_gradients(points, reference, cells, moduli, output_dims=dims)
    return energy, (cells, edge_gradients, valid_cells, moduli)


def _energy_bwd(num_batch, num_points, residuals, energy_bar):
    cells, edge_gradients, valid_cells, moduli = residuals
    _, _, scatter = _callables(edge_gradients.dtype)
    dims = {"points_bar": (num_batch * num_points,), "reference_bar": (num_batch * num_points,)}
    points_bar, reference_bar = scatter(cells, edge_gradients, valid_cells, energy_bar, output_dims=dims)
    # The moduli are validated Python floats, not differentiated.
    return points_bar, reference_bar, None, jnp.zeros_like(moduli)


_energy.defvjp(_energy_fwd, _energy_bwd)
