"""The six deformation energies: JAX path (the specification), validation and semantics."""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import geomjax._dispatch as dispatch
from geomjax import (
    closed_surface_volume_energy,
    simplex_inversion_energy,
    simplex_measure_energy,
    simplex_strain_energy,
    surface_bending_energy,
    total_measure_energy,
)

SIMPLEX_ENERGIES = (simplex_strain_energy, simplex_measure_energy, total_measure_energy, simplex_inversion_energy)
PER_CELL_ENERGIES = (simplex_strain_energy, simplex_measure_energy, simplex_inversion_energy)

# A cube split into six positively oriented tetrahedra around its main diagonal, and an
# octahedron (a closed, outward-oriented surface).
CUBE_POINTS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
CUBE_TETS = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
OCTAHEDRON_POINTS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
OCTAHEDRON_FACES = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def hinges_of(faces: np.ndarray) -> np.ndarray:
    """Interior hinges (i, j, k, l): faces (i, j, k) and (j, i, l), one row per undirected edge."""
    opposite = {}
    for a, b, c in faces:
        for i, j, k in ((a, b, c), (b, c, a), (c, a, b)):
            opposite[i, j] = k
    return np.array([(i, j, k, opposite[j, i]) for (i, j), k in opposite.items() if i < j and (j, i) in opposite])


OCTAHEDRON_HINGES = hinges_of(OCTAHEDRON_FACES)


def rng_array(seed, shape, scale=1.0, dtype=jnp.float64):
    return jnp.asarray(scale * np.random.default_rng(seed).normal(size=shape), dtype)


def random_rotation(seed, dims):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(dims, dims)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def jax_energy(energy, *args, **kwargs):
    return energy(*args, implementation="jax", **kwargs)


def deformed_cube(seed=0, amount=0.1, dtype=jnp.float64):
    rest = jnp.asarray(CUBE_POINTS, dtype)
    return rest + rng_array(seed, rest.shape, amount, dtype), rest, jnp.asarray(CUBE_TETS)


def deformed_octahedron(seed=0, amount=0.1, dtype=jnp.float64):
    rest = jnp.asarray(OCTAHEDRON_POINTS, dtype)
    return rest + rng_array(seed, rest.shape, amount, dtype), rest


# ------------------------------------------------------------------------------------------
# Hand-checked values on single cells


def test_segment_values():
    rest = jnp.array([[0.0], [2.0]])
    cells = jnp.array([[0, 1]])
    stretched, reflected = jnp.array([[0.0], [3.0]]), jnp.array([[0.0], [-3.0]])
    eps = (1.5**2 - 1) / 2  # 1x1 strain: no deviatoric part, so W = V0 (lambda/2 + mu) eps^2
    for current in (stretched, reflected):
        np.testing.assert_allclose(jax_energy(simplex_strain_energy, current, rest, cells, lame_lambda=0.6, shear_modulus=0.8),
                                   2 * (0.3 + 0.8) * eps**2, rtol=1e-14)
    np.testing.assert_allclose(jax_energy(simplex_measure_energy, stretched, rest, cells), 0.5 * 2 * 0.5**2, rtol=1e-14)
    np.testing.assert_allclose(jax_energy(simplex_measure_energy, reflected, rest, cells), 0.5 * 2 * 2.5**2, rtol=1e-14)
    assert float(jax_energy(simplex_inversion_energy, stretched, rest, cells)) == 0.0
    np.testing.assert_allclose(jax_energy(simplex_inversion_energy, reflected, rest, cells, minimum_jacobian=0.5),
                               0.5 * 2 * 2.0**2, rtol=1e-14)


def test_triangle_and_tetrahedron_values():
    triangle = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    sx, sy = 1.2, 0.9
    current = triangle * jnp.array([sx, sy])
    ex, ey = (sx**2 - 1) / 2, (sy**2 - 1) / 2
    lam, mu = 0.7, 1.3
    expected = 0.5 * (mu * (ex**2 + ey**2) + lam / 2 * (ex + ey) ** 2)
    got = jax_energy(simplex_strain_energy, current, triangle, jnp.array([[0, 1, 2]]), lame_lambda=lam, shear_modulus=mu)
    np.testing.assert_allclose(got, expected, rtol=1e-13)
    np.testing.assert_allclose(jax_energy(simplex_measure_energy, current, triangle, jnp.array([[0, 1, 2]]), target_ratio=0.5),
                               0.5 * 0.5 * (sx * sy - 0.5) ** 2, rtol=1e-13)

    tet = jnp.asarray(CUBE_POINTS[[0, 4, 2, 1]])
    cells = jnp.array([[0, 1, 2, 3]])
    s = 1.3
    eps = (s**2 - 1) / 2
    expected = (1 / 6) * (mu * 3 * eps**2 + lam / 2 * (3 * eps) ** 2)
    np.testing.assert_allclose(jax_energy(simplex_strain_energy, s * tet, tet, cells, lame_lambda=lam, shear_modulus=mu), expected, rtol=1e-13)
    np.testing.assert_allclose(jax_energy(simplex_measure_energy, s * tet, tet, cells), 0.5 / 6 * (s**3 - 1) ** 2, rtol=1e-13)
    np.testing.assert_allclose(jax_energy(simplex_inversion_energy, -s * tet, tet, cells, minimum_jacobian=0.2),
                               0.5 / 6 * (0.2 + s**3) ** 2, rtol=1e-13)


