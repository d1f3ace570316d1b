"""Block Jacobi-PCG (``jacobi_pcg``) and its lineax solver (``JacobiPCG``): values, stopping rule,
failure reporting, implicit differentiation, ``jvp`` and ``vmap``."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from geomjax.linalg import JacobiPCG, jacobi_pcg
from geomjax.linalg._pcg import FLOOR_FACTOR


def _helmholtz_1d(num_rows, stiffness_weight, dtype=jnp.float64):
    """``I + w L`` with ``L`` the 1D Neumann Laplacian: SPD, condition ~ 4w."""
    laplacian = 2 * np.eye(num_rows) - np.eye(num_rows, k=1) - np.eye(num_rows, k=-1)
    laplacian[0, 0] = laplacian[-1, -1] = 1
    return jnp.asarray(np.eye(num_rows) + stiffness_weight * laplacian, dtype)


def _solve(matrix, rhs, guess=None, rtol=1e-10, max_steps=500):
    guess = jnp.zeros_like(rhs) if guess is None else guess
    return jax.jit(lambda m, b, g: jacobi_pcg(lambda x: m @ x, b, 1 / jnp.diagonal(m), g, rtol=rtol, max_steps=max_steps))(
        matrix, rhs, guess
    )


def test_columns_solved_to_the_two_norm_tolerance():
    rng = np.random.default_rng(0)
    factor = rng.normal(size=(40, 40))
    matrix = jnp.asarray(factor @ factor.T / 40 + np.diag(rng.uniform(0.5, 5.0, 40)))
    # Columns of very different sizes, and an all-zero one: each has its own recurrence.
    rhs = jnp.asarray(rng.normal(size=(40, 3)) * np.array([1e-8, 1.0, 0.0]))
    result = _solve(matrix, rhs)
    assert bool(result.converged) and not bool(result.breakdown)
    exact = np.linalg.solve(np.asarray(matrix), np.asarray(rhs))
    np.testing.assert_allclose(result.solution[:, 1], exact[:, 1], rtol=1e-8)
    np.testing.assert_allclose(result.solution[:, 0], exact[:, 0], rtol=1e-8)
    assert np.array_equal(np.asarray(result.solution[:, 2]), np.zeros(40))
    residual = np.linalg.norm(np.asarray(rhs) - np.asarray(matrix) @ np.asarray(result.solution))
    assert residual <= 1e-10 * np.linalg.norm(np.asarray(rhs))


def test_sparse_right_hand_side_converges_to_the_right_answer():
    """lineax.CG(rtol, atol=0) stops after one step here (per-element scale |b_i| = 0 off the
    spike); the 2-norm rule iterates until the whole field is solved."""
    matrix = _helmholtz_1d(300, 400.0)
    rhs = jnp.zeros((300, 1)).at[150, 0].set(1.0)
    result = _solve(matrix, rhs)
    assert bool(result.converged) and int(result.num_steps) > 10
    np.testing.assert_allclose(result.solution, np.linalg.solve(np.asarray(matrix), np.asarray(rhs)), rtol=1e-8, atol=1e-14)


def test_zero_rhs_and_exact_guess_need_no_iteration():
    matrix = _helmholtz_1d(50, 10.0)
    zero = _solve(matrix, jnp.zeros((50, 2)))
    assert int(zero.num_steps) == 0 and bool(zero.converged)
    assert np.array_equal(np.asarray(zero.solution), np.zeros((50, 2)))
    # A constant is an eigenvector of I + wL with eigenvalue 1: the guess is exact.
    exact = _solve(matrix, jnp.ones((50, 2)), guess=jnp.ones((50, 2)))
    assert int(exact.num_steps) == 0 and np.array_equal(np.asarray(exact.solution), np.ones((50, 2)))


def test_initial_guess_is_dropped_when_worse_than_zero():
    matrix = _helmholtz_1d(200, 100.0)
    rhs = jnp.asarray(np.random.default_rng(1).normal(size=(200, 2)))
    from_zero = _solve(matrix, rhs)
    from_bad_guess = _solve(matrix, rhs, guess=1e6 * jnp.ones_like(rhs))
    assert int(from_bad_guess.num_steps) == int(from_zero.num_steps)
    np.testing.assert_array_equal(from_bad_guess.solution, from_zero.solution)
    good_guess = _solve(matrix, rhs, guess=from_zero.solution * (1 + 1e-6))
    assert int(good_guess.num_steps) < int(from_zero.num_steps)


def test_failures_are_flagged():
    matrix = _helmholtz_1d(100, 100.0)
    rhs = jnp.asarray(np.random.default_rng(2).normal(size=(100, 1)))
    capped = _solve(matrix, rhs, max_steps=3)
    assert not bool(capped.converged) and not bool(capped.breakdown) and int(capped.num_steps) == 3
    # Positive diagonal (a valid preconditioner) but an indefinite 2x2 block: eigenvalues 4 and -2.
    indefinite = jnp.eye(100).at[10, 11].set(3.0).at[11, 10].set(3.0)
    broken = _solve(indefinite, rhs)
    assert bool(broken.breakdown) and not bool(broken.converged)
    negative_preconditioner = jax.jit(
        lambda b: jacobi_pcg(lambda x: matrix @ x, b, -1 / jnp.diagonal(matrix), jnp.zeros_like(b), rtol=1e-8, max_steps=50)
    )(rhs)
    assert bool(negative_preconditioner.breakdown)
    not_finite = _solve(matrix, rhs.at[3, 0].set(jnp.nan))
    assert bool(not_finite.breakdown) and not bool(not_finite.converged)


def test_float32_convergence_is_on_the_true_residual():
    """Convergence is declared on ``b - A x`` recomputed with the operator, not on the recurrence
    residual, which drifts below it in float32 on stiff systems: here the recurrence meets the
    tolerance first, the true residual does not, and the iteration restarts from it."""
    matrix = _helmholtz_1d(2000, 2000.0, jnp.float32)
    rhs = jnp.asarray(np.random.default_rng(3).normal(size=(2000, 3)), jnp.float32)
    matvecs = [0]

    def matvec(x):
        jax.debug.callback(lambda: matvecs.__setitem__(0, matvecs[0] + 1))
        return matrix @ x

    result = jax.jit(lambda b: jacobi_pcg(matvec, b, 1 / jnp.diagonal(matrix), jnp.zeros_like(b), rtol=1e-4, max_steps=3000))(rhs)
    assert bool(result.converged) and result.solution.dtype == jnp.float32 and not bool(result.at_rounding_floor)
    # One initial residual, one product per iteration, one true residual per (re)start: > 1 start.
    assert matvecs[0] - int(result.num_steps) - 1 >= 2
    true_residual = np.asarray(rhs, np.float64) - np.asarray(matrix, np.float64) @ np.asarray(result.solution, np.float64)
    assert np.linalg.norm(true_residual) <= 1e-4 * np.linalg.norm(np.asarray(rhs, np.float64))


def test_float32_accepts_the_rounding_floor_and_no_more():
    """A tolerance below what float32 can hold: the solve stops at the rounding floor (the residual
    of the exact solution rounded to float32 is about 0.27 eps ||D x||), not after max_steps, and
    flags it; the answer is the exact solution to float32's accuracy for this conditioning."""
    matrix = _helmholtz_1d(2000, 2000.0, jnp.float32)
    rhs = jnp.asarray(np.random.default_rng(5).normal(size=(2000, 2)), jnp.float32)
    exact = np.linalg.solve(np.asarray(matrix, np.float64), np.asarray(rhs, np.float64))
    rounded_residual = np.linalg.norm(np.asarray(rhs, np.float64) - np.asarray(matrix, np.float64) @ exact.astype(np.float32))
    eps = float(jnp.finfo(jnp.float32).eps)
    floor = eps * np.linalg.norm(np.diagonal(np.asarray(matrix, np.float64))[:, None] * exact)
    assert rounded_residual > 1e-9 * np.linalg.norm(np.asarray(rhs))  # far above rtol: the floor binds
    result = _solve(matrix, rhs, rtol=1e-9, max_steps=3000)
    assert bool(result.converged) and bool(result.at_rounding_floor) and not bool(result.breakdown)
    true_residual = np.asarray(rhs, np.float64) - np.asarray(matrix, np.float64) @ np.asarray(result.solution, np.float64)
    assert np.linalg.norm(true_residual) <= FLOOR_FACTOR * floor
    # Forward error: that residual through the inverse (its smallest eigenvalue is 1).
    assert np.linalg.norm(np.asarray(result.solution, np.float64) - exact) <= FLOOR_FACTOR * floor
    # In float64 the same tolerance is met outright, without the floor.
    double = _solve(matrix.astype(jnp.float64), rhs.astype(jnp.float64), rtol=1e-9, max_steps=3000)
    assert bool(double.converged) and not bool(double.at_rounding_floor)


