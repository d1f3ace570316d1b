"""geomjax.optimize.register_surface: a template surface onto a target by an FFD lattice."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from geomjax import Mesh, free_form_deform_points, icosphere, signed_distance_field, simplex_strain_energy, surface_bending_energy
from geomjax.energy.bending import bending_residuals
from geomjax.energy.strain import strain_residuals
from geomjax.optimize import register_surface
from geomjax.optimize import _registration as registration_module
from geomjax.optimize._registration import registration_residuals

BOX = {"origin": [-1.5, -1.5, -1.5], "extent": [3.0, 3.0, 3.0]}
RESOLUTION = (3, 3, 3)  # degree-2 Bernstein: reproduces every affine map of the box exactly


def _sphere():
    sphere = icosphere(2)
    return jnp.asarray(sphere.points), jnp.asarray(sphere.cells)


def _distances(points, target_points, target_faces) -> np.ndarray:
    """Unsigned distances to the target surface, by the signed-distance op (independent of the fit)."""
    return np.abs(np.asarray(signed_distance_field(target_points, target_faces, points)[0]))


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_residual_forms_sum_to_the_energies(implementation):
    """The Gauss-Newton residuals of the regularisers square to the library's energies."""
    points, faces = _sphere()
    rng = np.random.default_rng(0)
    moved = points * jnp.asarray([1.2, 0.9, 1.0]) + jnp.asarray(rng.normal(0, 0.03, points.shape))
    for lame_lambda, shear_modulus in ((1.0, 1.0), (0.3, 2.0)):
        energy = simplex_strain_energy(moved, points, faces, lame_lambda=lame_lambda, shear_modulus=shear_modulus, reduction="none", implementation=implementation)
        residuals, valid = strain_residuals(moved[None], points[None], faces, shear_modulus, lame_lambda / 2 + shear_modulus / 2)
        assert bool(jnp.all(valid))
        np.testing.assert_allclose(jnp.sum(jnp.square(residuals[0]), axis=-1), energy, rtol=1e-12)
    hinges = Mesh(points, faces).hinges
    energy = surface_bending_energy(moved, points, hinges, reduction="none", implementation=implementation)
    residuals, valid = bending_residuals(moved[None], points[None], hinges)
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(jnp.square(residuals[0]), energy, rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("implementation", [None, "jax"])
def test_a_template_lands_on_a_stretched_target(implementation):
    """The target is the template under an affine stretch, which the lattice can represent: the
    registered vertices end on the target surface (they started up to 0.2 away)."""
    points, faces = _sphere()
    template = points * 0.9
    target = points * jnp.asarray([1.2, 0.9, 1.0])
    assert _distances(template, target, faces).max() > 0.15
    lattice = register_surface(template, faces, target, faces, RESOLUTION, **BOX, implementation=implementation)
    moved = free_form_deform_points(template, lattice, **BOX)
    # Point-to-plane residuals vanish on the target's face planes; the Tikhonov term (1e-10)
    # leaves a bias of a few 1e-6.
    assert _distances(moved, target, faces).max() < 1e-4


def test_float32_registration_under_x64():
    """float32 surfaces while jax_enable_x64 is on (as in these tests): the default dogleg solver
    used to fail with a TypeError inside optimistix (its step norms started as float64)."""
    points, faces = _sphere()
    template, target = (points * 0.9).astype(jnp.float32), (points * jnp.asarray([1.2, 0.9, 1.0])).astype(jnp.float32)
    lattice = register_surface(template, faces, target, faces, RESOLUTION, **BOX)
    assert lattice.dtype == jnp.float32
    moved = free_form_deform_points(template, lattice, **BOX)
    # From 0.2 away to the float32 stopping tolerance (1e-5 of the lattice) and the Tikhonov
    # bias (1e-6 in float32): a few 1e-4.
    assert _distances(moved.astype(jnp.float64), target.astype(jnp.float64), faces).max() < 1e-3


def test_regularisers_and_their_effect(monkeypatch):
    points, faces = _sphere()
    template, target = points * 0.9, points
    free = free_form_deform_points(template, register_surface(template, faces, target, faces, RESOLUTION, **BOX), **BOX)
    # Bending is blind to a uniform scaling: the fit is the same.
    bent = free_form_deform_points(template, register_surface(template, faces, target, faces, RESOLUTION, bending_weight=1e-2, **BOX), **BOX)
    assert _distances(bent, target, faces).max() < 1e-4
    # Strain resists the stretch from 0.9 to 1: the template stays short of the target, more so
    # for a larger weight.
    # A positive weight is traced: the second solve reuses the first's program (no new trace).
    traces = []
    monkeypatch.setattr(registration_module, "registration_residuals", lambda *a, **k: traces.append(k) or registration_residuals(*a, **k))
    radii, lattices, traced = [], [], []
    for weight in (1e-4, 1e-2):
        lattices.append(register_surface(template, faces, target, faces, RESOLUTION, strain_weight=weight, **BOX))
        radii.append(float(jnp.mean(jnp.linalg.norm(free_form_deform_points(template, lattices[-1], **BOX), axis=-1))))
        traced.append(len(traces))
    assert traced[1] == traced[0] <= 1
    free_radius = float(jnp.mean(jnp.linalg.norm(free, axis=-1)))
    assert 0.9 < radii[1] < 0.97 < radii[0] < free_radius
    # At 1e-2 the strain residuals stay large at the optimum, where Gauss-Newton
    # (optimistix.Dogleg) converged linearly and ran out of the default 200 steps (646 were
    # needed). The default solver converged (no RuntimeError above), to a stationary point of
    # the objective: a plain Newton step from it (the loss's Hessian and gradient, solved densely
    # here) is below 1e-6 of the lattice (Dogleg's point after 200 steps: 1.4e-2, after 400:
    # 2.8e-4).
    cells = Mesh(template, faces).cells
    residuals = registration_residuals(
        cells, cells, None, None, **BOX, basis="bernstein", strain_weight=1e-2, bending_weight=0.0, regularization=1e-10, implementation="jax", brute_force=True
    )

    def loss(lat):
        return 0.5 * jnp.sum(jnp.square(residuals(lat, (template, target))))

    size = lattices[1].size
    hessian, gradient = np.asarray(jax.hessian(loss)(lattices[1])).reshape(size, size), np.asarray(jax.grad(loss)(lattices[1])).reshape(size)
    assert np.abs(np.linalg.lstsq(hessian, -gradient, rcond=None)[0]).max() < 1e-6


def test_solution_is_differentiable_and_batches():
    """Implicit adjoint: d/ds of the registered mean radius onto a target scaled by s, against
    central differences of the registration itself; vmap over targets gives the single fits."""
    points, faces = _sphere()
    template = points * 0.9

    def mean_radius(scale):
        lattice = register_surface(template, faces, points * scale, faces, RESOLUTION, **BOX)
        return jnp.mean(jnp.linalg.norm(free_form_deform_points(template, lattice, **BOX), axis=-1))

    gradient = jax.grad(mean_radius)(1.0)
    # The solver stops within its tolerance (1e-8) and nearest faces may switch within the step:
    # a step of 1e-3 keeps both effects near 1e-5, below the comparison's 1e-3.
    step = 1e-3
    finite_difference = (mean_radius(1.0 + step) - mean_radius(1.0 - step)) / (2 * step)
    np.testing.assert_allclose(gradient, finite_difference, rtol=1e-3)
    assert abs(float(gradient) - 1.0) < 0.01  # the registered surface scales with the target

    scales = jnp.asarray([0.95, 1.1])
    batched = jax.vmap(lambda s: register_surface(template, faces, points * s, faces, RESOLUTION, **BOX))(scales)
    for k, scale in enumerate(scales):
        single = register_surface(template, faces, points * scale, faces, RESOLUTION, **BOX)
        # Point-to-plane residuals leave the vertices free to slide along the target by about
        # the tolerance's effect (1e-5 here): both fits land on the target, at nearly one place.
        moved = free_form_deform_points(template, batched[k], **BOX)
        assert _distances(moved, points * scale, faces).max() < 1e-4
        np.testing.assert_allclose(moved, free_form_deform_points(template, single, **BOX), atol=1e-4)


def test_errors():
    points, faces = _sphere()
    with pytest.raises(ValueError, match="resolution must have 3 entries"):
        register_surface(points, faces, points, faces, (3, 3), **BOX)
    with pytest.raises(ValueError, match="strain_weight must be a finite real >= 0"):
        register_surface(points, faces, points, faces, RESOLUTION, strain_weight=-1.0, **BOX)
    with pytest.raises(ValueError, match="bending_weight must be a finite real >= 0"):
        register_surface(points, faces, points, faces, RESOLUTION, bending_weight=float("inf"), **BOX)
    with pytest.raises(TypeError, match="must share a dtype"):
        register_surface(points, faces, points.astype(jnp.float32), faces, RESOLUTION, **BOX)
    with pytest.raises(ValueError, match="triangle surfaces in 3-D"):
        register_surface(points[:, :2], faces, points[:, :2], faces, RESOLUTION, **BOX)


def test_a_registration_that_does_not_finish_is_reported():
    points, faces = _sphere()
    stretched = points * jnp.array([1.3, 1.0, 0.8])
    with pytest.raises(RuntimeError, match=r"register_surface: the least-squares solve did not succeed within max_steps=2"):
        register_surface(points, faces, stretched, faces, RESOLUTION, max_steps=2, **BOX)
    solution = register_surface(points, faces, stretched, faces, RESOLUTION, max_steps=2, return_solution=True, **BOX)
    assert solution.result == optx.RESULTS.nonlinear_max_steps_reached
    # Given the steps it needs, the same problem succeeds (the failure above is the budget's).
    full = register_surface(points, faces, stretched, faces, RESOLUTION, return_solution=True, **BOX)
    assert full.result == optx.RESULTS.successful