def test_embedded_cells_use_intrinsic_unsigned_measures():
    rotation = jnp.asarray(random_rotation(1, 3))
    triangle = jnp.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    cells = jnp.array([[0, 1, 2]])
    sx = 1.5
    current = (triangle * jnp.array([sx, 1.0, 1.0])) @ rotation.T + 3.0
    ex = (sx**2 - 1) / 2
    np.testing.assert_allclose(jax_energy(simplex_strain_energy, current, triangle, cells, lame_lambda=1.0, shear_modulus=1.0),
                               1.0 * (ex**2 + 0.5 * ex**2), rtol=1e-13)
    np.testing.assert_allclose(jax_energy(simplex_measure_energy, current, triangle, cells), 0.5 * 1.0 * (sx - 1) ** 2, rtol=1e-13)
    # Unsigned: a mirrored embedded triangle satisfies the target.
    mirrored = triangle * jnp.array([1.0, -1.0, 1.0])
    assert abs(float(jax_energy(simplex_measure_energy, mirrored, triangle, cells))) < 1e-30
    segment = jnp.array([[1.0, 2.0, 3.0], [2.0, 4.0, 5.0]])
    np.testing.assert_allclose(jax_energy(simplex_measure_energy, 0.5 * segment, segment, jnp.array([[0, 1]])),
                               0.5 * 3.0 * 0.25, rtol=1e-13)


def test_total_measure_allows_redistribution():
    square = jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.5, 0.5]])
    cells = jnp.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    moved = square.at[4].set(jnp.array([0.2, 0.7]))
    assert abs(float(jax_energy(total_measure_energy, moved, square, cells))) < 1e-30
    assert float(jax_energy(simplex_measure_energy, moved, square, cells)) > 0.01
    np.testing.assert_allclose(jax_energy(total_measure_energy, 2 * square, square, cells, target_ratio=2.0), 0.5 * 1 * 2.0**2, rtol=1e-14)
    # Local inversions cancel in the signed sum: fold the centre out through an edge.
    folded = square.at[4].set(jnp.array([0.5, -0.25]))
    assert abs(float(jax_energy(total_measure_energy, folded, square, cells))) < 1e-30


def test_bending_values_and_branch_cut():
    hinge = jnp.array([[0, 1, 2, 3]])

    def wings(angle_left, angle_right):
        # Edge along x; each wing at unit distance, angle measured around +x from +y / -y.
        return jnp.array([
            [0.0, 0.0, 0.0], [2.0, 0.0, 0.0],
            [1.0, math.cos(angle_left), math.sin(angle_left)],
            [1.0, -math.cos(angle_right), -math.sin(angle_right)],
        ])  # fmt: skip

    rest = wings(0.0, 0.0)
    assert float(jax_energy(surface_bending_energy, rest, rest, hinge)) == 0.0
    # l0^2 / (A_L + A_R) = 4 / 2; lifting the right wing by phi bends the hinge by phi.
    for phi in (0.3, -0.7, 2.5):
        np.testing.assert_allclose(jax_energy(surface_bending_energy, wings(0.0, -phi), rest, hinge), 0.5 * 2 * phi**2, rtol=1e-12)
    # Rest folded to +170 degrees, current to -170 degrees: through +-pi the change is 20 degrees.
    near = math.radians(170.0)
    rest_fold, current_fold = wings(0.0, near), wings(0.0, -near)
    got = float(jax_energy(surface_bending_energy, current_fold, rest_fold, hinge))
    np.testing.assert_allclose(got, 0.5 * 2 * math.radians(20.0) ** 2, rtol=1e-10)
    assert got < 0.5  # not ~(2 pi)^2


def test_volume_values():
    rest = jnp.asarray(OCTAHEDRON_POINTS)
    faces = jnp.asarray(OCTAHEDRON_FACES)
    volume = 4 / 3
    np.testing.assert_allclose(jax_energy(closed_surface_volume_energy, 1.5 * rest + 7.0, rest, faces),
                               0.5 * volume * (1.5**3 - 1) ** 2, rtol=1e-13)
    # Either global winding works, and a translated copy has the same volume.
    reversed_faces = faces[:, ::-1]
    np.testing.assert_allclose(jax_energy(closed_surface_volume_energy, 1.5 * rest, rest, reversed_faces, target_ratio=2.0),
                               0.5 * volume * (1.5**3 - 2) ** 2, rtol=1e-13)
    assert abs(float(jax_energy(closed_surface_volume_energy, rest + 1e6, rest, faces))) < 1e-20


