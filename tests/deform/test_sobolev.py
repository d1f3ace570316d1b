"""sobolev_deform_points (JAX path and the public API): H^1 smoothing of a displacement.

Values and gradients are checked against an independent dense computation
(``tests/linalg/meshes.py``: pseudo-inverse barycentric gradients, dense assembly,
``jnp.linalg.solve`` and its autodiff). Warp parity lives in ``test_sobolev_warp.py``.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import geomjax._dispatch as dispatch
from geomjax import sobolev_deform_points
from geomjax.linalg import row_pattern
from tests.linalg.meshes import MESHES, dense_sobolev, grid_triangles, kuhn_simplices

LENGTH = 0.3
# Runtime checks inside a user's jit or grad (equinox.error_if) raise JaxRuntimeError on an
# executable's first run and, from JAX's cached C++ dispatch path, ValueError("INTERNAL: ...")
# afterwards; both carry the message. Eager calls of the op raise the documented type
# (RuntimeError for non-convergence, ValueError for bad indices and degenerate cells).
TRACED_ERRORS = (RuntimeError, ValueError)


def _mesh(name, dtype=jnp.float64):
    points, cells = MESHES[name]()
    return jnp.asarray(points, dtype), jnp.asarray(cells)


def _field(shape, dtype=jnp.float64, seed=0):
    return jnp.asarray(np.random.default_rng(seed).normal(size=shape), dtype)


def _sobolev(points, cells, displacement, **kwargs):
    kwargs = {"length_scale": LENGTH, "implementation": "jax", **kwargs}
    return sobolev_deform_points(points, cells, displacement, **kwargs)


def test_hand_checked_chain():
    # x = 0, 1, 2 with two unit segments: K = [[1,-1,0],[-1,2,-1],[0,-1,1]], m̄ = 2/3; with l = 1
    # and d = (0, 1, 0), (2/3 I + K) u = (0, 2/3, 0) gives u = (3, 5, 3) / 11.
    points = jnp.array([[0.0], [1.0], [2.0]])
    out = _sobolev(points, jnp.array([[0, 1], [1, 2]]), jnp.array([[0.0], [1.0], [0.0]]), length_scale=1.0)
    np.testing.assert_allclose(out - points, [[3 / 11], [5 / 11], [3 / 11]], rtol=1e-10)


@pytest.mark.parametrize("mesh", sorted(MESHES))
def test_matches_dense_solve(mesh):
    points, cells = _mesh(mesh)
    displacement = _field(points.shape)
    out = _sobolev(points, cells, displacement)
    assert out.shape == points.shape and out.dtype == points.dtype
    np.testing.assert_allclose(out, dense_sobolev(points, cells, displacement, LENGTH), rtol=1e-8, atol=1e-9)


def test_fixed_points_stay_fixed_and_isolated_points_keep_their_displacement():
    points, cells = _mesh("triangles-3d")
    points = jnp.concatenate([points, jnp.array([[3.0, 3.0, 3.0], [4.0, 4.0, 4.0]])])  # isolated 20, 21
    displacement = _field(points.shape, seed=1)
    fixed = jnp.zeros(points.shape[0], bool).at[jnp.array([0, 4, 19, 21])].set(True)
    out = _sobolev(points, cells, displacement, fixed_points=fixed)
    np.testing.assert_array_equal(out[fixed], points[fixed])
    np.testing.assert_array_equal(out[20], points[20] + displacement[20])
    np.testing.assert_allclose(out, dense_sobolev(points, cells, displacement, LENGTH, fixed), rtol=1e-8, atol=1e-9)


def test_constant_displacement_is_reproduced_exactly():
    points, cells = _mesh("tetrahedra")
    displacement = jnp.broadcast_to(jnp.array([0.25, -1.5, 3.0]), points.shape)
    np.testing.assert_array_equal(_sobolev(points, cells, displacement, length_scale=2.0), points + displacement)


def test_sparse_displacement_and_sparse_loss():
    """One displaced vertex and a loss on two vertices: both solves have a sparse right-hand side
    (where lineax.CG with atol=0 stops after one step) and must still be solved exactly."""
    points, cells = grid_triangles(12, 12)
    points, cells = jnp.asarray(points), jnp.asarray(cells)
    displacement = jnp.zeros_like(points).at[70, 1].set(1.0)
    out = _sobolev(points, cells, displacement, length_scale=0.2)
    reference = jax.jit(dense_sobolev, static_argnums=3)(points, cells, displacement, 0.2)
    np.testing.assert_allclose(out, reference, rtol=1e-8, atol=1e-12)
    assert np.count_nonzero(np.abs(np.asarray(out - points)[:, 1]) > 1e-6) > 50  # spread over the mesh

    def loss(deform):
        return lambda p, d: jnp.sum(deform(p, d)[jnp.array([3, 100]), 1])

    grads = jax.jit(jax.grad(loss(lambda p, d: _sobolev(p, cells, d, length_scale=0.2)), argnums=(0, 1)))(points, displacement)
    expected = jax.jit(jax.grad(loss(lambda p, d: dense_sobolev(p, cells, d, 0.2)), argnums=(0, 1)))(points, displacement)
    for got, want in zip(grads, expected):
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize("mesh", ["segments-2d", "tetrahedra"])
def test_gradients_match_dense_autodiff_and_satisfy_the_adjoint_identity(mesh):
    points, cells = _mesh(mesh)
    displacement = _field(points.shape, seed=2)
    fixed = jnp.zeros(points.shape[0], bool).at[1].set(True)
    weights = _field(points.shape, seed=3)

    def ours(p, d):
        return _sobolev(p, cells, d, fixed_points=fixed, tolerance=1e-13)

    tangents = (_field(points.shape, seed=4), _field(points.shape, seed=5))

    @jax.jit
    def derivatives(p, d):
        out, pullback = jax.vjp(ours, p, d)
        _, forward = jax.jvp(ours, (p, d), tangents)
        return pullback(weights * jnp.cos(out)), forward, pullback(weights)

    grads, forward, backward = derivatives(points, displacement)
    dense = jax.jit(jax.grad(lambda p, d: jnp.sum(weights * jnp.sin(dense_sobolev(p, cells, d, LENGTH, fixed))), argnums=(0, 1)))
    for got, want in zip(grads, dense(points, displacement)):
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)
    assert float(jnp.abs(grads[0][2:]).max()) > 1e-3  # the geometry gradient is not trivial
    # <g, J t> == <J^T g, t> with J the Jacobian in (points, displacement).
    np.testing.assert_allclose(jnp.sum(weights * forward), sum(jnp.sum(b * t) for b, t in zip(backward, tangents)), rtol=1e-9)


def test_gradients_match_finite_differences():
    points, cells = _mesh("triangles-2d")
    displacement = _field(points.shape, seed=6)

    def deform(p, d):
        return _sobolev(p, cells, d, tolerance=1e-13)

    check_grads(deform, (points, displacement), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_gradient_is_an_implicit_adjoint_solve():
    points, cells = _mesh("segments-3d")
    displacement = _field(points.shape)
    jaxpr = str(jax.make_jaxpr(jax.grad(lambda p, d: jnp.sum(_sobolev(p, cells, d) ** 2), argnums=(0, 1)))(points, displacement))
    # The forward solve and its transpose (the adjoint solve) are linear_solve primitives; the CG
    # while loop inside them is never differentiated (reverse mode through a while loop is
    # impossible in JAX, so an unrolled CG could not even be built).
    assert jaxpr.count("linear_solve") >= 2


def test_batched_vmap_jit_and_traced_cells_equal_the_loop():
    points, cells = _mesh("triangles-2d")
    batch_points = jnp.stack([points, 1.5 * points, points + 0.25])
    batch_displacement = _field(batch_points.shape, seed=7)
    fixed = jnp.zeros(batch_points.shape[:2], bool).at[1, 3].set(True).at[2, 0].set(True)
    batched = _sobolev(batch_points, cells, batch_displacement, fixed_points=fixed)
    for b in range(3):
        single = _sobolev(batch_points[b], cells, batch_displacement[b], fixed_points=fixed[b])
        np.testing.assert_allclose(batched[b], single, rtol=1e-12, atol=1e-14)
    vmapped = jax.vmap(lambda p, d, f: _sobolev(p, cells, d, fixed_points=f))(batch_points, batch_displacement, fixed)
    np.testing.assert_allclose(vmapped, batched, rtol=1e-12, atol=1e-14)

    # cells as a jit argument: no host pattern, the per-cell (scatter) product and Jacobi instead
    # of the multilevel preconditioner. Different iterates: both solved tightly, to compare.
    tight = _sobolev(batch_points, cells, batch_displacement, fixed_points=fixed, tolerance=1e-13)
    traced = jax.jit(lambda p, c, d: _sobolev(p, c, d, fixed_points=fixed, tolerance=1e-13))(batch_points, cells, batch_displacement)
    np.testing.assert_allclose(traced, tight, rtol=1e-10, atol=1e-12)

    def loss(p, c):
        return jnp.sum(_sobolev(p, c, batch_displacement, tolerance=1e-13) ** 2)

    grad_traced = jax.jit(jax.grad(loss))(batch_points, cells)
    grad_concrete = jax.jit(jax.grad(lambda p: loss(p, cells)))(batch_points)
    np.testing.assert_allclose(grad_traced, grad_concrete, rtol=1e-9, atol=1e-12)


def test_wide_fans_use_the_per_cell_product():
    angles = np.linspace(0, 2 * np.pi, 41)[:-1]
    points = jnp.asarray(np.concatenate([[[0.0, 0.0]], np.stack([np.cos(angles), np.sin(angles)], 1)]))
    rim = np.arange(1, 41)
    cells = jnp.asarray(np.stack([np.zeros(40, int), rim, rim % 40 + 1], 1))
    assert row_pattern(np.asarray(cells), points.shape[0]) is None
    displacement = _field(points.shape, seed=8)
    np.testing.assert_allclose(_sobolev(points, cells, displacement, length_scale=0.1),
                               dense_sobolev(points, cells, displacement, 0.1), rtol=1e-8, atol=1e-10)  # fmt: skip


def test_float32():
    points, cells = _mesh("triangles-3d", jnp.float32)
    displacement = _field(points.shape, jnp.float32, seed=9)
    out = _sobolev(points, cells, displacement)
    assert out.dtype == jnp.float32
    reference = dense_sobolev(points.astype(jnp.float64), cells, displacement.astype(jnp.float64), LENGTH)
    np.testing.assert_allclose(out, reference, rtol=0, atol=3e-6)
    grads = jax.jit(jax.grad(lambda p, d: jnp.sum(_sobolev(p, cells, d) ** 2), argnums=(0, 1)))(points, displacement)
    assert all(g.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(g))) for g in grads)


def test_non_convergence_raises_in_forward_and_adjoint():
    points, cells = _mesh("triangles-fine")
    displacement = _field(points.shape, seed=10)
    with pytest.raises(RuntimeError, match="did not converge within 1 iterations. Increase max_iterations or relax tolerance"):
        _sobolev(points, cells, displacement, max_iterations=1)
    with pytest.raises(TRACED_ERRORS, match="did not converge"):
        jax.block_until_ready(jax.jit(lambda p: _sobolev(p, cells, displacement, max_iterations=1))(points))
    # A constant displacement is solved by the initial guess (no iteration); the adjoint solve
    # for a rough cotangent is not, and must raise rather than return an inexact gradient.
    constant = jnp.ones_like(points)
    np.testing.assert_array_equal(_sobolev(points, cells, constant, max_iterations=1), points + 1)
    weights = _field(points.shape, seed=11)
    with pytest.raises(TRACED_ERRORS, match="did not converge within 1 iterations"):
        jax.block_until_ready(jax.grad(lambda p: jnp.sum(weights * _sobolev(p, cells, constant, max_iterations=1)))(points))
    with pytest.raises(RuntimeError, match="did not converge"):
        _sobolev(points, cells, displacement.at[3, 0].set(jnp.nan))


def test_degenerate_cells():
    points, cells = _mesh("triangles-2d")
    displacement = _field(points.shape)
    collapsed = points.at[5].set(points[0])  # cell (0, 4, 5) gets a repeated point
    with pytest.raises(ValueError, match="cells must be finite, nondegenerate simplices"):
        _sobolev(collapsed, cells, displacement)
    with pytest.raises(ValueError, match="cells must be finite, nondegenerate simplices"):
        _sobolev(points.at[2, 0].set(jnp.inf), cells, displacement)
    with pytest.raises(TRACED_ERRORS, match="cells must be finite, nondegenerate simplices"):
        jax.block_until_ready(jax.jit(lambda p: _sobolev(p, cells, displacement))(collapsed))
    # length_scale = 0 short-circuits before any assembly: degenerate cells are accepted.
    fixed = jnp.zeros(points.shape[0], bool).at[5].set(True)
    out = _sobolev(collapsed, cells, displacement, length_scale=0.0, fixed_points=fixed)
    np.testing.assert_array_equal(out, collapsed + jnp.where(fixed[:, None], 0.0, displacement))


def test_index_range():
    points, cells = _mesh("segments-2d")
    displacement = _field(points.shape)
    with pytest.raises(ValueError, match=r"cells indices must be in \[0, 9\)"):
        _sobolev(points, cells.at[2, 1].set(9), displacement)
    with pytest.raises(ValueError, match=r"cells indices must be in \[0, 9\)"):
        _sobolev(points, cells.at[0, 0].set(-1), displacement)
    with pytest.raises(TRACED_ERRORS, match=r"cells indices must be in \[0, 9\)"):
        jax.block_until_ready(jax.jit(lambda c: _sobolev(points, c, displacement))(cells.at[2, 1].set(9)))


def test_empty_inputs():
    empty = jnp.zeros((0, 3))
    np.testing.assert_array_equal(_sobolev(empty, jnp.zeros((0, 3), jnp.int32), empty), empty)
    # No cells: every point is isolated and keeps its displacement; gradients are defined.
    points, displacement = _field((5, 3)), _field((5, 3), seed=1)
    no_cells = jnp.zeros((0, 2), jnp.int64)
    np.testing.assert_array_equal(_sobolev(points, no_cells, displacement), points + displacement)
    grads = jax.grad(lambda p, d: jnp.sum(_sobolev(p, no_cells, d) ** 2), argnums=(0, 1))(points, displacement)
    np.testing.assert_allclose(grads[1], 2 * (points + displacement))
    batch = jnp.zeros((0, 4, 2))
    assert _sobolev(batch, jnp.array([[0, 1], [2, 3]]), batch).shape == (0, 4, 2)


def test_defaults_and_dispatch(monkeypatch):
    points, cells = _mesh("segments-1d", jnp.float32)
    displacement = _field(points.shape, jnp.float32)
    jax_result = _sobolev(points, cells, displacement)
    np.testing.assert_array_equal(sobolev_deform_points(points, cells, displacement, length_scale=LENGTH, implementation="torch"), jax_result)
    # Default tolerance 1e-6 in float32: within a few ulps of the dense float64 solution.
    reference = dense_sobolev(points.astype(jnp.float64), cells, displacement.astype(jnp.float64), LENGTH)
    np.testing.assert_allclose(jax_result, reference, atol=2e-6)
    monkeypatch.setattr(dispatch, "warp_available", lambda: False)
    np.testing.assert_array_equal(sobolev_deform_points(points, cells, displacement, length_scale=LENGTH), jax_result)
    with pytest.raises(ImportError, match="warp-lang"):
        sobolev_deform_points(points, cells, displacement, length_scale=LENGTH, implementation="warp")


def test_bad_input_errors():
    points, cells = _mesh("triangles-2d")
    displacement = _field(points.shape)
    call = sobolev_deform_points
    cases = [
        (TypeError, "points", lambda: call(points.astype(jnp.int32), cells, displacement, length_scale=0.1)),
        (TypeError, "displacement", lambda: call(points, cells, displacement.astype(jnp.float32), length_scale=0.1)),
        (TypeError, "cells", lambda: call(points, cells.astype(jnp.float64), displacement, length_scale=0.1)),
        (TypeError, "cells", lambda: call(points, cells.astype(jnp.int16), displacement, length_scale=0.1)),
        (TypeError, "fixed_points", lambda: call(points, cells, displacement, length_scale=0.1, fixed_points=jnp.zeros(20, jnp.int32))),
        (TypeError, "fixed_points", lambda: call(points, cells, displacement, length_scale=0.1, fixed_points=jnp.zeros(20))),
        (TypeError, "length_scale", lambda: call(points, cells, displacement, length_scale=True)),
        (TypeError, "length_scale", lambda: call(points, cells, displacement, length_scale="1")),
        (TypeError, "max_iterations", lambda: call(points, cells, displacement, length_scale=0.1, max_iterations=10.0)),
        (TypeError, "max_iterations", lambda: call(points, cells, displacement, length_scale=0.1, max_iterations=True)),
        (TypeError, "tolerance", lambda: call(points, cells, displacement, length_scale=0.1, tolerance=False)),
        (ValueError, "displacement", lambda: call(points, cells, displacement[:-1], length_scale=0.1)),
        (ValueError, "points", lambda: call(points[0], cells, displacement[0], length_scale=0.1)),
        (ValueError, "cells", lambda: call(points, cells[0], displacement, length_scale=0.1)),
        (ValueError, "V >= 2", lambda: call(points, cells[:, :1], displacement, length_scale=0.1)),
        (ValueError, "need D >= 3", lambda: call(points, jnp.zeros((1, 4), jnp.int32), displacement, length_scale=0.1)),
        (ValueError, "fixed_points", lambda: call(points, cells, displacement, length_scale=0.1, fixed_points=jnp.zeros(19, bool))),
        (ValueError, "fixed_points", lambda: call(points, cells, displacement, length_scale=0.1, fixed_points=jnp.zeros((1, 20), bool))),
        (ValueError, "length_scale", lambda: call(points, cells, displacement, length_scale=-0.1)),
        (ValueError, "length_scale", lambda: call(points, cells, displacement, length_scale=float("nan"))),
        (ValueError, "length_scale", lambda: call(points.astype(jnp.float32), cells, displacement.astype(jnp.float32), length_scale=1e20)),
        (ValueError, "max_iterations", lambda: call(points, cells, displacement, length_scale=0.1, max_iterations=0)),
        (ValueError, "tolerance", lambda: call(points, cells, displacement, length_scale=0.1, tolerance=0.0)),
        (ValueError, "tolerance", lambda: call(points, cells, displacement, length_scale=0.1, tolerance=float("inf"))),
        (ValueError, "exactly the shape", lambda: call(points[None], cells, displacement, length_scale=0.1)),
        (KeyError, "implementation", lambda: call(points, cells, displacement, length_scale=0.1, implementation="cuda")),
    ]
    for error, message, thunk in cases:
        with pytest.raises(error, match=message):
            thunk()


def test_higher_simplices_are_jax_only():
    points, cells = kuhn_simplices(1, 4)
    with pytest.raises(ValueError, match="implementation='warp' supports segments, triangles and tetrahedra"):
        sobolev_deform_points(jnp.asarray(points), jnp.asarray(cells), jnp.zeros(points.shape), length_scale=0.1, implementation="warp")


@pytest.mark.parametrize("implementation", ["jax", "warp"])
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    num_points=st.integers(0, 5),
    dim=st.integers(1, 3),
    cells=st.lists(st.lists(st.integers(-2, 6), min_size=2, max_size=3), max_size=4),
    dtype=st.sampled_from([jnp.float32, jnp.float64, jnp.int32]),
    fill=st.sampled_from([0.0, 1.0, np.nan, np.inf]),
    length_scale=st.sampled_from([0.0, 0.5, -1.0, np.nan, True]),
)
def test_bad_input_never_crashes(implementation, num_points, dim, cells, dtype, fill, length_scale):
    """Random malformed arguments either run or raise a documented exception; out-of-range cells
    never reach a kernel."""
    width = len(cells[0]) if cells else 2
    cells = jnp.asarray([c[:width] + [0] * (width - len(c)) for c in cells] or np.zeros((0, width)), jnp.int32)
    points = jax.device_put(np.random.default_rng(num_points).normal(size=(num_points, dim)).astype(dtype))
    if num_points:
        points = points.at[0, 0].set(fill) if dtype != jnp.int32 else points
    try:
        out = sobolev_deform_points(points, cells, points, length_scale=length_scale, implementation=implementation)
    except (TypeError, ValueError, RuntimeError):
        return
    assert out.shape == points.shape
