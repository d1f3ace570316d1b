"""sobolev_deform_points on Warp: kernels against dense matrices, values and gradients against the
JAX path and the dense reference, vmap, jit, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from geomjax import sobolev_deform_points
from geomjax.linalg import CellStiffness, off_diagonal_entries, simplex_stiffness
from tests.linalg.meshes import MESHES, dense_sobolev, dense_stiffness, grid_triangles

pytest.importorskip("warp")
from warp_ffi.sobolev import stiffness_diagonal, stiffness_product, vertex_incidence  # noqa: E402

LENGTH = 0.3
WARP_MESHES = ["segments-1d", "segments-2d", "segments-3d", "triangles-2d", "triangles-3d", "tetrahedra"]
# See tests/deform/test_sobolev.py: runtime checks inside jit/grad surface as either type.
TRACED_ERRORS = (RuntimeError, ValueError)


def _mesh(name, dtype=jnp.float64):
    points, cells = MESHES[name]()
    return jnp.asarray(points, dtype), jnp.asarray(cells)


def _field(shape, dtype=jnp.float64, seed=0):
    return jnp.asarray(np.random.default_rng(seed).normal(size=shape), dtype)


def _sobolev(points, cells, displacement, implementation="warp", **kwargs):
    return sobolev_deform_points(points, cells, displacement, length_scale=LENGTH, implementation=implementation, **kwargs)


def test_incidence_is_a_stable_sort_of_the_cell_slots():
    cells = jnp.array([[0, 2, 5], [5, 2, 1], [2, 0, 5]], jnp.int32)  # vertices 3, 4 and 6 unreferenced
    offsets, order = vertex_incidence(cells, 7)
    flat = np.asarray(cells).ravel()
    np.testing.assert_array_equal(order, np.argsort(flat, kind="stable"))
    np.testing.assert_array_equal(offsets, np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=7))]))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("mesh", WARP_MESHES)
def test_products_match_the_dense_matrix(mesh, dtype):
    points, cells = _mesh(mesh)
    stiffness, _ = dense_stiffness(points, cells)
    local, _, _ = simplex_stiffness(points, cells)
    entries = off_diagonal_entries(local).astype(dtype)
    cells32 = cells.astype(jnp.int32)
    incidence = vertex_incidence(cells32, points.shape[0])
    x = _field((points.shape[0], points.shape[1]), dtype, seed=1)
    tolerance = {jnp.float32: 2e-5, jnp.float64: 1e-12}[dtype]
    product = stiffness_product(x, entries, cells32, *incidence)
    assert product.dtype == dtype
    np.testing.assert_allclose(product, stiffness @ x.astype(jnp.float64), rtol=0, atol=tolerance * float(jnp.abs(stiffness).max()))
    np.testing.assert_allclose(stiffness_diagonal(entries, cells32, *incidence), jnp.diagonal(stiffness), rtol=tolerance)


def test_chunked_two_thread_product_is_deterministic():
    points, cells = grid_triangles(110, 100)  # 11,000 vertices: several launch chunks
    points, cells = jnp.asarray(points), jnp.asarray(cells, jnp.int32)
    local, _, _ = simplex_stiffness(points, cells)
    incidence = vertex_incidence(cells, points.shape[0])
    x = _field((points.shape[0], 3), seed=2)
    first = stiffness_product(x, off_diagonal_entries(local), cells, *incidence)
    np.testing.assert_array_equal(first, stiffness_product(x, off_diagonal_entries(local), cells, *incidence))
    np.testing.assert_allclose(first, CellStiffness.assemble(local, cells, points.shape[0])(x), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "mesh, dtype", [(m, jnp.float64) for m in WARP_MESHES] + [("segments-2d", jnp.float32), ("tetrahedra", jnp.float32)]
)
def test_values_match_the_jax_path_and_the_dense_solve(mesh, dtype):
    points, cells = _mesh(mesh, dtype)
    points = jnp.concatenate([points, jnp.full((1, points.shape[1]), 5.0, dtype)])  # one isolated vertex
    displacement = _field(points.shape, dtype, seed=3)
    fixed = jnp.zeros(points.shape[0], bool).at[2].set(True)
    # Solved tightly in float64: the two paths may precondition differently (the JAX path picks
    # Jacobi on meshes this easy), so their iterates agree only to the tolerance.
    tight = {"tolerance": 1e-13} if dtype == jnp.float64 else {}
    warp = _sobolev(points, cells, displacement, fixed_points=fixed, **tight)
    assert warp.dtype == dtype and warp.shape == points.shape
    np.testing.assert_allclose(warp, _sobolev(points, cells, displacement, "jax", fixed_points=fixed, **tight), rtol=0,
                               atol={jnp.float32: 2e-6, jnp.float64: 1e-12}[dtype])  # fmt: skip
    if dtype == jnp.float64:
        np.testing.assert_allclose(warp, dense_sobolev(points, cells, displacement, LENGTH, fixed), rtol=1e-8, atol=1e-9)
    np.testing.assert_array_equal(warp[2], points[2])
    np.testing.assert_array_equal(warp[-1], points[-1] + displacement[-1])


@pytest.mark.parametrize("mesh", ["segments-3d", "tetrahedra"])
def test_gradients_match_the_jax_path_also_under_vmap(mesh):
    points, cells = _mesh(mesh)
    batch_points = jnp.stack([points, points * 1.3 + 0.1])
    batch_displacement = _field(batch_points.shape, seed=4)
    fixed = jnp.zeros(batch_points.shape[:2], bool).at[1, 0].set(True)
    weights = _field(batch_points.shape, seed=5)

    def gradient(implementation):
        def loss(p, d, f, w):
            return jnp.sum(w * jnp.sin(_sobolev(p, cells, d, implementation, fixed_points=f, tolerance=1e-13)))

        return jax.jit(jax.vmap(jax.grad(loss, argnums=(0, 1))))

    inputs = (batch_points, batch_displacement, fixed, weights)
    warp, jax_ = gradient("warp")(*inputs), gradient("jax")(*inputs)
    for got, want in zip(warp, jax_):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-11)
    assert float(jnp.abs(warp[0]).max()) > 1e-3

    # Batched input (not vmap) through the public op, and a jit with cells as an argument.
    def batched_loss(p, d, c):
        return jnp.sum(weights * jnp.sin(sobolev_deform_points(p, c, d, length_scale=LENGTH, fixed_points=fixed,
                                                              tolerance=1e-13, implementation="warp")))  # fmt: skip

    batched = jax.jit(jax.grad(batched_loss, argnums=(0, 1)))(batch_points, batch_displacement, cells)
    for got, want in zip(batched, jax_):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-11)


def test_gradients_match_finite_differences():
    points, cells = _mesh("triangles-2d")
    displacement = _field(points.shape, seed=6)
    check_grads(lambda p, d: _sobolev(p, cells, d, tolerance=1e-13), (points, displacement), order=1, modes=("rev",),
                eps=1e-6, atol=1e-6, rtol=1e-6)  # fmt: skip
    # An explicit Warp backend is first order: forward mode names the transform and the way out.
    with pytest.raises(NotImplementedError, match="forward-mode differentiation .*implementation='jax'"):
        jax.jvp(lambda p: _sobolev(p, cells, displacement), (points,), (points,))


def test_float32_gradients_match_the_jax_path():
    points, cells = _mesh("triangles-3d", jnp.float32)
    displacement = _field(points.shape, jnp.float32, seed=7)

    def gradient(implementation):
        return jax.grad(lambda p, d: jnp.sum(_sobolev(p, cells, d, implementation) ** 2), argnums=(0, 1))(points, displacement)

    for got, want in zip(gradient("warp"), gradient("jax")):
        assert got.dtype == jnp.float32
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-4 * float(jnp.abs(want).max()))


def test_failures():
    points, cells = _mesh("triangles-fine")
    displacement = _field(points.shape, seed=8)
    with pytest.raises(RuntimeError, match="did not converge within 1 iterations. Increase max_iterations or relax tolerance"):
        _sobolev(points, cells, displacement, max_iterations=1)
    constant = jnp.ones_like(points)  # solved by the initial guess; the adjoint solve is not
    weights = _field(points.shape, seed=9)
    with pytest.raises(TRACED_ERRORS, match="did not converge within 1 iterations"):
        jax.block_until_ready(jax.grad(lambda p: jnp.sum(weights * _sobolev(p, cells, constant, max_iterations=1)))(points))
    with pytest.raises(ValueError, match="cells must be finite, nondegenerate simplices"):
        _sobolev(points.at[1].set(points[0]), cells, displacement)  # vertices 0 and 1 share a cell
    # Out-of-range indices in traced cells raise, and are clamped before any kernel reads them.
    with pytest.raises(TRACED_ERRORS, match=rf"cells indices must be in \[0, {points.shape[0]}\)"):
        jax.block_until_ready(jax.jit(lambda c: _sobolev(points, c, displacement))(cells.at[3, 1].set(1000)))
