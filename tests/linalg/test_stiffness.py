"""P1 stiffness: local matrices, the two matrix-free products, the host pattern and the uniform mass."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from geomjax.linalg import (
    CellStiffness,
    RowStiffness,
    off_diagonal_entries,
    off_diagonal_pairs,
    referenced_vertices,
    row_pattern,
    simplex_stiffness,
    uniform_lumped_mass,
)

from .meshes import MESHES, dense_stiffness, local_stiffness


@pytest.mark.parametrize("mesh", sorted(MESHES))
def test_local_matrices_and_products_match_an_independent_dense_assembly(mesh):
    points, cells = MESHES[mesh]()
    points, cells = jnp.asarray(points), jnp.asarray(cells)
    local, measures, determinants = jax.jit(simplex_stiffness)(points, cells)
    reference_local, reference_measures = jax.jit(jax.vmap(local_stiffness))(points[cells])
    np.testing.assert_allclose(local, reference_local, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(measures, reference_measures, rtol=1e-12)
    assert bool(jnp.all(determinants > 0))

    stiffness, _ = dense_stiffness(points, cells)
    num_points = points.shape[0]
    x = jnp.asarray(np.random.default_rng(1).normal(size=(num_points, 3)))
    rows = RowStiffness.assemble(local, row_pattern(np.asarray(cells), num_points))
    per_cell = CellStiffness.assemble(local, cells, num_points)
    constant = jnp.full((num_points, 2), 3.7)
    for product in (rows, per_cell):
        value, diagonal, of_constant = jax.jit(lambda p: (p(x), p.diagonal(), p(constant)))(product)
        np.testing.assert_allclose(value, stiffness @ x, rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(diagonal, jnp.diagonal(stiffness), rtol=1e-11, atol=1e-12)
        # Difference form: constants are exact null vectors.
        assert np.array_equal(np.asarray(of_constant), np.zeros((num_points, 2)))


def test_hand_checked_segment_and_right_triangle():
    local, measure, _ = simplex_stiffness(jnp.array([[0.5], [2.5]]), jnp.array([[0, 1]]))
    np.testing.assert_allclose(local[0], [[0.5, -0.5], [-0.5, 0.5]])  # [[1, -1], [-1, 1]] / h
    np.testing.assert_allclose(measure, [2.0])
    # Unit right triangle: cotangent weights 1/2 on the legs' opposite edges, 0 on the hypotenuse's.
    local, measure, _ = simplex_stiffness(jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]), jnp.array([[0, 1, 2]]))
    np.testing.assert_allclose(local[0], [[1.0, -0.5, -0.5], [-0.5, 0.5, 0.0], [-0.5, 0.0, 0.5]], atol=1e-15)
    np.testing.assert_allclose(measure, [0.5])


def test_off_diagonal_order_is_row_major():
    a, b = off_diagonal_pairs(3)
    assert list(zip(a.tolist(), b.tolist())) == [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]
    local = jnp.arange(9.0).reshape(1, 3, 3)
    np.testing.assert_array_equal(off_diagonal_entries(local), [[1, 2, 3, 5, 6, 7]])


@pytest.mark.parametrize("corners", [
    [[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]],  # collinear
    [[0.0, 0.0], [1.0, 0.0], [1.0, 0.0]],  # repeated vertex
    [[0.0, 0.0], [np.nan, 0.0], [0.0, 1.0]],  # not finite
])  # fmt: skip
def test_invalid_cells_get_zero_values_and_finite_gradients(corners):
    points = jnp.array(corners)
    local, measure, determinant = simplex_stiffness(points, jnp.array([[0, 1, 2]]))
    assert not bool(determinant[0] > 0)
    assert np.array_equal(np.asarray(local), np.zeros((1, 3, 3))) and float(measure[0]) == 0.0
    gradient = jax.grad(lambda p: jnp.sum(simplex_stiffness(p, jnp.array([[0, 1, 2]]))[0] ** 2))(points)
    assert bool(jnp.all(jnp.isfinite(gradient)))


def test_row_pattern_cached_on_contents_and_wide_fans_fall_back():
    points, cells = MESHES["triangles-2d"]()
    first = row_pattern(cells, len(points))
    assert row_pattern(cells.copy(), len(points)) is first
    assert row_pattern(cells.astype(np.int32), len(points)) is not first  # dtype is part of the key
    assert first.neighbours.shape == (len(points), 6) and bool(first.referenced.all())
    # Padded slots point at the row itself.
    num_neighbours = np.array([len(set(cells[np.any(cells == i, axis=1)].ravel())) - 1 for i in range(len(points))])
    assert np.array_equal((np.asarray(first.neighbours) != np.arange(len(points))[:, None]).sum(1), num_neighbours)
    # A fan of 200 triangles around vertex 0: padding every row to 201 would be wasteful.
    fan = np.stack([np.zeros(200, int), np.arange(1, 201), np.arange(2, 202)], axis=1)
    assert row_pattern(fan, 202) is None


def test_uniform_mass_and_referenced_vertices():
    points, cells = MESHES["tetrahedra"]()
    points = jnp.concatenate([jnp.asarray(points), jnp.ones((3, 3))])  # three isolated vertices
    _, lumped = dense_stiffness(points, jnp.asarray(cells))
    _, measures, _ = simplex_stiffness(points, jnp.asarray(cells))
    referenced = referenced_vertices(jnp.asarray(cells), points.shape[0])
    assert np.array_equal(np.asarray(referenced), np.arange(points.shape[0]) < points.shape[0] - 3)
    count = jnp.sum(referenced)
    expected = float(jnp.sum(lumped) / (points.shape[0] - 3))
    np.testing.assert_allclose(uniform_lumped_mass(measures, count), expected, rtol=1e-13)
    assert float(uniform_lumped_mass(jnp.zeros((0,)), jnp.asarray(0))) == 1.0
