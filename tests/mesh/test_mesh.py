"""geomjax.Mesh: construction checks, derived connectivity, caching, transformations, deformations."""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import geomjax.mesh as mesh_module
from geomjax import (
    Mesh,
    displace_points,
    free_form_deform_points,
    icosphere,
    morph_points,
    polyline,
    radial_basis_function_deform_points,
    rectangle,
)

# Outward-oriented boundary of the unit tetrahedron (0, e_x, e_y, e_z).
TETRA_POINTS = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
# Worked by hand: edge (u, v), opposite vertex in the lower-numbered face, then in the other.
TETRA_HINGES = [[0, 1, 2, 3], [0, 2, 1, 3], [0, 3, 1, 2], [1, 2, 0, 3], [1, 3, 0, 2], [2, 3, 0, 1]]


def _random(shape, dtype=jnp.float64, seed=0):
    return jnp.asarray(np.random.default_rng(seed).uniform(-1.0, 1.0, size=shape), dtype)


def _count_calls(monkeypatch, name):
    calls = []
    original = getattr(mesh_module, name)

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(mesh_module, name, counted)
    return calls


def _hinges_by_dictionary(triangles):
    """Independent hinge builder: a dictionary from undirected edges to their faces."""
    faces_of = {}
    for f, tri in enumerate(triangles.tolist()):
        for a, b, c in ((tri[0], tri[1], tri[2]), (tri[1], tri[2], tri[0]), (tri[2], tri[0], tri[1])):
            faces_of.setdefault((min(a, b), max(a, b)), []).append((f, c))
    rows = []
    for (u, v), faces in sorted(faces_of.items()):
        if len(faces) == 2:
            (_, k), (_, l) = sorted(faces)
            rows.append([u, v, k, l])
    return np.array(rows, dtype=np.int64).reshape(-1, 4)


# ---------------------------------------------------------------------------------------------
# Construction


@pytest.mark.parametrize("cell_dtype", [np.int8, np.uint16, np.int32, np.int64, np.uint64])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_construction_accepts_any_integer_cells_and_caches_int32(cell_dtype, dtype):
    mesh = Mesh(jnp.asarray(TETRA_POINTS, dtype), TETRA_FACES.astype(cell_dtype))
    assert mesh.cells.dtype == jnp.int32 and mesh.points.dtype == dtype
    np.testing.assert_array_equal(mesh.cells, TETRA_FACES)
    assert mesh.topology.cells_host.dtype == np.int64 and not mesh.topology.cells_host.flags.writeable
    assert (mesh.n_points, mesh.n_cells, mesh.n_spatial_dims, mesh.n_manifold_dims) == (4, 4, 3, 2)
    assert mesh.cells is mesh.cells


def test_construction_accepts_jax_cells_and_empty_topology():
    mesh = Mesh(jnp.zeros((0, 2)), jnp.zeros((0, 3), jnp.int32))
    assert mesh.n_points == 0 and mesh.n_cells == 0 and mesh.cells.shape == (0, 3)
    assert mesh.edges.shape == (0, 2) and mesh.hinges.shape == (0, 4)
    lonely = Mesh(jnp.zeros((5, 3)), np.zeros((0, 4), np.int64))
    assert lonely.n_manifold_dims == 3 and lonely.edges.shape == (0, 2)


@pytest.mark.parametrize(
    "points, cells, match",
    [
        (TETRA_POINTS.astype(np.float16), TETRA_FACES, "float32 or float64"),
        (TETRA_POINTS.astype(np.int32), TETRA_FACES, "float32 or float64"),
        (TETRA_POINTS, TETRA_FACES.astype(np.float64), "integer"),
        (TETRA_POINTS, TETRA_FACES.astype(bool), "non-bool"),
        (TETRA_POINTS, TETRA_FACES.tolist(), "integer array"),
    ],
)
def test_construction_type_errors(points, cells, match):
    with pytest.raises(TypeError, match=match):
        Mesh(points, cells)


