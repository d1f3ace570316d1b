"""The six deformation energies: Warp kernels against the JAX specification."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

pytest.importorskip("warp")

import warp_ffi.bending  # noqa: E402
import warp_ffi.measure  # noqa: E402
import warp_ffi.strain  # noqa: E402
import warp_ffi.volume  # noqa: E402
from geomjax import (  # noqa: E402
    closed_surface_volume_energy,
    simplex_inversion_energy,
    simplex_measure_energy,
    simplex_strain_energy,
    surface_bending_energy,
    total_measure_energy,
)

from .test_energies import CUBE_TETS, OCTAHEDRON_FACES, OCTAHEDRON_HINGES, deformed_cube, deformed_octahedron, rng_array  # noqa: E402

PARAMETERS = {
    simplex_strain_energy: {"lame_lambda": 0.4, "shear_modulus": 1.1},
    simplex_measure_energy: {"target_ratio": 0.8},
    total_measure_energy: {"target_ratio": 1.2},
    simplex_inversion_energy: {"minimum_jacobian": 1.05},
    surface_bending_energy: {},
    closed_surface_volume_energy: {"target_ratio": 0.9},
}
PER_TERM = (simplex_strain_energy, simplex_measure_energy, simplex_inversion_energy, surface_bending_energy)


def tolerance(dtype):
    return {"rtol": 2e-4, "atol": 2e-5} if dtype == jnp.float32 else {"rtol": 1e-10, "atol": 1e-12}


@functools.cache
def _terms_and_gradients(energy, implementation):
    """``(points, reference, topology, weights) -> (terms, gradients)`` as one jitted program
    (run eagerly, the value-and-gradient compiles a one-primitive program per operation)."""
    kwargs = PARAMETERS[energy]

    def run(points, reference, topology, weights):
        def loss(p, r):
            terms = energy(p, r, topology, reduction="none", implementation=implementation, **kwargs)
            return jnp.nansum(terms if weights is None else terms * weights), terms

        (_, terms), grads = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(points, reference)
        return terms, grads

    return jax.jit(run)


def evaluate(energy, implementation, points, reference, topology, weights=None):
    """Per-term values and the gradients of a weighted NaN-ignoring sum, for one backend."""
    return _terms_and_gradients(energy, implementation)(points, reference, topology, weights)


def assert_parity(energy, points, reference, topology, weights=None):
    tol = tolerance(points.dtype)
    terms_warp, grads_warp = evaluate(energy, "warp", points, reference, topology, weights)
    terms_jax, grads_jax = evaluate(energy, "jax", points, reference, topology, weights)
    assert terms_warp.dtype == points.dtype and terms_warp.shape == terms_jax.shape
    np.testing.assert_array_equal(np.isnan(np.asarray(terms_warp)), np.isnan(np.asarray(terms_jax)), err_msg=energy.__name__)
    np.testing.assert_allclose(terms_warp, terms_jax, **tol, err_msg=energy.__name__)
    for name, a, b in zip(("points", "reference_points"), grads_warp, grads_jax):
        assert a.dtype == points.dtype
        np.testing.assert_allclose(a, b, **tol, err_msg=f"{energy.__name__} d/d{name}")
    return terms_warp, grads_jax


@pytest.mark.parametrize("dtype", (jnp.float32, jnp.float64))
def test_tetrahedra_parity_with_invalid_cells(dtype):
    current, rest, cells = deformed_cube(40, 0.15, dtype)
    cells = jnp.concatenate([cells, cells[:3]]).astype(jnp.int64)
    cells = cells.at[6, 2].set(8).at[7, 0].set(-1).at[8, 1].set(2**32 + 1)  # out of range, incl. int32 wrap-around
    rest = rest.at[5].set(rest[4])  # collapses an edge of cells 4 and 5
    current = current.at[2].set(jnp.nan)
    cells = jnp.concatenate([cells, jnp.array([[1, 3, 5, 7]])])  # a cell touching none of the above
    for energy in (simplex_strain_energy, simplex_measure_energy, simplex_inversion_energy):
        terms, _ = assert_parity(energy, current, rest, cells, weights=jnp.arange(1, 11, dtype=dtype))
        invalid = np.array([2 in c or {4, 5} <= set(c) for c in np.asarray(cells)])
        invalid[6:9] = True
        np.testing.assert_array_equal(np.isnan(np.asarray(terms)), invalid, err_msg=energy.__name__)
    assert_parity(total_measure_energy, current, rest, cells)
    valid = jnp.asarray(CUBE_TETS[[0, 3]])  # no vertex 2, no collapsed edge
    assert_parity(total_measure_energy, current, rest, valid)


def test_lower_dimensional_and_embedded_cells():
    cases, rng = [], np.random.default_rng(47)
    # (D, m): segments in 1D, 2D and 3D, triangles in 2D and 3D (tetrahedra are covered above).
    for dims, m in ((1, 1), (2, 1), (2, 2), (3, 1), (3, 2)):
        rest = rng_array(41 + dims, (7, dims))
        current = rest + rng_array(44 + dims, (7, dims), 0.2)
        cells = jnp.asarray([rng.permutation(7)[: m + 1] for _ in range(5)]).at[4, 0].set(9)
        cases.append((current, rest, cells))
    cases.append(tuple(a.astype(jnp.float32) if a.dtype == jnp.float64 else a for a in cases[4]))
    for current, rest, cells in cases:
        for energy in (simplex_strain_energy, simplex_measure_energy):
            assert_parity(energy, current, rest, cells)
    # The other measure-based energies share the measure kernels; one full-dimensional check each.
    current, rest, cells = cases[2]
    for energy in (total_measure_energy, simplex_inversion_energy):
        assert_parity(energy, current, rest, cells[:4])


@pytest.mark.parametrize("dtype", (jnp.float32, jnp.float64))
def test_surface_parity(dtype):
    current, rest = deformed_octahedron(50, 0.15, dtype)
    hinges = jnp.asarray(OCTAHEDRON_HINGES).at[3, 2].set(6)
    terms, _ = assert_parity(surface_bending_energy, current.at[1].set(jnp.inf), rest, hinges, weights=jnp.linspace(0.5, 2.0, 12, dtype=dtype))
    np.testing.assert_array_equal(np.isnan(np.asarray(terms)), [k == 3 or 1 in h for k, h in enumerate(OCTAHEDRON_HINGES)])
    current2, rest2 = deformed_octahedron(51, 0.15, dtype)
    faces = jnp.asarray(OCTAHEDRON_FACES)
    assert_parity(closed_surface_volume_energy, current2 + 100.0, rest2 - 3.0, faces[:, ::-1])


def test_degenerate_and_invalid_surface_primitives():
    dtype = jnp.float64
    # Exactly degenerate hinges (axis-aligned, so rounding cannot hide the zero): points 0, 1, 2
    # collinear in both configurations, point 5 on top of point 0 at rest.
    rest = jnp.asarray([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0.5, 1, 0], [0.5, -1, 0.2], [0, 0, 0]], dtype)
    current = (rest + rng_array(57, rest.shape, 0.1, dtype)).at[:3].set(rest[:3])
    hinges = jnp.array([[0, 1, 3, 4], [0, 1, 2, 4], [0, 1, 3, 2], [0, 5, 3, 4], [1, 2, 3, 4]])
    terms, _ = assert_parity(surface_bending_energy, current, rest, hinges)
    np.testing.assert_array_equal(np.isnan(np.asarray(terms)), [False, True, True, True, False])

    current2, rest2 = deformed_octahedron(51, 0.15, dtype)
    faces = jnp.asarray(OCTAHEDRON_FACES)
    for bad_points, bad_faces in ((current2, faces.at[2, 0].set(-1)), (current2.at[4].set(jnp.nan), faces)):
        value, grads = evaluate(closed_surface_volume_energy, "warp", bad_points, rest2, bad_faces)
        assert np.isnan(float(value)) and all(not np.any(np.asarray(g)) for g in grads)


def test_bending_branch_cut_on_warp():
    # Rest hinge folded to +170 degrees, current to -170 degrees: a 20 degree change through pi.
    angle = np.radians(170.0)
    rest = jnp.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, -np.cos(angle), -np.sin(angle)]])
    current = rest.at[3, 2].set(np.sin(angle))
    hinge = jnp.array([[0, 1, 2, 3]])
    value, grad = jax.value_and_grad(lambda p: surface_bending_energy(p, rest, hinge, implementation="warp"))(current)
    np.testing.assert_allclose(value, 0.5 * 2 * np.radians(20.0) ** 2, rtol=1e-10)
    # Rotating the right wing towards the rest fold (decreasing |wrap(theta - theta0)|) lowers it.
    assert float(grad[3, 2]) > 0


def test_batches_vmap_and_jit_match_jax():
    current, rest, cells = deformed_cube(52, 0.1)
    points = jnp.stack([current, 1.1 * current])
    references = jnp.stack([rest, rest + 0.5])
    surface_current, surface_rest = deformed_octahedron(53, 0.1)
    surface_points, surface_references = jnp.stack([surface_current, 0.9 * surface_current]), jnp.stack([surface_rest, surface_rest])
    # Total measure and inversion share the measure kernels.
    cases = [(e, points, references, cells) for e in (simplex_strain_energy, simplex_measure_energy)]
    cases += [(surface_bending_energy, surface_points, surface_references, jnp.asarray(OCTAHEDRON_HINGES)),
              (closed_surface_volume_energy, surface_points, surface_references, jnp.asarray(OCTAHEDRON_FACES))]
    for energy, p, r, topology in cases:
        terms, grads_jax = assert_parity(energy, p, r, topology)  # aligned (B, N, D) batches
        # Designs are independent, so per-design values and gradients are the batched ones.
        fn = lambda p, r: energy(p, r, topology, implementation="warp", **PARAMETERS[energy])  # noqa: B023,E731
        values, grads = jax.jit(jax.vmap(jax.value_and_grad(fn, argnums=(0, 1))))(p, r)
        np.testing.assert_allclose(values, terms.reshape(len(p), -1).sum(axis=1), rtol=1e-12, err_msg=energy.__name__)
        for a, b in zip(grads, grads_jax):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-13, err_msg=energy.__name__)


def test_first_order_finite_differences():
    current, rest, cells = deformed_cube(54, 0.1)
    surface_current, surface_rest = deformed_octahedron(55, 0.1)
    hinges = jnp.asarray(OCTAHEDRON_HINGES)

    def fn(p, r, q, s):
        return jnp.stack([
            simplex_strain_energy(p, r, cells, lame_lambda=0.3, implementation="warp"),
            simplex_measure_energy(p, r, cells[:, :3], implementation="warp"),
            surface_bending_energy(q, s, hinges, implementation="warp"),
        ])  # fmt: skip

    check_grads(fn, (current, rest, surface_current, surface_rest), order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_empty_and_missing_points():
    current, rest, cells = deformed_cube()
    for energy in PER_TERM:
        topology = jnp.zeros((0, 4), jnp.int32)
        value, grad = jax.value_and_grad(lambda p: energy(p, rest, topology, implementation="warp"))(current)  # noqa: B023
        assert float(value) == 0.0 and not np.any(np.asarray(grad))
        assert energy(current[None], rest[None], topology, reduction="none", implementation="warp").shape == (1, 0)
        assert energy(jnp.zeros((0, 8, 3)), jnp.zeros((0, 8, 3)), cells, reduction="none", implementation="warp").shape == (0, 6)
        missing = energy(jnp.zeros((0, 3)), jnp.zeros((0, 3)), cells, reduction="none", implementation="warp")
        assert missing.shape == (6,) and np.isnan(np.asarray(missing)).all()
    assert np.isnan(float(total_measure_energy(jnp.zeros((0, 3)), jnp.zeros((0, 3)), cells, implementation="warp")))
    faces = jnp.asarray(OCTAHEDRON_FACES)
    assert np.isnan(float(closed_surface_volume_energy(jnp.zeros((0, 3)), jnp.zeros((0, 3)), faces, implementation="warp")))
    assert closed_surface_volume_energy(jnp.zeros((0, 6, 3)), jnp.zeros((0, 6, 3)), faces, reduction="none", implementation="warp").shape == (0,)


def test_dimension_rules_and_default_backend(monkeypatch):
    points4 = rng_array(56, (6, 4))
    triangles = jnp.array([[0, 1, 2], [2, 3, 5]])
    for energy in (simplex_strain_energy, simplex_measure_energy, total_measure_energy):
        with pytest.raises(ValueError, match="D <= 3"):
            energy(points4, 2 * points4, triangles, implementation="warp")
        np.testing.assert_array_equal(energy(points4, 2 * points4, triangles), energy(points4, 2 * points4, triangles, implementation="jax"))

    calls = []

    def spy(module, name):
        original = getattr(module, name)

        def wrapper(*args, **kwargs):
            calls.append(name)
            return original(*args, **kwargs)

        monkeypatch.setattr(module, name, wrapper)

    spy(warp_ffi.measure, "simplex_measures")
    spy(warp_ffi.strain, "simplex_strain_terms")
    spy(warp_ffi.bending, "surface_bending_terms")
    spy(warp_ffi.volume, "face_volumes")
    current, rest, cells = deformed_cube()
    surface_current, surface_rest = deformed_octahedron()
    for energy in (simplex_strain_energy, simplex_measure_energy, total_measure_energy, simplex_inversion_energy):
        energy(current, rest, cells)
    surface_bending_energy(surface_current, surface_rest, jnp.asarray(OCTAHEDRON_HINGES))
    closed_surface_volume_energy(surface_current, surface_rest, jnp.asarray(OCTAHEDRON_FACES))
    # The volume's default is JAX on CPU (its Warp path measured slower, see the registry).
    assert calls == ["simplex_strain_terms"] + ["simplex_measures"] * 3 + ["surface_bending_terms"]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(indices=st.lists(st.integers(-(2**40), 2**40) | st.integers(-2, 9), min_size=24, max_size=24))
def test_arbitrary_index_values_never_read_out_of_bounds(indices):
    current, rest, _ = deformed_cube(58, 0.1)
    cells = jnp.asarray(np.array(indices, np.int64).reshape(6, 4))
    in_range = np.all((np.asarray(cells) >= 0) & (np.asarray(cells) < 8), axis=1)
    # A hinge with a repeated vertex can have a face whose two edge vectors coincide, whose cross
    # product is rounding noise (FMA contraction differs between backends): compared only for NaN.
    distinct = np.array([len(set(row)) == 4 for row in np.asarray(cells)])
    for energy, compared in ((simplex_measure_energy, np.ones(6, bool)), (surface_bending_energy, distinct | ~in_range)):
        warp_terms = np.asarray(energy(current, rest, cells, reduction="none", implementation="warp"))
        jax_terms = np.asarray(energy(current, rest, cells, reduction="none", implementation="jax"))
        assert np.isnan(warp_terms[~in_range]).all()
        np.testing.assert_array_equal(np.isnan(warp_terms[compared]), np.isnan(jax_terms[compared]))
        np.testing.assert_allclose(warp_terms[compared], jax_terms[compared], rtol=1e-10, atol=1e-12)
