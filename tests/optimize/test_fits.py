"""geomjax.optimize fits: FFD lattices and morph control displacements by least squares."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from geomjax import free_form_deform_points, morph_points
from geomjax.optimize import fit_free_form_deformation, fit_morph

RESOLUTION = (3, 4, 3)
BOX = {"origin": [0.0, 0.0, 0.0], "extent": [1.0, 1.0, 1.0]}


def _bernstein_design(points, resolution):
    """``(N, nodes)`` tensor-product Bernstein weights by the binomial closed form (NumPy)."""
    u = np.asarray(points, np.float64)
    columns = []
    for node in np.ndindex(*resolution):
        weight = np.ones(len(u))
        for d, i in enumerate(node):
            p = resolution[d] - 1
            weight *= math.comb(p, i) * u[:, d] ** i * (1 - u[:, d]) ** (p - i)
        columns.append(weight)
    return np.stack(columns, axis=1)


def _rng_points(seed, n):
    return jnp.asarray(np.random.default_rng(seed).uniform(0.0, 1.0, (n, 3)))


def test_ffd_fit_recovers_the_lattice_that_made_the_targets():
    points = _rng_points(0, 120)
    true = jnp.asarray(np.random.default_rng(1).normal(0, 0.1, (*RESOLUTION, 3)))
    targets = free_form_deform_points(points, true, **BOX)
    lattice = fit_free_form_deformation(points, targets, RESOLUTION, **BOX)
    np.testing.assert_allclose(np.asarray(lattice), np.asarray(true), rtol=0, atol=1e-9)


def test_ffd_fit_with_regularization_is_the_ridge_solution_and_its_derivative():
    """Fewer points than nodes: the ridge solution (A^T A + lam I)^-1 A^T (T - P) of the closed-form
    design matrix A; its derivative with respect to the targets is that matrix's."""
    points = _rng_points(2, 20)  # 20 points, 36 nodes
    targets = points + jnp.asarray(np.random.default_rng(3).normal(0, 0.05, points.shape))
    lam = 1e-2
    design = _bernstein_design(points, RESOLUTION)
    ridge = np.linalg.solve(design.T @ design + lam * np.eye(design.shape[1]), design.T)
    expected = (ridge @ np.asarray(targets - points)).reshape(*RESOLUTION, 3)

    def fit(t):
        return fit_free_form_deformation(points, t, RESOLUTION, regularization=lam, **BOX)

    np.testing.assert_allclose(np.asarray(fit(targets)), expected, rtol=0, atol=1e-9)
    weights = jnp.asarray(np.random.default_rng(4).normal(size=(*RESOLUTION, 3)))
    gradient = jax.grad(lambda t: jnp.sum(weights * fit(t)))(targets)  # implicit adjoint
    np.testing.assert_allclose(np.asarray(gradient), ridge.T @ np.asarray(weights).reshape(-1, 3), rtol=0, atol=1e-9)


def test_fits_batch_under_vmap():
    points = jnp.stack([_rng_points(5, 60), _rng_points(6, 60)])
    trues = jnp.asarray(np.random.default_rng(7).normal(0, 0.1, (2, *RESOLUTION, 3)))
    targets = jax.vmap(lambda p, lat: free_form_deform_points(p, lat, **BOX))(points, trues)
    lattices = jax.vmap(lambda p, t: fit_free_form_deformation(p, t, RESOLUTION, **BOX))(points, targets)
    np.testing.assert_allclose(np.asarray(lattices), np.asarray(trues), rtol=0, atol=1e-9)


def test_morph_fit_recovers_the_control_displacements():
    rng = np.random.default_rng(8)
    points, controls = jnp.asarray(rng.uniform(0, 1, (150, 3))), jnp.asarray(rng.uniform(0, 1, (8, 3)))
    true = jnp.asarray(rng.normal(0, 0.05, (8, 3)))
    targets = morph_points(points, controls, true, radius=0.7)
    np.testing.assert_allclose(np.asarray(fit_morph(points, targets, controls, radius=0.7)), np.asarray(true), rtol=0, atol=1e-9)
    # Differentiable in the controls' positions too: finite differences of a fitted quantity.
    direction = jnp.asarray(rng.normal(size=controls.shape))

    def fitted(c):
        return jnp.sum(fit_morph(points, targets, c, radius=0.7) ** 2)

    step = 1e-6
    numeric = (fitted(controls + step * direction) - fitted(controls - step * direction)) / (2 * step)
    analytic = jnp.sum(jax.grad(fitted)(controls) * direction)
    np.testing.assert_allclose(float(analytic), float(numeric), rtol=1e-5)


def test_fit_errors():
    points = _rng_points(9, 10)
    with pytest.raises(ValueError, match="target_points must have the shape and dtype of points"):
        fit_free_form_deformation(points, points[:5], RESOLUTION, **BOX)
    with pytest.raises(ValueError, match="regularization must be a finite real >= 0"):
        fit_free_form_deformation(points, points, RESOLUTION, regularization=-1.0, **BOX)
    with pytest.raises(ValueError, match="resolution must give one node count per coordinate"):
        fit_free_form_deformation(points, points, (3, 3), **BOX)
    with pytest.raises(ValueError, match="target_points must have the shape and dtype of points"):
        fit_morph(points, points.astype(jnp.float32), points[:3], radius=0.5)


def test_non_finite_targets_and_failed_solves_are_reported():
    points = _rng_points(9, 40)
    bad = points.at[3, 1].set(jnp.nan)
    with pytest.raises(ValueError, match="target_points must be finite"):
        fit_free_form_deformation(points, bad, RESOLUTION, **BOX)
    with pytest.raises(ValueError, match="target_points must be finite"):
        fit_morph(points, bad, points[:4], radius=0.5)
    # A Gauss-Newton step that cannot confirm its tolerance in one step (nonlinear in nothing,
    # but max_steps=1 leaves no step to check convergence): optimistix's result says so.
    moved = 1.2 * points
    with pytest.raises(RuntimeError, match=r"fit_free_form_deformation: the least-squares solve did not succeed within max_steps=1"):
        fit_free_form_deformation(points, moved, RESOLUTION, max_steps=1, **BOX)
    solution = fit_free_form_deformation(points, moved, RESOLUTION, max_steps=1, return_solution=True, **BOX)
    assert solution.result == optx.RESULTS.nonlinear_max_steps_reached
    assert solution.value.shape == (*RESOLUTION, 3)
    # Traced non-finite targets (no eager check) fail the solve's own check.
    with pytest.raises(RuntimeError, match="fit_morph: the least-squares solve did not succeed"):
        jax.vmap(lambda t: fit_morph(points, t, points[:4], radius=0.5))(jnp.stack([moved, bad]))