def test_vmap_matches_a_loop_and_freezes_finished_items():
    matrix = _helmholtz_1d(80, 50.0)
    rhs = jnp.asarray(np.random.default_rng(4).normal(size=(3, 80, 2))).at[1].set(0.0)
    solve = jax.vmap(lambda b: jacobi_pcg(lambda x: matrix @ x, b, 1 / jnp.diagonal(matrix), jnp.zeros_like(b), rtol=1e-10, max_steps=500))
    batched = solve(rhs)
    for item in range(3):
        single = _solve(matrix, rhs[item])
        np.testing.assert_allclose(batched.solution[item], single.solution, rtol=1e-13, atol=1e-15)
        assert int(batched.num_steps[item]) == int(single.num_steps)


def test_the_iteration_itself_is_not_reverse_differentiable():
    """Gradients must come from implicit differentiation: CG runs in a while loop."""
    matrix = _helmholtz_1d(10, 1.0)
    with pytest.raises(ValueError, match="[Rr]everse-mode differentiation does not work"):
        jax.grad(lambda b: jnp.sum(jacobi_pcg(lambda x: matrix @ x, b, 1 / jnp.diagonal(matrix), b, rtol=1e-8, max_steps=50).solution))(
            jnp.ones((10, 1))
        )


# ---------------------------------------------------------------------------------------------
# The lineax solver.