def test_traced_cells_are_a_type_error():
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda c: Mesh(jnp.asarray(TETRA_POINTS), c).points)(jnp.asarray(TETRA_FACES))


def test_traced_points_are_accepted():
    out = jax.jit(lambda p: Mesh(p, TETRA_FACES).hinges)(jnp.asarray(TETRA_POINTS))
    np.testing.assert_array_equal(out, TETRA_HINGES)


@pytest.mark.parametrize(
    "points, cells, match",
    [
        (TETRA_POINTS[0], TETRA_FACES, r"\(N, D\)"),
        (TETRA_POINTS[None], TETRA_FACES, r"\(N, D\)"),
        (TETRA_POINTS, TETRA_FACES.reshape(-1), r"\(M, K\)"),
        (TETRA_POINTS, np.array([[0], [1]]), "K = 2, 3 or 4"),
        (np.zeros((6, 4)), np.array([[0, 1, 2, 3, 4]]), "K = 2, 3 or 4"),
        (TETRA_POINTS[:, :2], np.array([[0, 1, 2, 3]]), "manifold dimension 3 cannot live in 2-D"),
        (TETRA_POINTS[:, :1], TETRA_FACES, "manifold dimension 2 cannot live in 1-D"),
        (TETRA_POINTS, np.array([[0, 1, 4]]), r"index range is \[0, 4\); cell 0"),
        (TETRA_POINTS, np.array([[0, 1, 2], [0, -1, 2]]), "cell 1 is"),
        (TETRA_POINTS, np.array([[0, 1, 2], [3, 1, 3]]), "distinct vertices; cell 1"),
        (np.zeros((0, 3)), np.array([[0, 1, 2]]), r"index range is \[0, 0\)"),
    ],
)
def test_construction_value_errors(points, cells, match):
    with pytest.raises(ValueError, match=match):
        Mesh(jnp.asarray(points), cells)


def test_data_checks():
    points = jnp.asarray(TETRA_POINTS)
    mesh = Mesh(points, TETRA_FACES, point_data={"w": np.ones(4), "nested": {"d": jnp.zeros((4, 3))}},
                cell_data={"id": np.arange(4)})
    assert isinstance(mesh.point_data["w"], jax.Array) and mesh.point_data["nested"]["d"].shape == (4, 3)
    with pytest.raises(ValueError, match=r"point_data\['w'\] must have N = 4 rows"):
        Mesh(points, TETRA_FACES, point_data={"w": np.ones(3)})
    with pytest.raises(ValueError, match=r"cell_data\['id'\] must have M = 4 rows"):
        Mesh(points, TETRA_FACES, cell_data={"id": np.ones(5)})
    with pytest.raises(ValueError, match="rows"):
        Mesh(points, TETRA_FACES, point_data={"scalar": np.zeros(())})
    with pytest.raises(TypeError, match="must be an array"):
        Mesh(points, TETRA_FACES, point_data={"w": [1.0, 2.0, 3.0, 4.0]})
    with pytest.raises(TypeError, match="mapping"):
        Mesh(points, TETRA_FACES, point_data=[np.ones(4)])


# ---------------------------------------------------------------------------------------------
# Derived connectivity


