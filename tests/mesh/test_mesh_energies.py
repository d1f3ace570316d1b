"""Mesh energy methods and sobolev_deform: the tensor functionals with cached, validated topology."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from geomjax import Mesh, icosphere, polyline, rectangle, tetrahedralized_box
from geomjax.deform.sobolev import sobolev_deform_points
from geomjax.energy.bending import surface_bending_energy
from geomjax.energy.inversion import simplex_inversion_energy
from geomjax.energy.measure import simplex_measure_energy
from geomjax.energy.strain import simplex_strain_energy
from geomjax.energy.total_measure import total_measure_energy
from geomjax.energy.volume import closed_surface_volume_energy

from .test_mesh import TETRA_FACES, TETRA_HINGES, TETRA_POINTS, _count_calls, _hinges_by_dictionary


def _perturbed(mesh, scale=0.05, seed=0):
    noise = np.random.default_rng(seed).normal(scale=scale, size=mesh.points.shape)
    return mesh.points + jnp.asarray(noise, mesh.points.dtype)


MESHES = {
    "segments": lambda dtype: polyline(jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.2, 0.0], [2.0, 0.0, 0.5]], dtype)),
    "triangles_2d": lambda dtype: rectangle(2, 3, dtype=dtype),
    "triangles_3d": lambda dtype: icosphere(1, dtype=dtype),
    "tetrahedra": lambda dtype: tetrahedralized_box(2, 1, 2, dtype=dtype),
}


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("kind", sorted(MESHES))
def test_cell_energies_equal_the_functionals_on_the_cached_cells(kind, dtype):
    mesh = MESHES[kind](dtype)
    points = _perturbed(mesh)
    cells = jnp.asarray(np.asarray(mesh.topology.cells_host))  # int64, independent of the cache
    rtol = 1e-5 if dtype == jnp.float32 else 1e-12
    cases = [
        (mesh.simplex_strain_energy(points, lame_lambda=0.5, shear_modulus=2.0, reduction="none", implementation="jax"),
         simplex_strain_energy(points, mesh.points, cells, lame_lambda=0.5, shear_modulus=2.0, reduction="none",
                               implementation="jax")),
        (mesh.simplex_measure_energy(points, target_ratio=1.5, reduction="mean", implementation="jax"),
         simplex_measure_energy(points, mesh.points, cells, target_ratio=1.5, reduction="mean", implementation="jax")),
        (mesh.total_measure_energy(points, target_ratio=0.9, implementation="jax"),
         total_measure_energy(points, mesh.points, cells, target_ratio=0.9, implementation="jax")),
    ]
    if mesh.n_manifold_dims == mesh.n_spatial_dims:
        cases.append((
            mesh.simplex_inversion_energy(points, minimum_jacobian=0.99, reduction="none", implementation="jax"),
            simplex_inversion_energy(points, mesh.points, cells, minimum_jacobian=0.99, reduction="none",
                                     implementation="jax"),
        ))
    for got, expected in cases:
        assert got.dtype == dtype
        np.testing.assert_allclose(got, expected, rtol=rtol, atol=0)
    assert float(cases[0][0].sum()) > 0


def test_bending_uses_hinges_equal_to_an_independent_builder():
    mesh = icosphere(1)
    points = _perturbed(mesh, seed=1)
    hinges = jnp.asarray(_hinges_by_dictionary(np.asarray(mesh.cells)))
    got = mesh.surface_bending_energy(points, reduction="none", implementation="jax")
    np.testing.assert_allclose(got, surface_bending_energy(points, mesh.points, hinges, reduction="none",
                                                           implementation="jax"), rtol=1e-12)
    tetra = Mesh(jnp.asarray(TETRA_POINTS), TETRA_FACES)
    moved = tetra.points.at[3].add(jnp.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(
        tetra.surface_bending_energy(moved, implementation="jax"),
        surface_bending_energy(moved, tetra.points, jnp.asarray(TETRA_HINGES), implementation="jax"), rtol=1e-12,
    )


def test_bending_is_independent_of_the_input_winding():
    sphere = icosphere(1)
    faces = np.asarray(sphere.cells)
    flipped = Mesh(sphere.points, np.where((np.arange(80) % 3 == 0)[:, None], faces[:, ::-1], faces))
    points = _perturbed(sphere, seed=2)
    np.testing.assert_allclose(flipped.surface_bending_energy(points, implementation="jax"),
                               sphere.surface_bending_energy(points, implementation="jax"), rtol=1e-12)
    assert float(sphere.surface_bending_energy(points, implementation="jax")) > 0


def test_volume_energy_of_a_scaled_sphere_is_analytic():
    sphere = icosphere(2)
    points, faces = np.asarray(sphere.points), np.asarray(sphere.cells)
    volume = np.einsum("ij,ij->i", points[faces[:, 0]], np.cross(points[faces[:, 1]], points[faces[:, 2]])).sum() / 6
    for scale in (0.5, 1.0, 1.3):
        got = sphere.closed_surface_volume_energy(sphere.points * scale, target_ratio=1.1, implementation="jax")
        np.testing.assert_allclose(got, 0.5 * volume * (scale**3 - 1.1) ** 2, rtol=1e-12)
    # Same as the functional, on any deformation.
    moved = _perturbed(sphere, seed=3)
    np.testing.assert_allclose(
        sphere.closed_surface_volume_energy(moved, implementation="jax"),
        closed_surface_volume_energy(moved, sphere.points, jnp.asarray(faces), implementation="jax"), rtol=1e-12,
    )


def test_default_backends_agree_with_the_jax_path():
    sphere = icosphere(1)
    moved = _perturbed(sphere, seed=4)
    for method in (sphere.surface_bending_energy, sphere.closed_surface_volume_energy, sphere.simplex_strain_energy):
        np.testing.assert_allclose(method(moved), method(moved, implementation="jax"), rtol=1e-10)


def test_energy_topology_requirements():
    sphere, plate, box = icosphere(0), rectangle(1, 1), tetrahedralized_box(1, 1, 1)
    with pytest.raises(ValueError, match="full-dimensional cells"):
        sphere.simplex_inversion_energy(sphere.points)
    for mesh in (plate, box):
        with pytest.raises(ValueError, match="triangle surface in 3-D"):
            mesh.surface_bending_energy(mesh.points)
        with pytest.raises(ValueError, match="triangle surface in 3-D"):
            mesh.closed_surface_volume_energy(mesh.points)
    open_cap = Mesh(sphere.points, np.asarray(sphere.cells)[1:])
    with pytest.raises(ValueError, match="surface is open"):
        open_cap.closed_surface_volume_energy(open_cap.points)
    bad = Mesh(sphere.points, np.concatenate([np.asarray(sphere.cells), np.asarray(sphere.cells)[:1, ::-1]]))
    with pytest.raises(ValueError, match="unique triangles"):
        bad.surface_bending_energy(bad.points)


def test_energy_points_must_match_the_mesh():
    sphere = icosphere(0)
    with pytest.raises(ValueError, match="shape of mesh.points"):
        sphere.simplex_strain_energy(sphere.points[None])
    with pytest.raises(ValueError, match="shape of mesh.points"):
        sphere.surface_bending_energy(sphere.points[:-1])
    with pytest.raises(TypeError, match="same dtype"):
        sphere.closed_surface_volume_energy(sphere.points.astype(jnp.float32))
    with pytest.raises(TypeError):
        sphere.simplex_measure_energy(np.asarray(sphere.points).tolist())
    batched = jax.vmap(lambda d: sphere.displace(d))(jnp.zeros((2, 12, 3)))
    with pytest.raises(ValueError, match="batched"):
        batched.simplex_strain_energy(batched.points[0])


def test_optimisation_loop_validates_and_traces_once(monkeypatch):
    validations = _count_calls(monkeypatch, "_validate_cells")
    hinge_builds = _count_calls(monkeypatch, "_build_hinges")
    closed_checks = _count_calls(monkeypatch, "_check_closed_surface")
    reference = icosphere(1)
    traces = []

    def loss(points):
        traces.append(1)
        return (reference.simplex_strain_energy(points, implementation="jax")
                + reference.surface_bending_energy(points, implementation="jax")
                + 10.0 * reference.closed_surface_volume_energy(points, target_ratio=1.2, implementation="jax"))

    step = jax.jit(jax.value_and_grad(loss))
    points = reference.points
    values = []
    for _ in range(5):
        value, gradient = step(points)
        values.append(float(value))
        points = points - 0.002 * gradient
    assert len(traces) == 1 and (len(validations), len(hinge_builds), len(closed_checks)) == (1, 1, 1)
    assert values[-1] < values[0]


def test_grad_jvp_and_vmap_of_a_mesh_energy():
    mesh = tetrahedralized_box(1, 1, 1)
    points = _perturbed(mesh, seed=5)
    check_grads(jax.jit(lambda p: mesh.simplex_strain_energy(p, implementation="jax")), (points,), order=1, modes=("fwd", "rev"))
    sphere = icosphere(0)
    moved = _perturbed(sphere, seed=6)
    check_grads(jax.jit(lambda p: sphere.surface_bending_energy(p, implementation="jax")), (moved,), order=1, modes=("rev",))
    batch = jnp.stack([_perturbed(mesh, seed=s) for s in range(3)])
    energies = jax.vmap(lambda p: mesh.simplex_inversion_energy(p, minimum_jacobian=1.0, implementation="jax"))(batch)
    loop = [mesh.simplex_inversion_energy(p, minimum_jacobian=1.0, implementation="jax") for p in batch]
    np.testing.assert_allclose(energies, loop, rtol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_sobolev_deform_equals_the_functional_on_the_mesh_cells(dtype):
    plate = rectangle(3, 3, dtype=dtype)
    displacement = jnp.asarray(np.random.default_rng(7).normal(size=(16, 2)), dtype)
    fixed = jnp.arange(16) < 4
    mesh = Mesh(plate.points, plate.cells, point_data={"d": displacement, "fixed": fixed})
    out = mesh.sobolev_deform("d", length_scale=0.3, fixed_points="fixed", implementation="jax")
    expected = sobolev_deform_points(plate.points, jnp.asarray(np.asarray(plate.topology.cells_host)), displacement,
                                     length_scale=0.3, fixed_points=fixed, implementation="jax")
    np.testing.assert_allclose(out.points, expected, rtol=1e-5 if dtype == jnp.float32 else 1e-12)
    np.testing.assert_array_equal(out.points[:4], plate.points[:4])
    assert out.topology is mesh.topology