def _parametrised_solve(theta, rhs, max_steps=200, guess=None):
    """Solve ``(diag(theta) + 3 L) x = rhs`` with lineax and JacobiPCG."""
    laplacian = _helmholtz_1d(theta.shape[0], 1.0) - jnp.eye(theta.shape[0])

    def matvec(x):
        return theta[:, None] * x + 3.0 * (laplacian @ x)

    operator = lx.FunctionLinearOperator(matvec, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), tags=lx.positive_semidefinite_tag)
    options = {"inverse_diagonal": jax.lax.stop_gradient(1 / (theta + 3.0 * jnp.diagonal(laplacian)))}
    if guess is not None:
        options["y0"] = guess
    return lx.linear_solve(operator, rhs, JacobiPCG(1e-12, max_steps, "test solve"), options=options).value


def _dense_solve(theta, rhs):
    laplacian = _helmholtz_1d(theta.shape[0], 1.0) - jnp.eye(theta.shape[0])
    return jnp.linalg.solve(jnp.diag(theta) + 3.0 * laplacian, rhs)


def _problem():
    rng = np.random.default_rng(5)
    return jnp.asarray(rng.uniform(0.5, 2.0, 30)), jnp.asarray(rng.normal(size=(30, 2)))


def test_lineax_solver_gradients_are_implicit_and_match_dense_autodiff():
    theta, rhs = _problem()

    def loss(solve):
        return lambda t, b: jnp.sum(jnp.sin(solve(t, b)))

    grads = jax.jit(jax.grad(loss(_parametrised_solve), argnums=(0, 1)))(theta, rhs)
    expected = jax.grad(loss(_dense_solve), argnums=(0, 1))(theta, rhs)
    for got, want in zip(grads, expected):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    # One forward and one transposed (adjoint) solve; the CG loop itself is never differentiated.
    jaxpr = str(jax.make_jaxpr(jax.grad(loss(_parametrised_solve), argnums=(0, 1)))(theta, rhs))
    assert jaxpr.count("linear_solve") >= 2

    tangents = (jnp.asarray(np.random.default_rng(6).normal(size=30)), jnp.ones_like(rhs))
    _, jvp = jax.jit(lambda t, b: jax.jvp(_parametrised_solve, (t, b), tangents))(theta, rhs)
    _, jvp_dense = jax.jvp(_dense_solve, (theta, rhs), tangents)
    np.testing.assert_allclose(jvp, jvp_dense, rtol=1e-9, atol=1e-12)

    thetas = jnp.stack([theta, 2 * theta])
    batched = jax.jit(jax.vmap(_parametrised_solve, in_axes=(0, None)))(thetas, rhs)
    np.testing.assert_allclose(batched, jax.vmap(_dense_solve, in_axes=(0, None))(thetas, rhs), rtol=1e-10)


def test_lineax_solver_raises_in_forward_and_adjoint_solves():
    # equinox.error_if raises JaxRuntimeError on an executable's first run and, from JAX's cached
    # C++ dispatch path, ValueError("INTERNAL: ...") on later runs; both carry the message.
    errors = (RuntimeError, ValueError)
    theta, rhs = _problem()
    with pytest.raises(errors, match="test solve: the Jacobi-PCG solve did not converge within 2 iterations"):
        jax.block_until_ready(_parametrised_solve(theta, rhs, max_steps=2))
    # The forward solve is exact from its guess (no iteration), the adjoint solve is not.
    exact = _dense_solve(theta, rhs)
    forward = _parametrised_solve(theta, rhs, max_steps=2, guess=exact)
    np.testing.assert_allclose(forward, exact, rtol=1e-12)
    with pytest.raises(errors, match="did not converge within 2 iterations"):
        jax.block_until_ready(jax.grad(lambda b: jnp.sum(jnp.sin(_parametrised_solve(theta, b, max_steps=2, guess=exact))))(rhs))


def test_lineax_solver_rejects_operators_not_tagged_positive():
    operator = lx.MatrixLinearOperator(jnp.eye(3))
    with pytest.raises(ValueError, match="positive"):
        lx.linear_solve(operator, jnp.ones(3), JacobiPCG(1e-8, 10), options={"inverse_diagonal": jnp.ones(3)})