def test_edges_of_each_simplex_type():
    tet = Mesh(jnp.asarray(TETRA_POINTS), np.array([[3, 1, 0, 2]]))
    np.testing.assert_array_equal(tet.edges, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    line = Mesh(jnp.zeros((4, 2)), np.array([[2, 1], [0, 1], [1, 2]]))
    np.testing.assert_array_equal(line.edges, [[0, 1], [1, 2]])
    sphere = icosphere(2)
    assert sphere.edges.shape == (3 * sphere.n_cells // 2, 2) and sphere.edges.dtype == jnp.int32


def test_hinges_of_the_tetrahedron_match_the_hand_built_list():
    np.testing.assert_array_equal(Mesh(jnp.asarray(TETRA_POINTS), TETRA_FACES).hinges, TETRA_HINGES)


def test_hinges_drop_boundary_edges():
    # Two triangles sharing edge (1, 2): one hinge, four boundary edges dropped.
    mesh = Mesh(jnp.zeros((4, 3)), np.array([[0, 1, 2], [2, 1, 3]]))
    np.testing.assert_array_equal(mesh.hinges, [[1, 2, 0, 3]])


def test_hinges_are_independent_of_the_input_winding_and_rotation():
    rng = np.random.default_rng(0)
    faces = np.asarray(icosphere(2).cells)
    flipped = np.where(rng.random(len(faces))[:, None] < 0.5, faces[:, ::-1], faces)
    rotated = np.stack([np.roll(row, shift) for row, shift in zip(flipped, rng.integers(0, 3, len(faces)))])
    reference = Mesh(jnp.zeros((162, 3)), faces).hinges
    np.testing.assert_array_equal(Mesh(jnp.zeros((162, 3)), rotated).hinges, reference)


def test_hinges_match_an_independent_builder_on_an_open_surface():
    faces = np.asarray(icosphere(1).cells)[np.random.default_rng(1).permutation(80)[:60]]
    hinges = Mesh(jnp.zeros((42, 3)), faces).hinges
    np.testing.assert_array_equal(hinges, _hinges_by_dictionary(faces))
    # Faces (u, v, k) and (v, u, l) are each a cyclic rotation of an input face, up to winding.
    face_sets = {frozenset(f) for f in faces.tolist()}
    for u, v, k, l in np.asarray(hinges).tolist():
        assert u < v and {u, v, k} in face_sets and {v, u, l} in face_sets


def test_hinge_errors():
    with pytest.raises(ValueError, match="cells 0 and 2 are the same face"):
        Mesh(jnp.zeros((4, 3)), np.array([[0, 1, 2], [2, 1, 3], [1, 2, 0]])).hinges
    fan = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(ValueError, match=r"edge \(0, 1\) belongs to 3 triangles"):
        Mesh(jnp.zeros((5, 3)), fan).hinges
    with pytest.raises(ValueError, match="triangle mesh"):
        Mesh(jnp.asarray(TETRA_POINTS), np.array([[0, 1, 2, 3]])).hinges


def _closed(faces, num_points=None):
    num_points = int(np.max(faces)) + 1 if num_points is None else num_points
    return Mesh(jnp.zeros((num_points, 3)), faces).topology.closed_surface_triangles()


def test_closed_surface_contract_accepts_closed_oriented_surfaces():
    np.testing.assert_array_equal(_closed(TETRA_FACES), TETRA_FACES)
    np.testing.assert_array_equal(_closed(TETRA_FACES[:, ::-1]), TETRA_FACES[:, ::-1])  # inward winding
    sphere = icosphere(3)
    np.testing.assert_array_equal(sphere.topology.closed_surface_triangles(), sphere.cells)


@pytest.mark.parametrize(
    "faces, match",
    [
        (np.zeros((0, 3), np.int64), "at least one triangle"),
        (TETRA_FACES[:3], r"belongs to 1, so the surface is open"),
        (np.concatenate([TETRA_FACES[:3], TETRA_FACES[3:, ::-1]]), r"consistently oriented triangles: cells 0 and 3 traverse edge \(1, 2\)"),
        (np.concatenate([TETRA_FACES, TETRA_FACES + 4]), "one edge-connected surface, got 2 components"),
        # Two tetrahedra sharing only the edge (0, 1): four triangles there.
        (np.concatenate([TETRA_FACES, np.where(TETRA_FACES >= 2, TETRA_FACES + 2, TETRA_FACES)]),
         r"edge \(0, 1\) belongs to 4, so the edge is non-manifold"),
        (np.concatenate([TETRA_FACES, TETRA_FACES[:1, [1, 2, 0]]]), "unique triangles"),
    ],
)
def test_closed_surface_contract_errors_name_the_rule(faces, match):
    with pytest.raises(ValueError, match=match):
        _closed(faces, num_points=8)


def test_component_count_on_many_components():
    faces = np.concatenate([TETRA_FACES + 4 * i for i in range(7)])
    with pytest.raises(ValueError, match="got 7 components"):
        _closed(faces)
    first, second = np.array([5, 3, 1, 0, 8]), np.array([4, 2, 0, 9, 7])
    assert mesh_module._count_components(10, first, second) == 5


# ---------------------------------------------------------------------------------------------
# Caching and transformations


def test_derived_meshes_share_the_topology_and_validate_once(monkeypatch):
    validations = _count_calls(monkeypatch, "_validate_cells")
    builds = _count_calls(monkeypatch, "_build_hinges")
    closed_checks = _count_calls(monkeypatch, "_check_closed_surface")
    mesh = Mesh(jnp.asarray(TETRA_POINTS), TETRA_FACES)
    derived = [
        mesh.displace(_random((4, 3))),
        mesh.with_points(_random((4, 3), seed=1)),
        jax.jit(lambda m: m.displace(jnp.ones((4, 3))))(mesh),
        jax.vmap(lambda d: mesh.displace(d))(_random((2, 4, 3))),
    ]
    for other in derived:
        assert other.topology is mesh.topology and other.cells is mesh.cells
        np.testing.assert_array_equal(other.hinges, TETRA_HINGES)
        other.topology.closed_surface_triangles()
    jax.jit(lambda p: Mesh(p, TETRA_FACES).points)(jnp.asarray(TETRA_POINTS))  # builds its own topology
    assert (len(validations), len(builds), len(closed_checks)) == (2, 1, 1)


def test_jit_loop_over_points_does_not_retrace_or_rebuild(monkeypatch):
    builds = _count_calls(monkeypatch, "_build_hinges")
    mesh = icosphere(1)
    traces = []

    def loss(points):
        traces.append(1)
        u, v, k, l = mesh.hinges.T
        return jnp.sum((points[u] - points[v]) ** 2) + jnp.sum((points[k] - points[l]) ** 2)

    step = jax.jit(jax.grad(loss))
    points = mesh.points
    for _ in range(4):
        points = points - 1e-3 * step(points)
    assert len(traces) == 1 and len(builds) == 1


def test_jit_with_mesh_argument_reuses_the_compilation_for_derived_meshes():
    traces = []

    @jax.jit
    def centroid(m):
        traces.append(1)
        return m.points[m.cells].mean(axis=(0, 1))

    mesh = rectangle(2, 2)
    for k in range(3):
        np.testing.assert_allclose(centroid(mesh.displace(jnp.full((9, 2), float(k)))), [0.5 + k, 0.5 + k])
    assert len(traces) == 1
    centroid(rectangle(2, 2))  # an independently built topology is a new static value
    assert len(traces) == 2


def test_grad_and_filter_grad_reach_the_points():
    mesh = Mesh(jnp.asarray(TETRA_POINTS), TETRA_FACES, point_data={"id": jnp.arange(4)})
    displacement = _random((4, 3))

    def loss_of_points(points):
        return jnp.sum(mesh.with_points(points).displace(displacement).points ** 2)

    expected = 2 * (mesh.points + displacement)
    np.testing.assert_allclose(jax.grad(loss_of_points)(mesh.points), expected)
    grads = eqx.filter_grad(lambda m: jnp.sum(m.displace(displacement).points ** 2))(mesh)
    np.testing.assert_allclose(grads.points, expected)


def test_vmap_of_a_deformation_equals_the_loop():
    mesh = rectangle(2, 1, dtype=jnp.float32)
    controls = jnp.asarray([[0.5, 0.5], [1.5, 0.5]], jnp.float32)
    displacements = _random((3, 2, 2), jnp.float32)
    batched = jax.vmap(lambda d: mesh.morph(controls, d, radius=1.0, implementation="jax"))(displacements)
    assert isinstance(batched, Mesh) and batched.points.shape == (3, 6, 2) and batched.topology is mesh.topology
    for i in range(3):
        single = mesh.morph(controls, displacements[i], radius=1.0, implementation="jax")
        np.testing.assert_allclose(batched.points[i], single.points, rtol=1e-6)
    # Vectorise a function of the batched mesh itself.
    sums = jax.vmap(lambda m: m.points.sum())(batched)
    np.testing.assert_allclose(sums, batched.points.sum(axis=(1, 2)), rtol=1e-6)


# ---------------------------------------------------------------------------------------------
# Deformation methods


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_displace_equals_the_functional_and_carries_data(dtype):
    points = _random((9, 2), dtype)
    mesh = Mesh(points, np.asarray(rectangle(2, 2).cells), point_data={"d": _random((9, 2), dtype, 1),
                "w": jnp.linspace(0, 1, 9).astype(dtype), "group": {"mask": jnp.arange(9) % 2 == 0}},
                cell_data={"c": jnp.arange(8)})
    out = mesh.displace("d", point_weights=("group", "mask"))
    expected = displace_points(points, mesh.point_data["d"], point_weights=mesh.point_data["group"]["mask"])
    np.testing.assert_array_equal(out.points, expected)
    carried = jax.tree.leaves((out.point_data, out.cell_data))
    assert all(a is b for a, b in zip(carried, jax.tree.leaves((mesh.point_data, mesh.cell_data)), strict=True))
    out = mesh.displace(mesh.point_data["d"], point_weights="w")
    np.testing.assert_array_equal(out.points, displace_points(points, mesh.point_data["d"], point_weights=mesh.point_data["w"]))


def test_missing_point_data_keys_list_the_available_ones():
    mesh = Mesh(jnp.zeros((4, 3)), TETRA_FACES, point_data={"d": jnp.zeros((4, 3)), "group": {"mask": jnp.ones(4, bool)}})
    with pytest.raises(KeyError, match=r"displacement='e' is not a point_data key; available keys: 'd', \('group', 'mask'\)"):
        mesh.displace("e")
    with pytest.raises(KeyError, match="point_weights=\\('group',\\)"):
        mesh.displace("d", point_weights=("group",))
    with pytest.raises(KeyError, match="available keys: none"):
        Mesh(jnp.zeros((4, 3)), TETRA_FACES).displace("d")


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_morph_and_rbf_equal_the_functionals(dtype):
    mesh = icosphere(1, dtype=dtype)
    controls, displacements = _random((5, 3), dtype, 2), _random((5, 3), dtype, 3) * 0.1
    weights = jnp.linspace(0, 1, 42).astype(dtype)
    mesh = Mesh(mesh.points, mesh.cells, point_data={"w": weights})
    out = mesh.morph(controls, displacements, radius=0.8, point_weights="w", implementation="jax")
    np.testing.assert_array_equal(
        out.points, morph_points(mesh.points, controls, displacements, radius=0.8, point_weights=weights, implementation="jax")
    )
    out = mesh.radial_basis_function_deform(controls, displacements, smoothing=0.1, point_weights="w", implementation="jax")
    expected = radial_basis_function_deform_points(
        mesh.points, controls, displacements, smoothing=0.1, point_weights=weights, implementation="jax"
    )
    np.testing.assert_array_equal(out.points, expected)
    assert out.topology is mesh.topology


def test_free_form_deform_derives_the_box_from_the_points_without_gradient():
    mesh = Mesh(_random((12, 3), seed=4), np.array([[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]]))
    lattice = _random((3, 2, 2, 3), seed=5)
    points = np.asarray(mesh.points)
    origin, extent = points.min(axis=0), points.max(axis=0) - points.min(axis=0)
    out = mesh.free_form_deform(lattice, implementation="jax")
    expected = free_form_deform_points(mesh.points, lattice, origin=jnp.asarray(origin), extent=jnp.asarray(extent),
                                       implementation="jax")
    np.testing.assert_array_equal(out.points, expected)
    # Only the extent derived from a given origin.
    out = mesh.free_form_deform(lattice, origin=[-2.0, -2.0, -2.0], basis="linear", implementation="jax")
    expected = free_form_deform_points(mesh.points, lattice, origin=[-2.0, -2.0, -2.0],
                                       extent=list(points.max(axis=0) + 2.0), basis="linear", implementation="jax")
    np.testing.assert_allclose(out.points, expected, rtol=1e-12)
    # The box is configuration: the gradient equals the one with a fixed box.
    def derived(p):
        return jnp.sum(mesh.with_points(p).free_form_deform(lattice, basis="cubic_hermite", implementation="jax").points ** 3)

    def fixed(p):
        return jnp.sum(free_form_deform_points(p, lattice, origin=jnp.asarray(origin), extent=jnp.asarray(extent),
                                               basis="cubic_hermite", implementation="jax") ** 3)

    np.testing.assert_allclose(jax.grad(derived)(mesh.points), jax.grad(fixed)(mesh.points), rtol=1e-12)


def test_free_form_deform_rejects_flat_derived_boxes():
    flat = polyline(5)  # all y = 0
    lattice = jnp.zeros((2, 2, 2), flat.points.dtype)
    with pytest.raises(ValueError, match="finite and positive on every axis"):
        flat.free_form_deform(lattice)
    with pytest.raises(RuntimeError, match="finite and positive on every axis"):
        jax.block_until_ready(jax.jit(lambda m: m.free_form_deform(lattice, implementation="jax").points)(flat))
    out = flat.free_form_deform(lattice, extent=[1.0, 1.0], implementation="jax")
    np.testing.assert_array_equal(out.points, flat.points)


def test_free_form_deform_of_an_empty_mesh_uses_the_unit_box():
    empty = Mesh(jnp.zeros((0, 2)), np.zeros((0, 2), np.int64))
    out = empty.free_form_deform(jnp.ones((2, 2, 2)), implementation="jax")
    assert out.points.shape == (0, 2)


def test_free_form_deform_origin_checks():
    mesh = rectangle(1, 1)
    lattice = jnp.zeros((2, 2, 2))
    with pytest.raises(ValueError, match=r"origin must have shape \(2,\)"):
        mesh.free_form_deform(lattice, origin=jnp.zeros((1, 2)))
    with pytest.raises(TypeError, match="same dtype"):
        mesh.free_form_deform(lattice, origin=jnp.zeros(2, jnp.float32))
    with pytest.raises(ValueError, match="finite"):
        mesh.free_form_deform(lattice, origin=[0.0, float("nan")])


def test_with_points_checks_the_shape():
    mesh = rectangle(1, 1)
    with pytest.raises(ValueError, match="shape of mesh.points"):
        mesh.with_points(jnp.zeros((3, 2)))
    with pytest.raises(TypeError):
        mesh.with_points(jnp.zeros((4, 2), jnp.int32))


def test_permuting_cells_keeps_the_edges():
    faces = np.asarray(icosphere(1).cells)
    for perm in itertools.islice(itertools.permutations(range(3)), 3):
        np.testing.assert_array_equal(Mesh(jnp.zeros((42, 3)), faces[:, perm]).edges, icosphere(1).edges)


@settings(max_examples=60, deadline=None)
@given(
    num_points=st.integers(0, 6),
    dims=st.integers(1, 4),
    cells=st.lists(st.lists(st.integers(-2, 7), min_size=3, max_size=3), min_size=0, max_size=8),
    cell_dtype=st.sampled_from([np.int16, np.int64, np.uint8, np.float32, np.bool_]),
)
def test_malformed_topology_raises_documented_errors(num_points, dims, cells, cell_dtype):
    cells = np.array(cells).reshape(-1, 3).astype(cell_dtype)
    try:
        mesh = Mesh(jnp.zeros((num_points, dims)), cells)
    except (TypeError, ValueError):
        return
    host = np.asarray(mesh.cells)
    assert host.shape == cells.shape and (host.size == 0 or (host.min() >= 0 and host.max() < num_points))
    for derived in (lambda: mesh.hinges, lambda: mesh.topology.closed_surface_triangles()):
        try:
            out = np.asarray(derived())
        except ValueError:
            continue
        assert out.size == 0 or (out.min() >= 0 and out.max() < num_points)
