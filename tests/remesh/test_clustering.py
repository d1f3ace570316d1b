"""remeshing / Mesh.remesh: manifold output on the surface, determinism, parity, density,
seeding paths, relaxation, barycentric transfer and validation."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from geomjax import Mesh, RemeshTopologyWarning, icosphere, rectangle, remeshing, tetrahedralized_box
from geomjax.remesh.clustering import remesh_with_sources
from benchmarks import _quality as quality
from tests.shared_meshes import requires_shared_meshes, shared_surface

pytest.importorskip("warp")

BACKENDS = ["jax", "warp"]


def _jittered_sphere(subdivisions=3, dtype=jnp.float64, seed=0, jitter=0.03):
    """An icosphere with jittered vertices: no exact symmetric ties between backends."""
    sphere = icosphere(subdivisions)
    points = np.asarray(sphere.points)
    points = points * (1 + jitter * np.random.default_rng(seed).uniform(-1, 1, (points.shape[0], 1)))
    return jnp.asarray(points, dtype), jnp.asarray(np.asarray(sphere.cells), jnp.int32)


def _edge_counts(faces):
    faces = np.asarray(faces)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return counts


def _check_surface_mesh(vertices, faces, source_vertices, source_faces, n_clusters, *, closed):
    vertices, faces = np.asarray(vertices), np.asarray(faces)
    assert 3 <= vertices.shape[0] <= n_clusters
    assert faces.ndim == 2 and faces.shape[1] == 3 and faces.min() >= 0 and faces.max() < vertices.shape[0]
    assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2]))
    assert np.array_equal(np.unique(faces), np.arange(vertices.shape[0]))  # no unused vertex
    counts = _edge_counts(faces)
    assert counts.max() <= 2
    if closed:
        assert np.all(counts == 2)
    gap = quality.surface_distances(vertices, np.asarray(source_vertices), np.asarray(source_faces)).max()
    assert gap < 1e-5 * np.abs(np.asarray(source_vertices)).max()
    stats = quality.triangle_quality(vertices, faces)
    assert stats["radius_ratio_min"] > 0


@pytest.mark.parametrize("implementation", BACKENDS)
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_sphere_remesh_is_closed_manifold_on_surface(implementation, dtype):
    vertices, faces = _jittered_sphere(dtype=dtype)
    out_vertices, out_faces = remeshing(vertices, faces, 150, implementation=implementation)
    assert out_vertices.dtype == dtype and out_faces.dtype == jnp.int32
    _check_surface_mesh(out_vertices, out_faces, vertices, faces, 150, closed=True)
    # Euler characteristic of a sphere.
    num_edges = _edge_counts(out_faces).size
    assert out_vertices.shape[0] - num_edges + out_faces.shape[0] == 2


@pytest.mark.parametrize("threshold", [256, 0])
def test_parity_and_determinism(threshold):
    """Farthest-point seeding (K <= threshold) and voxel stratification (threshold 0)."""
    vertices, faces = _jittered_sphere()
    jax_out = remesh_with_sources(vertices, faces, 120, farthest_point_threshold=threshold, implementation="jax")
    warp_out = remesh_with_sources(vertices, faces, 120, farthest_point_threshold=threshold, implementation="warp")
    np.testing.assert_array_equal(jax_out.faces, warp_out.faces)
    np.testing.assert_allclose(jax_out.vertices, warp_out.vertices, atol=1e-12)
    # Source faces may differ where a vertex sits on an edge shared by two faces (a tie); the
    # point they describe may not.
    for out in (jax_out, warp_out):
        corners = np.asarray(vertices)[np.asarray(faces)[np.asarray(out.source_faces)]]
        np.testing.assert_allclose(np.einsum("vk,vkd->vd", np.asarray(out.barycentric), corners), jax_out.vertices, atol=1e-12)
    again = remesh_with_sources(vertices, faces, 120, farthest_point_threshold=threshold, implementation="warp")
    np.testing.assert_array_equal(again.vertices, warp_out.vertices)
    np.testing.assert_array_equal(again.faces, warp_out.faces)


def test_the_background_thread_changes_nothing(monkeypatch):
    # Below BACKGROUND_MIN_VERTICES the edge graph, plane terms and patch search run on the
    # calling thread; forced onto the background thread, every output is the same to the bit,
    # and an error raised there still reaches the caller.
    from geomjax.remesh import clustering

    vertices, faces = _jittered_sphere()
    assert vertices.shape[0] < clustering.BACKGROUND_MIN_VERTICES
    inline = remesh_with_sources(vertices, faces, 120)
    monkeypatch.setattr(clustering, "BACKGROUND_MIN_VERTICES", 0)
    threaded = remesh_with_sources(vertices, faces, 120)
    for a, b in zip(inline, threaded):
        np.testing.assert_array_equal(a, b)

    def broken(*args):
        raise RuntimeError("edge graph failed")

    monkeypatch.setattr(clustering.MeshEdges, "of", broken)
    with pytest.raises(RuntimeError, match="edge graph failed"):
        remesh_with_sources(vertices, faces, 120)
    monkeypatch.setattr(clustering, "BACKGROUND_MIN_VERTICES", 10**9)
    with pytest.raises(RuntimeError, match="edge graph failed"):
        remesh_with_sources(vertices, faces, 120)


def test_source_faces_and_weights_rebuild_the_vertices():
    vertices, faces = _jittered_sphere()
    result = remesh_with_sources(vertices, faces, 80)
    weights = np.asarray(result.barycentric)
    assert np.all(weights >= -1e-12) and np.allclose(weights.sum(axis=1), 1)
    corners = np.asarray(vertices)[np.asarray(faces)[np.asarray(result.source_faces)]]
    np.testing.assert_allclose(np.einsum("vk,vkd->vd", weights, corners), result.vertices, atol=1e-12)


def test_reference_algorithm_without_relaxation():
    # A smooth surface: on one rough at the cluster scale (3% jitter on 4 vertices per cluster),
    # the relaxation keeps the roughness's "creases" where they are and gains nothing.
    vertices, faces = _jittered_sphere(4, jitter=0.01)
    plain = remesh_with_sources(vertices, faces, 150, reference=True)
    relaxed = remesh_with_sources(vertices, faces, 150)
    _check_surface_mesh(plain.vertices, plain.faces, vertices, faces, 150, closed=True)
    plain_stats = quality.triangle_quality(plain.vertices, plain.faces)
    relaxed_stats = quality.triangle_quality(relaxed.vertices, relaxed.faces)
    assert relaxed_stats["radius_ratio_mean"] > plain_stats["radius_ratio_mean"]
    assert relaxed_stats["min_angle_deg_min"] > plain_stats["min_angle_deg_min"]


def test_more_iterations_and_clusters():
    vertices, faces = _jittered_sphere(4)
    for iterations in (0, 1, 6):
        out_vertices, out_faces = remeshing(vertices, faces, 600, max_iterations=iterations, farthest_point_threshold=0)
        _check_surface_mesh(out_vertices, out_faces, vertices, faces, 600, closed=True)
    out_vertices, _ = remeshing(vertices, faces, vertices.shape[0])
    assert out_vertices.shape[0] > 0.9 * vertices.shape[0]


@pytest.mark.parametrize("implementation", BACKENDS)
def test_density_puts_more_vertices_where_it_is_larger(implementation):
    # About 9 input vertices per cluster: on coarser inputs the clusters are too few vertices to
    # follow the density (4 per cluster: 1.1x to 1.2x only, the reference algorithm's too).
    vertices, faces = _jittered_sphere(4, jitter=0.01)
    z = np.asarray(vertices)[:, 2]
    density = jnp.asarray(np.where(z > 0, 4.0, 1.0))
    out_vertices, out_faces = remeshing(vertices, faces, 300, vertex_density=density, implementation=implementation)
    _check_surface_mesh(out_vertices, out_faces, vertices, faces, 300, closed=True)
    upper = np.sum(np.asarray(out_vertices)[:, 2] > 0)
    # A 2-D CVT has point density ~ sqrt(rho): 2x here.
    assert upper > 1.7 * (out_vertices.shape[0] - upper)
    if implementation == "warp":
        # A constant density is uniform; scaling the density changes nothing.
        uniform = remeshing(vertices, faces, 300, implementation=implementation)
        constant = remeshing(vertices, faces, 300, vertex_density=jnp.full(z.shape, 3.0), implementation=implementation)
        np.testing.assert_array_equal(uniform[0], constant[0])
        scaled = remeshing(vertices, faces, 300, vertex_density=7 * density, implementation=implementation)
        np.testing.assert_allclose(scaled[0], out_vertices, atol=1e-12)


def test_open_surface_keeps_its_boundary():
    plate = rectangle(24, 24)
    # In millimetres: the relaxation's reach (half a spacing) is then far above 1, and a vertex
    # that does not move (the boundary) once made it overflow a division (a RuntimeWarning).
    points = 1000.0 * jnp.concatenate([plate.points, 0.1 * jnp.sin(3 * plate.points[:, :1])], axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out_vertices, out_faces = remeshing(points, plate.cells, 120, farthest_point_threshold=0)
    _check_surface_mesh(out_vertices, out_faces, points, plate.cells, 120, closed=False)
    counts = _edge_counts(out_faces)
    assert np.sum(counts == 1) > 0
    xy = np.asarray(out_vertices)[:, :2]
    assert xy.min() < 100.0 and xy.max() > 900.0


def test_int64_indices_give_int64_faces():
    vertices, faces = _jittered_sphere(2)
    _, out_faces = remeshing(vertices, faces.astype(jnp.int64), 40)
    assert out_faces.dtype == jnp.int64
    _, out_faces = remeshing(vertices, np.asarray(faces).astype(np.uint16), 40)
    assert out_faces.dtype == jnp.int32


def test_empty_result_is_a_runtime_error():
    triangle = np.array([[0.0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0]])
    vertices = jnp.asarray(np.concatenate([triangle + offset for offset in ([0, 0, 0], [5, 0, 0], [0, 5, 0])]))
    faces = jnp.arange(9, dtype=jnp.int32).reshape(3, 3)
    with pytest.raises(RuntimeError, match="no triangle"):
        remeshing(vertices, faces, 3)


def test_errors():
    vertices, faces = _jittered_sphere(1)
    with pytest.raises(TypeError, match="mesh_vertices"):
        remeshing(faces, faces, 10)
    with pytest.raises(TypeError, match="mesh_indices"):
        remeshing(vertices, faces.astype(jnp.float32), 10)
    with pytest.raises(ValueError, match="mesh_vertices"):
        remeshing(vertices[:2], jnp.zeros((1, 3), jnp.int32), 3)
    with pytest.raises(ValueError, match="mesh_indices"):
        remeshing(vertices, faces.reshape(-1), 10)
    with pytest.raises(ValueError, match="mesh_indices"):
        remeshing(vertices, faces.at[0, 0].set(-1), 10)
    with pytest.raises(ValueError, match="finite"):
        remeshing(vertices.at[3, 1].set(jnp.inf), faces, 10)
    with pytest.raises(ValueError, match="n_clusters"):
        remeshing(vertices, faces, vertices.shape[0] + 1)
    with pytest.raises(ValueError, match="n_clusters"):
        remeshing(vertices, faces, 2)
    with pytest.raises(TypeError, match="n_clusters"):
        remeshing(vertices, faces, True)
    with pytest.raises(ValueError, match="max_iterations"):
        remeshing(vertices, faces, 10, max_iterations=-1)
    with pytest.raises(ValueError, match="vertex_density"):
        remeshing(vertices, faces, 10, vertex_density=jnp.zeros(vertices.shape[0]))
    with pytest.raises(ValueError, match="vertex_density"):
        remeshing(vertices, faces, 10, vertex_density=jnp.ones(3))
    with pytest.raises(TypeError, match="vertex_density"):
        remeshing(vertices, faces, 10, vertex_density=jnp.ones(vertices.shape[0], jnp.int32))
    for name in ("search_radius_scale", "voxel_width_scale"):
        with pytest.raises(ValueError, match=name):
            remeshing(vertices, faces, 10, **{name: 0.0})
    with pytest.raises(ValueError, match="hash_grid_resolution"):
        remeshing(vertices, faces, 10, hash_grid_resolution=257)
    with pytest.raises(ValueError, match="farthest_point_threshold"):
        remeshing(vertices, faces, 10, farthest_point_threshold=-1)
    with pytest.raises(ValueError, match="farthest_point_oversampling"):
        remeshing(vertices, faces, 10, farthest_point_oversampling=0)
    with pytest.raises(ValueError, match="zero area"):
        remeshing(jnp.zeros_like(vertices), faces, 10)
    for implementation in BACKENDS:
        with pytest.raises(ValueError, match="remeshing: vertex coordinates must be at most 3.35e"):
            remeshing(vertices * 1e300, faces, 10, implementation=implementation)
    with pytest.raises(KeyError):
        remeshing(vertices, faces, 10, implementation="open3d")
    with pytest.raises(TypeError, match="eagerly"):
        jax.jit(lambda v: remeshing(v, faces, 10))(vertices)


# ---------------------------------------------------------------------------------------------
# Topology and features on real and stress-case surfaces


def _euler_and_boundary(faces):
    counts = _edge_counts(faces)
    return np.unique(np.asarray(faces)).size - counts.size + len(faces), int(np.sum(counts == 1))


def _smallest_angle(vertices, faces):
    return quality.triangle_quality(vertices, faces)["min_angle_deg_min"]


def _torus(major, minor, around, across):
    """A closed torus grid: ``around x across`` vertices, two triangles per grid cell."""
    u, v = np.meshgrid(np.arange(around) * 2 * np.pi / around, np.arange(across) * 2 * np.pi / across, indexing="ij")
    ring = major + minor * np.cos(v)
    points = np.stack([ring * np.cos(u), ring * np.sin(u), minor * np.sin(v)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(around), np.arange(across), indexing="ij")
    a, b = i * across + j, (i + 1) % around * across + j
    c, d = (i + 1) % around * across + (j + 1) % across, i * across + (j + 1) % across
    return points, np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]).reshape(-1, 3).astype(np.int32)


def _two_spheres():
    """Two unit spheres whose surfaces cross (centres 0.8 apart): a self-intersecting input."""
    sphere = icosphere(4)
    points, cells = np.asarray(sphere.points, np.float64), np.asarray(sphere.cells)
    return np.concatenate([points, points + [0.8, 0.0, 0.0]]), np.concatenate([cells, cells + len(points)])


def _pancake():
    """A closed sphere squashed to 2% of its width: top and bottom 50x closer than the clusters."""
    sphere = icosphere(4)
    return np.asarray(sphere.points, np.float64) * [1.0, 1.0, 0.02], np.asarray(sphere.cells)


def _duplicated_sphere():
    """icosphere(4) with every vertex stored twice, the copies unused."""
    sphere = icosphere(4)
    return np.concatenate([np.asarray(sphere.points, np.float64)] * 2), np.asarray(sphere.cells)


def _sliver_sphere():
    """icosphere(3) with each triangle split at a point 1e-4 of the way from its centroid to a
    corner: three triangles per face, two of them slivers."""
    sphere = icosphere(3)
    points, cells = np.asarray(sphere.points, np.float64), np.asarray(sphere.cells)
    centre = points[cells].mean(axis=1)
    centre += 1e-4 * (points[cells[:, 0]] - centre)
    new = len(points) + np.arange(len(cells))
    fan = [np.stack([cells[:, k], cells[:, (k + 1) % 3], new], axis=1) for k in range(3)]
    return np.concatenate([points, centre]), np.concatenate(fan)


STRESS_CASES = {
    # Euclidean clusters weld the two sides (the reference algorithm opens 45 boundary edges).
    "thin sheet": (_pancake, 200),
    # Euclidean clusters join the spheres where they cross (the reference: Euler characteristic -14).
    "self-intersecting": (_two_spheres, 300),
    "sliver triangles": (_sliver_sphere, 150),
    "duplicated vertices": (_duplicated_sphere, 200),
    # 40 clusters around a torus of tube radius 1/4: the reference opens 4 boundary edges.
    "coarse torus": (lambda: _torus(1.0, 0.25, 96, 24), 40),
}


@pytest.mark.parametrize("case", list(STRESS_CASES))
def test_stress_cases_keep_their_topology(case):
    build, n_clusters = STRESS_CASES[case]
    points, cells = build()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RemeshTopologyWarning)
        vertices, faces = remeshing(jnp.asarray(points), jnp.asarray(cells, jnp.int32), n_clusters)
    assert _euler_and_boundary(faces) == _euler_and_boundary(cells)
    _check_surface_mesh(vertices, faces, points, cells, n_clusters, closed=True)
    assert _smallest_angle(vertices, faces) > 10.0


def test_too_few_clusters_for_a_thin_tube_warn():
    # A tube 0.1 across and 40 clusters for a ring of length 2 pi: each cluster wraps the tube.
    points, cells = _torus(1.0, 0.05, 128, 8)
    with pytest.warns(RemeshTopologyWarning, match="topology differs from the input's .* use more clusters"):
        remeshing(jnp.asarray(points), jnp.asarray(cells), 60)


# Shared meshes, their cluster counts, and the largest sampled Hausdorff distance to the input in
# cluster spacings sqrt(area / K) (measured 0.22 to 0.66; a cut-off tip or a hole is about one
# spacing or more: before the surface clusters and quadric points, at 2000 clusters, 0.85 on
# fertility and 2.1 on the screwdriver, with 8 and 6 boundary edges).
REAL_MESHES = [
    ("fertility.off", 2000, 0.5),  # closed, genus 4
    ("screwdriver.off", 2000, 0.5),  # CAD: sharp edges and a thin tip
    ("camelhead.off", 1000, 0.9),  # open (one boundary loop)
    ("decimated-knight.off", 250, 0.9),  # two input vertices per cluster
]


@requires_shared_meshes
@pytest.mark.parametrize(("name", "n_clusters", "max_spacings"), REAL_MESHES)
def test_real_meshes_keep_topology_and_features(name, n_clusters, max_spacings):
    points, cells = shared_surface(name)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RemeshTopologyWarning)
        vertices, faces = remeshing(jnp.asarray(points), jnp.asarray(cells), n_clusters)
    euler, boundary = _euler_and_boundary(cells)
    out_euler, out_boundary = _euler_and_boundary(faces)
    assert out_euler == euler and (out_boundary == 0) == (boundary == 0)
    _check_surface_mesh(vertices, faces, points, cells, n_clusters, closed=boundary == 0)
    assert _smallest_angle(vertices, faces) > 10.0
    spacing = np.sqrt(quality.surface_area(points, cells) / n_clusters)
    hausdorff = quality.hausdorff_distance(points, cells, vertices, faces, num_probes=20_000)
    assert hausdorff < max_spacings * spacing


# ---------------------------------------------------------------------------------------------
# Mesh.remesh


def test_mesh_remesh_transfers_point_data_exactly_for_linear_fields():
    vertices, faces = _jittered_sphere()
    field = vertices @ jnp.array([1.0, -2.0, 0.5])
    mesh = Mesh(vertices, np.asarray(faces), point_data={"f": field, "nested": {"xyz": vertices}, "skip": field})
    coarse = mesh.remesh(100, point_data_keys=["f", ("nested", "xyz")])
    assert isinstance(coarse, Mesh) and coarse.n_points <= 100
    assert set(coarse.point_data) == {"f", "nested"}
    # Linear fields are reproduced exactly on the (flat) source triangles.
    np.testing.assert_allclose(coarse.point_data["f"], coarse.points @ jnp.array([1.0, -2.0, 0.5]), atol=1e-12)
    np.testing.assert_allclose(coarse.point_data["nested"]["xyz"], coarse.points, atol=1e-12)
    assert _edge_counts(coarse.cells).max() <= 2


def test_mesh_remesh_is_differentiable_in_the_field():
    vertices, faces = _jittered_sphere(2)
    result = remesh_with_sources(vertices, faces, 40)

    def transferred(field):
        mesh = Mesh(vertices, np.asarray(faces), point_data={"f": field})
        return mesh.remesh(40, point_data_keys=["f"]).point_data["f"]

    field = jnp.asarray(np.random.default_rng(0).normal(size=vertices.shape[0]))
    check_grads(lambda f: jnp.sum(jnp.sin(transferred(f))), (field,), order=1, modes=["rev"])
    # d(sum of transferred values) / d(field) = total barycentric weight each source vertex gets.
    expected = np.zeros(vertices.shape[0])
    np.add.at(expected, np.asarray(faces)[np.asarray(result.source_faces)].reshape(-1), np.asarray(result.barycentric).reshape(-1))
    np.testing.assert_allclose(jax.grad(lambda f: jnp.sum(transferred(f)))(field), expected, atol=1e-12)


def test_mesh_remesh_resolution_field_and_errors():
    vertices, faces = _jittered_sphere(4)
    z = vertices[:, 2]
    mesh = Mesh(vertices, np.asarray(faces), point_data={"r": jnp.where(z > 0, 2.0, 1.0), "i": jnp.arange(z.shape[0])})
    fine_top = mesh.remesh(300, resolution_field="r")
    upper = np.sum(np.asarray(fine_top.points)[:, 2] > 0)
    assert upper > 2.5 * (fine_top.n_points - upper)  # density r^4 = 16x, so about 4x the points
    by_density = mesh.remesh(300, vertex_density="r")
    assert np.sum(np.asarray(by_density.points)[:, 2] > 0) < upper
    with pytest.raises(ValueError, match="at most one"):
        mesh.remesh(50, vertex_density="r", resolution_field="r")
    with pytest.raises(KeyError, match="missing"):
        mesh.remesh(50, point_data_keys=["missing"])
    with pytest.raises(TypeError, match="floating"):
        mesh.remesh(50, point_data_keys=["i"])
    with pytest.raises(TypeError, match="point_data_keys"):
        mesh.remesh(50, point_data_keys=[3])
    with pytest.raises(NotImplementedError):
        tetrahedralized_box(2, 2, 2).remesh(5)
    with pytest.raises(NotImplementedError):
        rectangle(3, 3).remesh(5)


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_low_precision_vertex_density_is_accepted(implementation):
    # The reference accepts any real floating-point density: float16, bfloat16 and float8 values
    # are read exactly (each is a float32) and remesh as those values given in float32.
    from tests.op_cases import CASES

    case = CASES["remeshing"](jnp.float64)
    vertices, faces, clusters = case.arrays[0], case.fixed["mesh_indices"], case.fixed["n_clusters"]
    density = 0.5 + jnp.abs(vertices[:, 0])  # non-constant: a constant density is uniform remeshing
    for dtype in (jnp.float16, jnp.bfloat16, jnp.float8_e4m3fn):
        narrow = density.astype(dtype)
        ours = remeshing(vertices, faces, clusters, vertex_density=narrow, implementation=implementation)
        expected = remeshing(vertices, faces, clusters, vertex_density=narrow.astype(jnp.float32), implementation=implementation)
        for a, b in zip(ours, expected):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=str(dtype))
    with pytest.raises(TypeError, match="vertex_density"):
        remeshing(vertices, faces, clusters, vertex_density=jnp.ones(len(vertices), jnp.int32), implementation=implementation)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_face_geometry_kernel_gives_numpy_s_bits(dtype, monkeypatch):
    # The masses and planes come from the faces' corners, doubled normals and areas: the Warp
    # kernel rounds each step as NumPy does (with warp-lang missing), so that the remesh is the
    # same either way; and both are the geometry (an independent float64 cross product).
    pytest.importorskip("warp")
    import geomjax.remesh.clustering as clustering

    vertices, faces = _jittered_sphere(dtype=dtype)
    vertices, faces = np.asarray(vertices) * 1e3, np.asarray(faces)
    monkeypatch.setattr(clustering, "FACE_KERNEL_MIN_FACES", 0)
    kernel = clustering._face_geometry(vertices, faces)
    monkeypatch.setattr(clustering, "warp_available", lambda: False)
    twin = clustering._face_geometry(vertices, faces)
    for ours, theirs in zip(kernel, twin, strict=True):
        assert ours.dtype == theirs.dtype == np.float64
        np.testing.assert_array_equal(ours, theirs)
    corners = vertices.astype(np.float64)[faces]
    doubled = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    np.testing.assert_array_equal(kernel[0], corners[:, 0])
    np.testing.assert_allclose(kernel[1], doubled, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(kernel[2], np.linalg.norm(doubled, axis=1) / 2, rtol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("num_centroids", [40, 600])
def test_nearest_centroids_with_previous_labels_are_exact(dtype, num_centroids):
    # Lloyd's warp assignment, given the previous labels, skips the search for points much
    # closer to their old cluster's moved centroid than that centroid is to any other (600
    # centroids: 5 points each), or measures only the neighbours of that centroid within twice
    # the point's distance (40: 75 points each, neighbour lists); the answer must stay the
    # brute-force nearest (ties: lowest index), also after a big move. One search object serves
    # the steps, as in the remesher: the labels it returned go back in without a copy.
    from warp_ffi.host import NEIGHBOUR_LIST_MIN_POINTS, CentroidSearch

    from geomjax._hash_grid import table_dims

    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, (3000, 3)).astype(dtype)
    assert (3000 >= NEIGHBOUR_LIST_MIN_POINTS * num_centroids) == (num_centroids == 40)
    centroids = points[rng.choice(3000, num_centroids, replace=False)]
    radius = 0.5
    dims = table_dims(points.min(0) - radius, points.max(0) + radius, radius, (32,) * 3)
    search = CentroidSearch(points, radius, radius, dims, "cpu")
    labels = None
    for step in range(4):
        found = search(centroids, labels)
        offsets = points[:, None, :].astype(np.float64) - centroids[None].astype(np.float64)
        np.testing.assert_array_equal(found, np.argmin(np.sum(offsets**2, axis=2), axis=1))
        if step == 0:
            # Any labels serve as a start (the remesher's first search starts from a guess).
            np.testing.assert_array_equal(search(centroids, rng.integers(0, num_centroids, 3000)), found)
            found = search(centroids)  # the last labels returned: the next step passes them back
        labels = found
        moved = np.array([points[labels == k].mean(axis=0) if np.any(labels == k) else centroids[k] for k in range(num_centroids)], dtype)
        # One centroid jumps across the box: its old members must find their new nearest.
        centroids = np.where(np.arange(num_centroids)[:, None] == step, -moved, moved).astype(dtype)


@pytest.mark.parametrize("final", [False, True])
def test_lloyd_stops_at_a_fixed_point_with_the_full_loop_s_result(final, monkeypatch):
    # Labels that repeat give back the centroids they were assigned to: the Lloyd loops stop
    # there. Against a plain loop of all the iterations (brute-force nearest, per-cluster means),
    # whose last assignment is to the final centroids if final, else to those before its means.
    from geomjax._hash_grid import table_dims
    from geomjax.remesh import clustering
    from geomjax.remesh._surface_clusters import VertexMoments

    rng = np.random.default_rng(5)
    points = rng.uniform(-1, 1, (3000, 3))
    mass = rng.uniform(0.5, 1.5, 3000)
    start = points[rng.choice(3000, 40, replace=False)]
    iterations = 100

    def nearest(centroids):
        return np.argmin(np.sum((points[:, None, :] - centroids[None]) ** 2, axis=2), axis=1)

    centroids, labels = start, nearest(start)
    for iteration in range(iterations):
        centroids = np.array([np.sum(points[labels == k] * mass[labels == k, None], axis=0) / np.sum(mass[labels == k]) for k in range(40)])
        if final or iteration < iterations - 1:
            labels = nearest(centroids)

    calls = []
    means = clustering.cluster_means
    monkeypatch.setattr(clustering, "cluster_means", lambda *args: calls.append(1) or means(*args))
    moments = VertexMoments.of(points, mass)
    dims = table_dims(points.min(0) - 0.5, points.max(0) + 0.5, 1.0, (32,) * 3)
    cpu = jax.devices("cpu")[0]
    for lloyd in (
        lambda: clustering._lloyd_warp(points, moments, start, iterations, 0.5, 32, cpu, final),
        lambda: clustering._lloyd_jax(points, moments, start, iterations, cpu, final),
    ):
        calls.clear()
        found, label = lloyd()
        assert len(calls) < iterations // 2  # it stopped early
        np.testing.assert_array_equal(label, labels)
        np.testing.assert_allclose(found, centroids, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_nearest_centroids_break_exact_ties_alike_on_both_backends(dtype):
    # Each point (t, t, t) is, in exact arithmetic, as far from the six permutations of a
    # centroid's coordinates: which one wins is decided by the rounding. Both backends must
    # round each squared component and sum left to right, as NumPy below (XLA once fused a
    # product into the sum and broke a quarter of these ties otherwise), then take the lowest
    # index among equals; regular meshes are full of such ties.
    import itertools

    from warp_ffi.host import nearest_centroids

    from geomjax._hash_grid import table_dims
    from geomjax.remesh.clustering import _nearest_jax

    rng = np.random.default_rng(0)
    triples = rng.uniform(-1, 1, (8, 3))
    centroids = np.concatenate([triple[list(order)][None] for triple in triples for order in itertools.permutations(range(3))]).astype(dtype)
    t = rng.uniform(-1, 1, 4000)
    points = np.stack([t, t, t], axis=1).astype(dtype)
    squares = (centroids[None] - points[:, None]) ** 2
    expected = np.argmin((squares[..., 0] + squares[..., 1]) + squares[..., 2], axis=1)
    np.testing.assert_array_equal(np.asarray(_nearest_jax(jnp.asarray(points), jnp.asarray(centroids))), expected)
    radius = 3.0
    dims = table_dims(points.min(0) - radius, points.max(0) + radius, radius, (8,) * 3)
    np.testing.assert_array_equal(nearest_centroids(points, centroids, radius, radius, dims, "cpu"), expected)
    # With previous labels (83 points per centroid: the neighbour lists), here the centroid
    # below the answer (often a tied permutation), the lowest tied index must still win.
    previous = np.maximum(expected - 1, 0)
    np.testing.assert_array_equal(nearest_centroids(points, centroids, radius, radius, dims, "cpu", previous), expected)
