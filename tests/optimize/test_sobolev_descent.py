"""geomjax.optimize: Sobolev gradient descent as optimistix pieces."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from geomjax import icosphere
from geomjax.optimize import SobolevDescent, SobolevGradientDescent

SPHERE = icosphere(2)  # 162 vertices: above the multilevel preconditioner's exact-solve size
LENGTH_SCALE = 0.2


def _dense_sobolev(points, cells, gradient, length_scale):
    """``r`` with ``(m I + l^2 K) r = m g`` by a dense solve: ``K`` the cotangent Laplacian (the P1
    stiffness of a triangle mesh), ``m`` the mean lumped vertex mass (a third of the adjacent areas)."""
    x, f = np.asarray(points, np.float64), np.asarray(cells)
    n = len(x)
    stiffness, mass = np.zeros((n, n)), np.zeros(n)
    for tri in f:
        corners = x[tri]
        area = 0.5 * np.linalg.norm(np.cross(corners[1] - corners[0], corners[2] - corners[0]))
        mass[tri] += area / 3
        for k in range(3):
            i, j, o = tri[(k + 1) % 3], tri[(k + 2) % 3], tri[k]
            u, v = x[i] - x[o], x[j] - x[o]
            weight = 0.5 * np.dot(u, v) / np.linalg.norm(np.cross(u, v))  # half the cotangent at o
            stiffness[i, j] -= weight
            stiffness[j, i] -= weight
            stiffness[i, i] += weight
            stiffness[j, j] += weight
    m = mass[mass > 0].mean()
    return np.linalg.solve(m * np.eye(n) + length_scale**2 * stiffness, m * np.asarray(gradient, np.float64))


def _misfit(y, target):
    return 0.5 * jnp.sum((y - target) ** 2)


def _ellipsoid(scale=1.0):
    return SPHERE.points * jnp.array([1.3, 1.0, 0.8]) * scale


def test_direction_is_the_sobolev_riesz_representative():
    gradient = jnp.asarray(np.random.default_rng(0).normal(size=SPHERE.points.shape))
    expected = _dense_sobolev(SPHERE.points, SPHERE.cells, gradient, LENGTH_SCALE)
    # Solved to a relative residual of 1e-10 (the operator's condition is ~1e2), and to the
    # descent's default 1e-3, which must stay a descent direction: g . r > 0.
    for tolerance, bound in ((1e-10, 1e-7), (None, 1e-1)):
        options = {} if tolerance is None else {"tolerance": tolerance}
        direction = SobolevDescent(SPHERE.cells, length_scale=LENGTH_SCALE, **options).direction(SPHERE.points, gradient)
        np.testing.assert_allclose(np.asarray(direction), expected, rtol=0, atol=bound * np.abs(expected).max())
        assert float(jnp.sum(gradient * direction)) > 0


def test_minimise_reaches_the_minimiser_and_keeps_fixed_points():
    target = _ellipsoid()
    solver = SobolevGradientDescent(SPHERE.cells, length_scale=LENGTH_SCALE, rtol=1e-9, atol=1e-9)
    solution = optx.minimise(_misfit, solver, SPHERE.points, args=target, max_steps=500)
    assert solution.result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(solution.value), np.asarray(target), rtol=0, atol=1e-6)
    fixed = np.zeros(SPHERE.points.shape[0], bool)
    fixed[:10] = True
    held = SobolevGradientDescent(SPHERE.cells, length_scale=LENGTH_SCALE, rtol=1e-9, atol=1e-9, fixed_points=fixed)
    moved = optx.minimise(_misfit, held, SPHERE.points, args=target, max_steps=500).value
    np.testing.assert_array_equal(np.asarray(moved)[:10], np.asarray(SPHERE.points)[:10])
    np.testing.assert_allclose(np.asarray(moved)[10:], np.asarray(target)[10:], rtol=0, atol=1e-6)


def test_optimum_is_differentiable_and_batches():
    """y*(s) = s T for the misfit to s T: its derivative is T (implicit adjoint, both modes), and
    vmap over designs equals solving each."""
    target = _ellipsoid()
    weights = jnp.asarray(np.random.default_rng(1).normal(size=target.shape))
    solver = SobolevGradientDescent(SPHERE.cells, length_scale=LENGTH_SCALE, rtol=1e-10, atol=1e-10)

    def optimum(scale):
        return optx.minimise(_misfit, solver, SPHERE.points, args=scale * target, max_steps=500, adjoint=optx.ImplicitAdjoint()).value

    expected = float(jnp.sum(weights * target))
    for derivative in (jax.grad, jax.jacfwd):
        np.testing.assert_allclose(float(derivative(lambda s: jnp.sum(weights * optimum(s)))(1.0)), expected, rtol=1e-8)
    scales = jnp.asarray([0.9, 1.2])
    batched = jax.jit(jax.vmap(optimum))(scales)
    for i, scale in enumerate(scales):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(scale * target), rtol=0, atol=1e-6)


def test_bad_cells_are_rejected():
    with pytest.raises(ValueError, match="cells must be a concrete"):
        SobolevDescent(np.zeros((3, 3)), length_scale=0.1)
    with pytest.raises(ValueError, match=r"cells must hold indices in \[0, 5\)"):
        SobolevDescent(np.array([[0, 1, 7]]), length_scale=0.1, num_points=5)