# ------------------------------------------------------------------------------------------
# Invariants


@pytest.mark.parametrize("dims, vertices", [(1, 2), (2, 2), (2, 3), (3, 2), (3, 3), (3, 4), (4, 3)])
def test_rigid_motions_give_zero_strain(dims, vertices):
    rest = rng_array(2, (9, dims))
    cells = jnp.asarray([np.random.default_rng(3).permutation(9)[:vertices] for _ in range(6)])
    moved = rest @ jnp.asarray(random_rotation(4, dims)).T + rng_array(5, (dims,))
    for energy in (simplex_strain_energy, simplex_measure_energy):
        np.testing.assert_allclose(jax_energy(energy, moved, rest, cells, reduction="none"), 0.0, atol=1e-13)
    if vertices - 1 == dims:
        assert float(jax_energy(simplex_inversion_energy, moved, rest, cells, minimum_jacobian=0.9)) == 0.0
    np.testing.assert_allclose(jax_energy(total_measure_energy, moved, rest, cells), 0.0, atol=1e-13)


@pytest.mark.parametrize("dims", (1, 2, 3))
def test_reflection_seen_by_measure_and_inversion_not_strain(dims):
    rest = jnp.asarray({1: [[0.0], [1.0], [3.0]], 2: [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], 3: CUBE_POINTS}[dims])
    cells = {1: jnp.array([[0, 1], [1, 2]]), 2: jnp.array([[0, 1, 2], [0, 2, 3]]), 3: jnp.asarray(CUBE_TETS)}[dims]
    mirror = jnp.ones(dims).at[0].set(-1.0)
    reflected = rest * mirror + 0.5
    strain = jax_energy(simplex_strain_energy, reflected, rest, cells, reduction="none")
    np.testing.assert_allclose(strain, 0.0, atol=1e-14)
    # q = -1 at target 1: 2 V0 per cell.
    measures = jax_energy(simplex_measure_energy, reflected, rest, cells, reduction="none")
    inversions = jax_energy(simplex_inversion_energy, reflected, rest, cells, reduction="none", minimum_jacobian=0.0)
    reference_measure = jax_energy(simplex_measure_energy, 0 * rest, rest, cells, reduction="none", target_ratio=1.0) * 2
    np.testing.assert_allclose(measures, 2 * reference_measure, rtol=1e-14)
    np.testing.assert_allclose(inversions, reference_measure / 2, rtol=1e-14)


def test_cell_vertex_order_and_cell_order_do_not_matter():
    current, rest, cells = deformed_cube(6, 0.2)
    permutations = list(itertools.permutations(range(4)))
    rng = np.random.default_rng(7)
    shuffled = jnp.asarray(np.stack([np.asarray(cells)[c, list(permutations[rng.integers(24)])] for c in range(len(cells))]))
    order = rng.permutation(len(cells))
    for energy in PER_CELL_ENERGIES:
        reference = jax_energy(energy, current, rest, cells, reduction="none")
        np.testing.assert_array_equal(jax_energy(energy, current, rest, shuffled, reduction="none"), reference)
        np.testing.assert_array_equal(jax_energy(energy, current, rest, shuffled[order], reduction="none"), reference[order])
    np.testing.assert_allclose(jax_energy(total_measure_energy, current, rest, shuffled[order]),
                               jax_energy(total_measure_energy, current, rest, cells), rtol=1e-14)


# ------------------------------------------------------------------------------------------
# Derivatives


def all_energies(current, rest, cube_cells, surface_current, surface_rest):
    hinges, faces = jnp.asarray(OCTAHEDRON_HINGES), jnp.asarray(OCTAHEDRON_FACES)
    return jnp.stack([
        jax_energy(simplex_strain_energy, current, rest, cube_cells, lame_lambda=0.4, shear_modulus=1.1),
        jax_energy(simplex_measure_energy, current, rest, cube_cells, target_ratio=0.8),
        jax_energy(total_measure_energy, current, rest, cube_cells, target_ratio=1.2),
        jax_energy(simplex_inversion_energy, current, rest, cube_cells, minimum_jacobian=1.5),
        jax_energy(surface_bending_energy, surface_current, surface_rest, hinges),
        jax_energy(closed_surface_volume_energy, surface_current, surface_rest, faces, target_ratio=0.9),
    ])  # fmt: skip


