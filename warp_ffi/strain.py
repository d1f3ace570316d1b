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

from typing import Any, no_type_check

import jax
import jax.numpy as jnp

from . import _energy
from ._energy import Coordinates, PerItem, Topology, factorial, finite, gram_schmidt, load_cell, scatter_edge_gradients, sorted_cell
from ._wrap import scalars, vectors, with_adjoint
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["simplex_strain_terms"]


@wp.func
@no_type_check
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
@no_type_check
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
@no_type_check
def _back_substitute(y0: Any, y1: Any, y2: Any, r00: Any, r01: Any, r02: Any, r11: Any, r12: Any, r22: Any):
    """Rows of ``R^-1 Y`` for upper-triangular ``R`` (unused rows of ``Y`` are zero)."""
    one = type(r00)(1.0)
    z2 = y2 * (one / r22)
    z1 = (y1 - r12 * z2) * (one / r11)
    z0 = (y0 - r01 * z1 - r02 * z2) * (one / r00)
    return z0, z1, z2


@wp.func
@no_type_check
def _cell_energy(
    points: wp.array(dtype=Any), reference: wp.array(dtype=Any), cells: wp.array2d(dtype=wp.int32), moduli: wp.array(dtype=Any),
    b: int, c: int, num_points: int,
):  # fmt: skip
    """Whether the cell is valid, its energy ``V0 w`` and what its gradients need (meaningless when invalid)."""
    m = cells.shape[1] - 1
    v, usable, e0, e1, e2, a0, a1, a2 = load_cell(points, reference, cells, b, c, num_points)
    q0, q1, q2, r00, r01, r02, r11, r12, r22 = gram_schmidt(a0, a1, a2, m)
    rest = r00 * r11 * r22 / factorial(m, r00)
    nil = type(r00)(0.0)
    finite_entries = finite(r01) and finite(r02) and finite(r12) and finite(rest)
    positive = r00 > nil and r11 > nil and r22 > nil
    f0, f1, f2 = _deformation(e0, e1, e2, r00, r01, r02, r11, r12, r22, m)
    w, stress, cauchy_green = _density(f0, f1, f2, moduli[0], moduli[1], m)
    valid = usable and finite_entries and positive
    return valid, rest * w, f0, f1, f2, q0, q1, q2, r00, r01, r02, r11, r12, r22, rest, w, stress, cauchy_green


@wp.kernel
@no_type_check
def _forward_kernel(
    points: Coordinates, reference: Coordinates, cells: Topology, moduli: wp.array(dtype=Any), num_points: int, offset: int,
    energy: PerItem,
):  # fmt: skip
    b, t = wp.tid()
    c = t + offset
    valid, cell_energy, f0, f1, f2, q0, q1, q2, r00, r01, r02, r11, r12, r22, rest, w, stress, cauchy_green = _cell_energy(
        points, reference, cells, moduli, b, c, num_points
    )
    energy[b * cells.shape[0] + c] = wp.where(valid, cell_energy, energy.dtype(wp.nan))


@wp.kernel
@no_type_check
def _gradient_kernel(
    points: Coordinates, reference: Coordinates, cells: Topology, moduli: wp.array(dtype=Any), num_points: int, offset: int,
    energy: PerItem, edge_gradients: wp.array2d(dtype=Any), valid_cells: wp.array(dtype=wp.int32),
):  # fmt: skip
    """The energy and, for the adjoint, ``dW/dE`` (rows 0-2) and ``dW/dE0`` (rows 3-5) per cell."""
    b, t = wp.tid()
    c = t + offset
    out = b * cells.shape[0] + c
    valid, cell_energy, f0, f1, f2, q0, q1, q2, r00, r01, r02, r11, r12, r22, rest, w, stress, cauchy_green = _cell_energy(
        points, reference, cells, moduli, b, c, num_points
    )
    if not valid:
        energy[out] = energy.dtype(wp.nan)
        valid_cells[out] = 0
        return
    valid_cells[out] = 1
    energy[out] = cell_energy
    m = cells.shape[1] - 1

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
@no_type_check
def _scatter_kernel(
    cells: Topology, edge_gradients: wp.array2d(dtype=Any), valid_cells: wp.array(dtype=wp.int32), energy_bar: PerItem,
    num_points: int, offset: int, points_bar: Coordinates, reference_bar: Coordinates,
):  # fmt: skip
    """Vertex gradients: the stored edge gradients of valid cells times the cotangent."""
    b, t = wp.tid()
    c = t + offset
    out = b * cells.shape[0] + c
    if valid_cells[out] == 0:
        return
    m = cells.shape[1] - 1
    v, in_range = sorted_cell(cells, c, num_points)
    g = energy_bar[out]
    base = b * num_points
    scatter_edge_gradients(points_bar, base, v, m, g * edge_gradients[out, 0], g * edge_gradients[out, 1], g * edge_gradients[out, 2])
    scatter_edge_gradients(reference_bar, base, v, m, g * edge_gradients[out, 3], g * edge_gradients[out, 4], g * edge_gradients[out, 5])


def _types(s):
    return {name: vectors(s) for name in ("points", "reference", *_energy.GRADIENT_NAMES)} | {
        "moduli": scalars(s),
        "energy": scalars(s),
        "energy_bar": scalars(s),
        "edge_gradients": vectors(s, ndim=2),
    }


_forward = _energy.energy_family(_forward_kernel, _types, outputs=("energy",))
_forward_with_gradients = _energy.energy_family(_gradient_kernel, _types, outputs=("energy", "edge_gradients", "valid_cells"))
_scatter = _energy.energy_family(_scatter_kernel, _types, outputs=_energy.GRADIENT_NAMES, accumulate=_energy.GRADIENT_NAMES)


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
    num_batch = points.shape[0]
    moduli = jnp.stack([shear_modulus, bulk_term]).astype(points.dtype)
    energy = _strain_energy(*_energy.kernel_inputs(points, reference_points, cells), moduli, num_batch)
    return energy.reshape(num_batch, -1)


def _energy_only(points, reference, cells, moduli, num_batch):
    size, num_points = num_batch * cells.shape[0], points.shape[0] // num_batch
    (energy,) = _forward(points.dtype)(points, reference, cells, moduli, num_points, launch=(num_batch, cells.shape[0]), shapes={"energy": (size,)})
    return energy


def _energy_and_edge_gradients(points, reference, cells, moduli, num_batch):
    size, num_points = num_batch * cells.shape[0], points.shape[0] // num_batch
    shapes = {"energy": (size,), "edge_gradients": (size, 6), "valid_cells": (size,)}
    energy, edge_gradients, valid_cells = _forward_with_gradients(points.dtype)(
        points, reference, cells, moduli, num_points, launch=(num_batch, cells.shape[0]), shapes=shapes
    )
    return energy, (edge_gradients, valid_cells)


def _scattered_gradients(args, saved, energy_bar):
    points, reference, cells, moduli, num_batch = args
    edge_gradients, valid_cells = saved
    shapes = dict.fromkeys(_energy.GRADIENT_NAMES, points.shape[:1])
    return _scatter(points.dtype)(
        cells, edge_gradients, valid_cells, energy_bar, points.shape[0] // num_batch, launch=(num_batch, cells.shape[0]), shapes=shapes
    )


# The moduli are validated Python floats, not differentiated.
_strain_energy = with_adjoint(_energy_and_edge_gradients, _scattered_gradients, primal=_energy_only, static_argnums=(4,), constant_argnums=(2, 3))