def test_finite_difference_gradients():
    current, rest, cells = deformed_cube(8, 0.1)
    surface_current, surface_rest = deformed_octahedron(9, 0.1)
    # minimum_jacobian=1.5 keeps every cell strictly inside the hinge's quadratic branch. Second
    # derivatives are checked by the Hessian-vector product test below.
    check_grads(lambda *a: all_energies(*a[:2], cells, *a[2:]), (current, rest, surface_current, surface_rest),
                order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_embedded_and_low_dimensional_gradients():
    rest2 = rng_array(10, (6, 2))
    rest3 = rng_array(11, (6, 3))
    tri = jnp.array([[0, 1, 2], [2, 3, 4], [1, 4, 5]])
    seg = jnp.array([[0, 1], [1, 2], [3, 5]])

    def fn(p2, r2, p3, r3):
        return jnp.stack([
            jax_energy(simplex_strain_energy, p2, r2, seg, lame_lambda=-0.5),
            jax_energy(simplex_measure_energy, p3, r3, tri),
            jax_energy(total_measure_energy, p3, r3, seg),
            jax_energy(simplex_strain_energy, p3, r3, tri),
        ])  # fmt: skip

    args = (rest2 + rng_array(12, (6, 2), 0.1), rest2, rest3 + rng_array(13, (6, 3), 0.1), rest3)
    check_grads(fn, args, order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_hessian_vector_products_match_finite_differences_of_the_gradient():
    current, rest, cells = deformed_cube(14, 0.1)
    surface_current, surface_rest = deformed_octahedron(15, 0.1)
    tangent = (rng_array(16, current.shape), rng_array(17, surface_current.shape))

    def gradient(p, q):
        return jax.grad(lambda p, q: jnp.sum(all_energies(p, rest, cells, q, surface_rest)), argnums=(0, 1))(p, q)

    _, hvp = jax.jvp(gradient, (current, surface_current), tangent)
    h = 1e-5
    plus = gradient(current + h * tangent[0], surface_current + h * tangent[1])
    minus = gradient(current - h * tangent[0], surface_current - h * tangent[1])
    for exact, p, m in zip(hvp, plus, minus):
        assert np.all(np.isfinite(np.asarray(exact)))
        np.testing.assert_allclose(exact, (p - m) / (2 * h), rtol=1e-6, atol=1e-7)


def test_collapsed_embedded_cell_has_zero_subgradient():
    rest = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    collapsed = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    cells = jnp.array([[0, 1, 2]])
    value, grad = jax.value_and_grad(lambda p: jax_energy(simplex_measure_energy, p, rest, cells))(collapsed)
    np.testing.assert_allclose(value, 0.5 * 0.5, rtol=1e-14)
    np.testing.assert_array_equal(grad, 0.0)


# ------------------------------------------------------------------------------------------
# Invalid primitives


def test_degenerate_reference_and_bad_indices_are_nan_without_gradient():
    current, rest, cells = deformed_cube(18, 0.1)
    # Vertex 7 moved into the plane x = 0 of vertices 0-3 flattens cells 0 and 1 exactly; vertex 3
    # moved onto vertex 1 collapses an edge of cell 0.
    flattened = rest.at[7].set(jnp.array([0.0, 0.5, 0.5]))
    collapsed = rest.at[3].set(rest[1])
    num_points = rest.shape[0]
    bad_cells = cells.at[2, 1].set(num_points).at[4, 3].set(-1).astype(jnp.int64).at[5, 0].set(2**32 + 1)
    for energy in PER_CELL_ENERGIES:
        terms = jax_energy(energy, current, rest, bad_cells, reduction="none")
        assert np.isnan(np.asarray(terms)[[2, 4, 5]]).all() and np.isfinite(np.asarray(terms)[[0, 1, 3]]).all()
        grads = jax.grad(lambda p, r: jnp.nansum(jax_energy(energy, p, r, bad_cells, reduction="none")), argnums=(0, 1))(current, rest)  # noqa: B023
        expected = jax.grad(lambda p, r: jax_energy(energy, p, r, cells[jnp.array([0, 1, 3])]), argnums=(0, 1))(current, rest)  # noqa: B023
        for g, e in zip(grads, expected):
            np.testing.assert_allclose(g, e, atol=1e-15)
        # Sum over a NaN term is NaN, but no NaN reaches the gradient of valid terms.
        assert np.isnan(float(jax_energy(energy, current, rest, bad_cells)))
        g = jax.grad(lambda p: jax_energy(energy, p, rest, bad_cells))(current)  # noqa: B023
        assert np.all(np.isfinite(np.asarray(g)))
        for degenerate, expect_nan in ((flattened, [0, 1]), (collapsed, [0])):
            terms = np.asarray(jax_energy(energy, current, degenerate, cells, reduction="none"))
            np.testing.assert_array_equal(np.flatnonzero(np.isnan(terms)), expect_nan)
    assert np.isnan(float(jax_energy(total_measure_energy, current, rest, bad_cells)))
    g = jax.grad(lambda p, r: jax_energy(total_measure_energy, p, r, bad_cells), argnums=(0, 1))(current, rest)
    assert all(np.array_equal(np.asarray(x), np.zeros(x.shape)) for x in g)


def test_non_finite_coordinates_and_zero_points():
    current, rest, cells = deformed_cube(19, 0.1)
    nan_current = current.at[6].set(jnp.nan)
    inf_rest = rest.at[6].set(jnp.inf)
    touching = np.array([6 in c for c in np.asarray(cells)])
    for energy in PER_CELL_ENERGIES:
        for p, r in ((nan_current, rest), (current, inf_rest)):
            terms = jax_energy(energy, p, r, cells, reduction="none")
            np.testing.assert_array_equal(np.isnan(np.asarray(terms)), touching)
            g = jax.grad(lambda p, r: jnp.nansum(jax_energy(energy, p, r, cells, reduction="none")), argnums=(0, 1))(p, r)  # noqa: B023
            assert all(np.all(np.isfinite(np.asarray(x))) for x in g)
        empty = jnp.zeros((0, 3))
        assert np.isnan(np.asarray(jax_energy(energy, empty, empty, cells, reduction="none"))).all()
    assert np.isnan(float(jax_energy(total_measure_energy, jnp.zeros((0, 3)), jnp.zeros((0, 3)), cells)))

    surface_current, surface_rest = deformed_octahedron(20, 0.1)
    hinges, faces = jnp.asarray(OCTAHEDRON_HINGES), jnp.asarray(OCTAHEDRON_FACES)
    terms = jax_energy(surface_bending_energy, surface_current.at[5].set(jnp.inf), surface_rest, hinges, reduction="none")
    np.testing.assert_array_equal(np.isnan(np.asarray(terms)), [5 in h for h in OCTAHEDRON_HINGES])
    assert np.isnan(float(jax_energy(closed_surface_volume_energy, surface_current, surface_rest.at[1].set(jnp.nan), faces)))
    assert np.isnan(float(jax_energy(closed_surface_volume_energy, jnp.zeros((0, 3)), jnp.zeros((0, 3)), faces)))
    bad_faces = faces.at[3, 2].set(6)
    value, g = jax.value_and_grad(lambda p: jax_energy(closed_surface_volume_energy, p, surface_rest, bad_faces))(surface_current)
    assert np.isnan(float(value)) and np.array_equal(np.asarray(g), np.zeros(g.shape))
    flat = surface_rest * jnp.array([1.0, 1.0, 0.0])  # zero rest volume
    assert np.isnan(float(jax_energy(closed_surface_volume_energy, surface_current, flat, faces)))


def test_degenerate_bending_hinges():
    surface_current, surface_rest = deformed_octahedron(21, 0.1)
    hinges = jnp.asarray(OCTAHEDRON_HINGES)
    i, j, k, _ = OCTAHEDRON_HINGES[0]
    # Current triangle (i, j, k) collapsed: k onto i.
    collapsed = surface_current.at[k].set(surface_current[i])
    terms = np.asarray(jax_energy(surface_bending_energy, collapsed, surface_rest, hinges, reduction="none"))
    # Hinges with an exactly zero edge vector (e = x_b - x_a, x_c - x_a or x_d - x_b) are NaN. A
    # face whose other two edges coincide is also degenerate, but its cross product is only
    # rounding noise (FMA contraction), so those hinges are left out; untouched ones stay finite.
    pair = {int(i), int(k)}
    zero_vector = np.array([pair in ({a, b}, {a, c}, {b, d}) for a, b, c, d in OCTAHEDRON_HINGES])
    touched = np.array([pair <= {a, b, c} or pair <= {a, b, d} for a, b, c, d in OCTAHEDRON_HINGES])
    assert zero_vector.sum() >= 2 and np.isnan(terms[zero_vector]).all() and np.isfinite(terms[~touched]).all()
    g = jax.grad(lambda p: jnp.nansum(jax_energy(surface_bending_energy, p, surface_rest, hinges, reduction="none")))(collapsed)
    assert np.all(np.isfinite(np.asarray(g)))
    # Zero-length reference edge.
    terms = jax_energy(surface_bending_energy, surface_current, surface_rest.at[j].set(surface_rest[i]), hinges, reduction="none")
    assert np.isnan(np.asarray(terms)[0])
    bad = hinges.at[1, 3].set(-3)
    terms = np.asarray(jax_energy(surface_bending_energy, surface_current, surface_rest, bad, reduction="none"))
    assert np.isnan(terms[1]) and np.isfinite(np.delete(terms, 1)).all()


# ------------------------------------------------------------------------------------------
# Reductions, batching, transformations, dtypes


def test_reductions_and_empty_topology():
    current, rest, cells = deformed_cube(22, 0.2)
    for energy in PER_CELL_ENERGIES:
        terms = jax_energy(energy, current, rest, cells, reduction="none")
        assert terms.shape == (6,)
        np.testing.assert_allclose(jax_energy(energy, current, rest, cells, reduction="sum"), jnp.sum(terms), rtol=1e-14)
        np.testing.assert_allclose(jax_energy(energy, current, rest, cells, reduction="mean"), jnp.mean(terms), rtol=1e-14)
        empty = jnp.zeros((0, 4), jnp.int32)
        assert jax_energy(energy, current, rest, empty, reduction="none").shape == (0,)
        assert jax_energy(energy, current[None], rest[None], empty, reduction="none").shape == (1, 0)
        for reduction in ("sum", "mean"):
            value, g = jax.value_and_grad(lambda p: jax_energy(energy, p, rest, empty, reduction=reduction))(current)  # noqa: B023
            assert float(value) == 0.0 and g.shape == current.shape and not np.any(np.asarray(g))
    hinges = jnp.zeros((0, 4), jnp.int64)
    surface_current, surface_rest = deformed_octahedron()
    assert float(jax_energy(surface_bending_energy, surface_current, surface_rest, hinges, reduction="mean")) == 0.0
    for energy, topology in ((total_measure_energy, jnp.zeros((0, 4), jnp.int32)), (closed_surface_volume_energy, jnp.zeros((0, 3), jnp.int32))):
        with pytest.raises(ValueError, match="at least one"):
            jax_energy(energy, current, rest, topology)


def test_batching_and_vmap_equal_loops():
    current, rest, cells = deformed_cube(23, 0.1)
    batch_current = jnp.stack([current, current * 1.1, current + rng_array(31, current.shape, 0.05)])
    batch_rest = jnp.stack([rest, rest, rest * 0.9])
    surface_current, surface_rest = deformed_octahedron(24, 0.1)
    surface_batch = jnp.stack([surface_current, surface_current * 0.8])
    surface_rest_batch = jnp.stack([surface_rest, surface_rest + 1.0])
    cases = [(e, batch_current, batch_rest, cells) for e in SIMPLEX_ENERGIES]
    cases += [(surface_bending_energy, surface_batch, surface_rest_batch, jnp.asarray(OCTAHEDRON_HINGES)),
              (closed_surface_volume_energy, surface_batch, surface_rest_batch, jnp.asarray(OCTAHEDRON_FACES))]
    for energy, points, reference, topology in cases:
        per_item = jnp.stack([jax_energy(energy, p, r, topology, reduction="none") for p, r in zip(points, reference)])
        batched = jax_energy(energy, points, reference, topology, reduction="none")
        np.testing.assert_allclose(batched, per_item, rtol=1e-14)
        # vmap (under jit) of value and gradient.
        values, grads = jax.jit(jax.vmap(jax.value_and_grad(lambda p, r: jax_energy(energy, p, r, topology), argnums=(0, 1))))(points, reference)  # noqa: B023
        np.testing.assert_allclose(values, per_item.reshape(len(points), -1).sum(axis=1), rtol=1e-13)
        loops = [jax.grad(lambda p, r: jax_energy(energy, p, r, topology), argnums=(0, 1))(p, r) for p, r in zip(points, reference)]  # noqa: B023
        for k in range(2):
            np.testing.assert_allclose(grads[k], jnp.stack([g[k] for g in loops]), rtol=1e-12, atol=1e-14)
    total = jax_energy(total_measure_energy, batch_current, batch_rest, cells, reduction="none")
    assert total.shape == (3,) and jax_energy(total_measure_energy, current, rest, cells, reduction="none").shape == ()


def test_jvp_matches_vjp():
    current, rest, cells = deformed_cube(25, 0.1)
    surface_current, surface_rest = deformed_octahedron(26, 0.1)
    cases = [(e, current, rest, cells) for e in SIMPLEX_ENERGIES]
    cases += [(surface_bending_energy, surface_current, surface_rest, jnp.asarray(OCTAHEDRON_HINGES)),
              (closed_surface_volume_energy, surface_current, surface_rest, jnp.asarray(OCTAHEDRON_FACES))]
    for energy, p, r, topology in cases:
        fn = lambda p, r: jax_energy(energy, p, r, topology)  # noqa: B023,E731
        tangents = (rng_array(27, p.shape), rng_array(28, r.shape))
        _, forward = jax.jvp(fn, (p, r), tangents)
        grads = jax.grad(fn, argnums=(0, 1))(p, r)
        np.testing.assert_allclose(forward, jnp.vdot(grads[0], tangents[0]) + jnp.vdot(grads[1], tangents[1]), rtol=1e-12)


def test_float32_matches_float64():
    current, rest, cells = deformed_cube(27, 0.2)
    surface_current, surface_rest = deformed_octahedron(28, 0.2)
    hinges, faces = jnp.asarray(OCTAHEDRON_HINGES), jnp.asarray(OCTAHEDRON_FACES)
    cases = [(e, current, rest, cells) for e in SIMPLEX_ENERGIES]
    cases += [(surface_bending_energy, surface_current, surface_rest, hinges), (closed_surface_volume_energy, surface_current, surface_rest, faces)]
    for energy, p, r, topology in cases:
        single = jax_energy(energy, p.astype(jnp.float32), r.astype(jnp.float32), topology.astype(jnp.int32), reduction="none")
        assert single.dtype == jnp.float32
        np.testing.assert_allclose(single, jax_energy(energy, p, r, topology, reduction="none"), rtol=2e-4, atol=1e-6)
    # Gradients keep the dtype (float32 gradients are compared with Warp's in the Warp tests).
    for energy, p, r, topology in (cases[0], cases[4]):
        g = jax.grad(lambda p: jnp.sum(jax_energy(energy, p, r.astype(jnp.float32), topology)))(p.astype(jnp.float32))  # noqa: B023
        assert g.dtype == jnp.float32


def test_large_coordinates_do_not_break_bending_scale_invariance():
    surface_current, surface_rest = deformed_octahedron(29, 0.2)
    hinges = jnp.asarray(OCTAHEDRON_HINGES)
    base = jax_energy(surface_bending_energy, surface_current, surface_rest, hinges, reduction="none")
    for scale in (1e-30, 1e30):
        scaled = jax_energy(surface_bending_energy, (scale * surface_current).astype(jnp.float32),
                            (scale * surface_rest).astype(jnp.float32), hinges, reduction="none")
        np.testing.assert_allclose(scaled, base, rtol=1e-4, atol=1e-6)


# ------------------------------------------------------------------------------------------
# Validation and dispatch


def test_errors():
    current, rest, cells = deformed_cube()
    surface_current, surface_rest = deformed_octahedron()
    for energy in SIMPLEX_ENERGIES:
        with pytest.raises(TypeError):
            jax_energy(energy, current.astype(jnp.int32), rest, cells)
        with pytest.raises(TypeError):
            jax_energy(energy, current.astype(jnp.float16), rest.astype(jnp.float16), cells)
        with pytest.raises(TypeError):
            jax_energy(energy, current, rest.astype(jnp.float32), cells)
        with pytest.raises(TypeError):
            jax_energy(energy, current, rest, cells.astype(jnp.float64))
        with pytest.raises(TypeError):
            jax_energy(energy, current, rest, cells.astype(jnp.int16))
        with pytest.raises(TypeError):
            jax_energy(energy, current, rest, cells > 2)
        with pytest.raises(TypeError):
            jax_energy(energy, current.tolist(), rest, cells)
        with pytest.raises(ValueError, match="shape"):
            jax_energy(energy, current, rest[:-1], cells)
        with pytest.raises(ValueError, match="shape"):
            jax_energy(energy, current[None], rest, cells)
        with pytest.raises(ValueError, match="shape"):
            jax_energy(energy, current, rest, jnp.zeros((3, 5), jnp.int32))
        with pytest.raises(ValueError, match="shape"):
            jax_energy(energy, current, rest, cells[0])
        with pytest.raises(ValueError, match="shape"):
            jax_energy(energy, current[0], rest[0], cells)
        with pytest.raises(ValueError, match="reduction"):
            jax_energy(energy, current, rest, cells, reduction="max")
        with pytest.raises(KeyError):
            energy(current, rest, cells, implementation="numpy")
    with pytest.raises(ValueError, match="D >= 3"):
        jax_energy(simplex_strain_energy, current[:, :2], rest[:, :2], cells)
    with pytest.raises(ValueError, match=r"lame_lambda \+ 2 \* shear_modulus / simplex_dimension must be nonnegative"):
        jax_energy(simplex_strain_energy, current, rest, cells, lame_lambda=-0.7, shear_modulus=1.0)
    jax_energy(simplex_strain_energy, current, rest, cells, lame_lambda=-2 / 3, shear_modulus=1.0)  # boundary: allowed
    # Moduli near the float max: -1e308 + 2 * 1e308 / 3 = -3.33e307 is negative and representable
    # (the message's value too, where 2 * 1e308 alone would overflow).
    with pytest.raises(ValueError, match=r"must be nonnegative, got -1e\+308 \+ 2 \* 1e\+308 / 3 = -3.33333\d*e\+307"):
        jax_energy(simplex_strain_energy, current, rest, cells, lame_lambda=-1e308, shear_modulus=1e308)
    with pytest.raises(ValueError, match="nonnegative"):
        jax_energy(simplex_strain_energy, current, rest, cells[:, :2], lame_lambda=-2.1, shear_modulus=1.0)
    with pytest.raises(ValueError, match="shear_modulus"):
        jax_energy(simplex_strain_energy, current, rest, cells, shear_modulus=-1.0)
    with pytest.raises(ValueError, match="lame_lambda"):
        jax_energy(simplex_strain_energy, current, rest, cells, lame_lambda=math.inf)
    with pytest.raises(TypeError, match="lame_lambda"):
        jax_energy(simplex_strain_energy, current, rest, cells, lame_lambda=True)
    # Each modulus representable, their bulk combination not: lambda / 2 + mu / 1 on segments is
    # 1.5e38 + 3e38 in float32 (and 8.5e307 + 1.7e308 in float64), beyond the largest float.
    for dtype, huge in ((jnp.float32, 3e38), (jnp.float64, 1.7e308)):
        for implementation in (None, "jax", "warp"):
            with pytest.raises(ValueError, match=r"lame_lambda / 2 \+ shear_modulus / simplex_dimension must be finite"):
                simplex_strain_energy(
                    current.astype(dtype), rest.astype(dtype), cells[:, :2], lame_lambda=huge, shear_modulus=huge, implementation=implementation
                )
    edge = simplex_strain_energy(current, rest, cells[:, :2], lame_lambda=1.7e308, shear_modulus=0.0, reduction="none")
    assert np.isfinite(np.asarray(edge)).all()  # the largest representable combination is accepted
    with pytest.raises(TypeError, match="shear_modulus"):
        jax_energy(simplex_strain_energy, current, rest, cells, shear_modulus="1")
    for energy in (simplex_measure_energy, total_measure_energy):
        for bad in (0.0, -1.0, math.nan, math.inf):
            with pytest.raises(ValueError, match="target_ratio"):
                jax_energy(energy, current, rest, cells, target_ratio=bad)
        with pytest.raises(TypeError, match="target_ratio"):
            jax_energy(energy, current, rest, cells, target_ratio=False)
        for bad in (1e300, 1e-46):  # outside float32's range, underflowing in float32
            with pytest.raises(ValueError, match="target_ratio"):
                jax_energy(energy, current.astype(jnp.float32), rest.astype(jnp.float32), cells, target_ratio=bad)
    with pytest.raises(ValueError, match="minimum_jacobian"):
        jax_energy(simplex_inversion_energy, current, rest, cells, minimum_jacobian=-0.1)
    with pytest.raises(TypeError, match="minimum_jacobian"):
        jax_energy(simplex_inversion_energy, current, rest, cells, minimum_jacobian=None)
    with pytest.raises(ValueError, match="full-dimensional"):
        jax_energy(simplex_inversion_energy, current, rest, cells[:, :3])
    hinges, faces = jnp.asarray(OCTAHEDRON_HINGES), jnp.asarray(OCTAHEDRON_FACES)
    with pytest.raises(ValueError, match="D = 3"):
        jax_energy(surface_bending_energy, surface_current[:, :2], surface_rest[:, :2], hinges)
    with pytest.raises(ValueError, match="shape"):
        jax_energy(surface_bending_energy, surface_current, surface_rest, faces)
    with pytest.raises(ValueError, match="D = 3"):
        jax_energy(closed_surface_volume_energy, jnp.zeros((6, 4)), jnp.zeros((6, 4)), faces)
    with pytest.raises(ValueError, match="shape"):
        jax_energy(closed_surface_volume_energy, surface_current, surface_rest, hinges)
    with pytest.raises(ValueError, match="target_ratio"):
        jax_energy(closed_surface_volume_energy, surface_current, surface_rest, faces, target_ratio=-2.0)
    with pytest.raises(TypeError):
        jax_energy(closed_surface_volume_energy, surface_current, surface_rest, faces.astype(bool))


def test_dispatch_rules(monkeypatch):
    current4 = rng_array(30, (6, 4))
    cells = jnp.array([[0, 1, 2], [2, 3, 5]])
    # D > 3: None falls back to JAX; "torch" means "jax".
    np.testing.assert_array_equal(simplex_measure_energy(current4, current4 * 2, cells),
                                  simplex_measure_energy(current4, current4 * 2, cells, implementation="torch"))
    monkeypatch.setattr(dispatch, "warp_available", lambda: False)
    current, rest, cells = deformed_cube()
    for energy in SIMPLEX_ENERGIES:
        with pytest.raises(ImportError):
            energy(current, rest, cells, implementation="warp")
        np.testing.assert_array_equal(energy(current, rest, cells), jax_energy(energy, current, rest, cells))
