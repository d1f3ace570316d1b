"""mesh_to_voxel_fraction: fraction of each voxel inside a triangle mesh."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from geomjax import icosphere, mesh_to_voxel_fraction
from geomjax.query.voxel import sample_points

BACKENDS = ["jax", "warp"]
TRACED_ERRORS = (RuntimeError, ValueError)

# Closed unit cube [0, 1]^3, outward normals.
CUBE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
CUBE_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [2, 3, 7], [2, 7, 6], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]])


def _sphere(subdivisions):
    mesh = icosphere(subdivisions)
    return mesh.points, jnp.asarray(mesh.cells, jnp.int32)


def _volume(vertices, faces):
    v, f = np.asarray(vertices, np.float64), np.asarray(faces)
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6)


@pytest.mark.parametrize("implementation", BACKENDS)
def test_windows_deep_inside_and_far_outside(implementation):
    vertices, faces = _sphere(2)
    # A single 0.1 voxel at the centre of the unit sphere (the reference reads 0 here).
    centre = mesh_to_voxel_fraction(vertices, faces, [-0.05, -0.05, -0.05], 0.1, (1, 1, 1), implementation=implementation)
    assert centre.shape == (1, 1, 1) and centre.dtype == jnp.float32 and float(centre[0, 0, 0]) == 1.0
    inside = mesh_to_voxel_fraction(vertices, faces, [-0.3, -0.2, -0.1], 0.1, (6, 4, 2), implementation=implementation)
    np.testing.assert_array_equal(inside, 1.0)
    outside = mesh_to_voxel_fraction(vertices, faces, [3.0, 3.0, 3.0], 0.5, (2, 2, 2), implementation=implementation)
    np.testing.assert_array_equal(outside, 0.0)


@pytest.mark.parametrize("implementation", BACKENDS)
def test_centre_of_a_sphere_equally_close_to_many_faces_is_inside(implementation):
    # Regression: Warp's closed mode took the pseudo-normal sign at the voxel centre, which reads
    # "outside" at the exact centre of an icosphere (many equally close faces).
    vertices, faces = _sphere(1)
    fractions = mesh_to_voxel_fraction(vertices, faces, [-0.9, -0.9, -0.9], 0.6, (3, 3, 3), n_samples=8, implementation=implementation)
    assert float(fractions[1, 1, 1]) == 1.0


@pytest.mark.parametrize("implementation", BACKENDS)
def test_self_intersecting_closed_mesh_is_the_union(implementation):
    # Two interpenetrating closed cubes as one mesh. Voxel faces lie on the cubes' faces, so each
    # voxel is wholly inside the union or wholly outside. A centre whose closest face belongs to
    # the other cube (e.g. (0.625, 0.625, 0.375), 0.125 below cube B's bottom, inside cube A) is
    # outside by that face's normal; the winding number (1 there) says inside.
    second = CUBE + 0.5
    vertices = jnp.asarray(np.concatenate([CUBE, second]))
    faces = jnp.asarray(np.concatenate([CUBE_FACES, CUBE_FACES + len(CUBE)]))
    fractions = mesh_to_voxel_fraction(vertices, faces, [-0.25, -0.25, -0.25], 0.25, (8, 8, 8), n_samples=8, implementation=implementation)
    centres = -0.125 + 0.25 * np.arange(8)
    z, y, x = np.meshgrid(centres, centres, centres, indexing="ij")
    in_first = (x > 0) & (x < 1) & (y > 0) & (y < 1) & (z > 0) & (z < 1)
    in_second = (x > 0.5) & (x < 1.5) & (y > 0.5) & (y < 1.5) & (z > 0.5) & (z < 1.5)
    np.testing.assert_array_equal(np.asarray(fractions), (in_first | in_second).astype(np.float32))


def _box_overlap(lower, upper, box_lower, box_upper):
    """Volume of ``[lower, upper]`` (arrays of boxes, ``(..., 3)``) inside ``[box_lower, box_upper]``."""
    return np.prod(np.clip(np.minimum(upper, box_upper) - np.maximum(lower, box_lower), 0.0, None), axis=-1)


def _overlapping_cubes(shift, size, origin, n, implementation):
    """Fractions of cubes A = [0, 1]^3 and B = A + shift (one mesh) on an ``n^3`` grid with 64
    samples, and the exact fractions (vol(A & V) + vol(B & V) - vol(A & B & V)) / vol(V).

    The callers place every face on a boundary of the 4 x 4 x 4 sub-cubes of the stratified
    sampling: each sub-cube is then wholly inside the union or wholly outside, its one sample
    says which, and the estimate equals the exact fraction.
    """
    vertices = jnp.asarray(np.concatenate([CUBE, CUBE + shift]))
    faces = jnp.asarray(np.concatenate([CUBE_FACES, CUBE_FACES + len(CUBE)]))
    fractions = mesh_to_voxel_fraction(vertices, faces, [origin] * 3, size, (n, n, n), n_samples=64, implementation=implementation)
    # Precondition: no sample lies on a face's plane (float32 rounding could put one there).
    _lower, samples = sample_points(jnp.full(3, origin, jnp.float32), size, (n, n, n), 64, 4, 42)
    assert not np.isin(np.asarray(samples), np.float32([0.0, shift, 1.0, 1.0 + shift])).any()
    k, j, i = np.meshgrid(*(np.arange(float(n)),) * 3, indexing="ij")
    lower = origin + size * np.stack([i, j, k], axis=-1)
    upper = lower + size
    in_a, in_b = _box_overlap(lower, upper, 0.0, 1.0), _box_overlap(lower, upper, shift, 1.0 + shift)
    return np.asarray(fractions), (in_a + in_b - _box_overlap(lower, upper, shift, 1.0)) / size**3


@pytest.mark.parametrize("implementation", BACKENDS)
def test_samples_across_an_inner_face_of_overlapping_closed_parts(implementation):
    # Regression: Warp's closed mode flipped the voxel centre's inside state by the parity of the
    # triangles crossed on the way to a sample. Cubes A and B = A + 0.25 have winding number 2 in
    # A & B, so a sample one crossing away from a centre in A & B (e.g. (0.375, 0.375, 0.375),
    # 0.125 inside B's lower faces) has winding number 1 and is inside. Every face lies on an odd
    # multiple of 1/8 from the origin: never on a voxel face or centre (multiples of 1/4, voxel
    # size 1/2), always on a sub-cube boundary (1/8).
    shift, size = 0.25, 0.5
    fractions, exact = _overlapping_cubes(shift, size, -0.375, 4, implementation)
    np.testing.assert_allclose(fractions, exact, rtol=0, atol=1e-6)
    assert abs(float(fractions.sum()) * size**3 - (2.0 - (1.0 - shift) ** 3)) < 1e-6


@pytest.mark.parametrize("implementation", BACKENDS)
def test_centres_on_faces_of_overlapping_closed_parts(implementation):
    # Warp's closed mode carries the winding number along each row and restarts it with a fresh
    # query after a centre on the surface (its voxel queries every sample). Cubes A and
    # B = A + 3/16, voxel size 1/4 from -3/8: A's faces pass through voxel centres (2 mod 4
    # sixteenths from the origin), B's through voxels on sub-cube boundaries (1 mod 4). On the
    # row y = z = 1/2 the centre x = 0 lies on A, and the next voxel (x = 1/4, marked by B's face
    # at 3/16) restarts in A & B with winding number 2: a restart that kept only the inside state
    # (1) would read its samples behind B's face (in A only) as outside.
    fractions, exact = _overlapping_cubes(0.1875, 0.25, -0.375, 8, implementation)
    np.testing.assert_allclose(fractions, exact, rtol=0, atol=1e-6)
    # The row y = z = 1/2, as described: centre x = 0 on A's face, then the restart in A & B.
    np.testing.assert_array_equal(fractions[3, 3], [0.0, 0.5, 1.0, 1.0, 1.0, 1.0, 0.25, 0.0])


def _octahedron(centre, rng):
    """A closed octahedron (unit radius, outward faces) with its vertices and each face's
    corners in a random order, so that every canonical edge order occurs."""
    corners = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    faces = []
    for sx, sy, sz in np.ndindex(2, 2, 2):
        face = [sx, 2 + sy, 4 + sz]
        faces.append(face if (sx + sy + sz) % 2 == 0 else face[::-1])
    order = rng.permutation(6)  # new index of each corner
    vertices = np.empty_like(corners)
    vertices[order] = corners + centre
    faces = np.array([np.roll(order[f], rng.integers(3)) for f in faces])
    return vertices, faces


def test_rows_through_mesh_vertices_count_each_crossing_once():
    # Warp carries the winding number along each row by counting crossings; here the row's line
    # passes exactly through the octahedra's tips (shared by four faces), where a crossing must
    # count once whatever the vertex order. The JAX path (every sample's own winding number) is
    # the reference; 40 random vertex and corner orders.
    rng = np.random.default_rng(0)
    for _ in range(40):
        first, second = _octahedron([0.0, 0.0, 0.0], rng), _octahedron([3.0, 0.0, 0.0], rng)
        vertices = np.concatenate([first[0], second[0]])
        faces = jnp.asarray(np.concatenate([first[1], second[1] + 6]))
        options = dict(origin=[-1.5, -0.25, -0.25], voxel_size=0.5, grid_dims=(10, 1, 1), n_samples=27)
        warp = mesh_to_voxel_fraction(jnp.asarray(vertices, jnp.float32), faces, **options, implementation="warp")
        reference = mesh_to_voxel_fraction(jnp.asarray(vertices), faces, **options, implementation="jax")
        np.testing.assert_allclose(np.asarray(warp), np.asarray(reference), rtol=0, atol=1e-6)


def test_a_hole_in_a_closed_mode_mesh_stays_local():
    # A sphere with a small hole at (-1, 0, 0) (6 faces removed; the voxels around it are still
    # marked by its rim), voxelised in closed mode: rows through the hole enter the sphere without
    # crossing a triangle. Warp's row chain must not carry that miscount along the row (it checks
    # each chain against a query where it ends, and walks a failing row again with a query per
    # marked centre): away from the hole, where the winding number is within the hole's solid
    # angle (< 0.05) of 0 or 1, Warp agrees with the JAX path (each sample's own winding number).
    # Without the check, 44 of these voxels read outside.
    vertices, faces = _sphere(3)
    points = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)
    hole = np.array([-1.0, 0.0, 0.0])
    kept = faces[np.linalg.norm(points[faces].mean(axis=1) - hole, axis=1) > 0.1]
    options = dict(origin=[-1.2] * 3, voxel_size=0.15, grid_dims=(16, 16, 16), n_samples=8)
    warp = np.asarray(mesh_to_voxel_fraction(jnp.asarray(points, jnp.float32), jnp.asarray(kept), **options, implementation="warp"))
    reference = np.asarray(mesh_to_voxel_fraction(jnp.asarray(points), jnp.asarray(kept), **options, implementation="jax"))
    centres = -1.2 + 0.15 * (np.arange(16) + 0.5)
    z, y, x = np.meshgrid(centres, centres, centres, indexing="ij")
    far = np.sqrt((x - hole[0]) ** 2 + (y - hole[1]) ** 2 + (z - hole[2]) ** 2) > 0.45
    through_hole = far & (np.abs(y) < 0.2) & (np.abs(z) < 0.2) & (np.abs(x) < 0.8)
    assert through_hole.sum() >= 8 and reference[through_hole].min() == 1.0  # rows past the hole, inside
    np.testing.assert_allclose(warp[far], reference[far], rtol=0, atol=1e-6)


@pytest.mark.parametrize("implementation", BACKENDS)
def test_z_major_layout_and_stratified_exact_half(implementation):
    # Box x in [0, 1.5] on a grid of unit voxels starting at x = 0: voxel 0 is inside, voxel 1
    # half inside (the box face lies on a sub-cube boundary, so stratified samples give exactly
    # one half whatever the jitter), voxels 2 and 3 outside; y and z spans are full.
    box = jnp.asarray(CUBE * [1.5, 3.0, 2.0] - [0.0, 0.5, 0.5])
    fractions = mesh_to_voxel_fraction(box, jnp.asarray(CUBE_FACES), [0.0, 0.0, 0.0], 1.0, (4, 2, 1), n_samples=64, implementation=implementation)
    assert fractions.shape == (1, 2, 4)
    np.testing.assert_array_equal(fractions, [[[1.0, 0.5, 0.0, 0.0], [1.0, 0.5, 0.0, 0.0]]])


def test_backends_agree_and_seed_is_deterministic():
    vertices, faces = _sphere(2)
    args = (vertices, faces, [-1.1, -1.05, -1.0], 0.3, (8, 7, 7))
    warp = mesh_to_voxel_fraction(*args, n_samples=27, seed=7, implementation="warp")
    jax_ = mesh_to_voxel_fraction(*args, n_samples=27, seed=7, implementation="jax")
    np.testing.assert_allclose(warp, jax_, atol=1e-6)
    assert np.sum((warp > 0) & (warp < 1)) > 50
    np.testing.assert_array_equal(warp, mesh_to_voxel_fraction(*args, n_samples=27, seed=7, implementation="warp"))
    assert not np.array_equal(warp, mesh_to_voxel_fraction(*args, n_samples=27, seed=8, implementation="warp"))
    # Unequal samples per sub-cube (20 samples over 8 sub-cubes) agree too.
    np.testing.assert_allclose(
        mesh_to_voxel_fraction(*args, n_samples=20, implementation="warp"), mesh_to_voxel_fraction(*args, n_samples=20, implementation="jax"), atol=1e-6
    )


def test_sample_positions_are_stratified_inside_the_voxel():
    lower, samples = sample_points(jnp.asarray([1.0, 2.0, 3.0]), 0.5, (2, 1, 1), 27, 3, 42)
    np.testing.assert_allclose(lower, [[1.0, 2.0, 3.0], [1.5, 2.0, 3.0]])
    local = (np.asarray(samples) - np.asarray(lower)[:, None, :]) / 0.5
    assert local.min() >= 0 and local.max() < 1
    cells = np.floor(local * 3).astype(int)
    for voxel in range(2):
        np.testing.assert_array_equal(np.sort(cells[voxel] @ [1, 3, 9]), np.arange(27))


def test_sphere_volume_from_fractions():
    vertices, faces = _sphere(3)
    h = 2.2 / 20
    fractions = mesh_to_voxel_fraction(vertices, faces, [-1.1, -1.1, -1.1], h, (20, 20, 20), n_samples=64)
    exact = _volume(vertices, faces)
    assert abs(float(fractions.sum()) * h**3 - exact) < 2e-3 * exact
    assert fractions.min() >= 0 and fractions.max() <= 1


def _imperfect_sphere():
    vertices, faces = _sphere(2)
    f = np.asarray(faces).copy()
    f[[3, 50, 120, 200]] = f[[3, 50, 120, 200]][:, ::-1]  # flipped faces
    f = np.delete(f, [10, 77, 150], axis=0)  # holes
    return vertices, jnp.asarray(f)


def test_open_mode_on_an_imperfect_mesh():
    vertices, faces = _imperfect_sphere()
    args = (vertices, faces, [-1.1, -1.1, -1.1], 0.275, (8, 8, 8))
    warp = mesh_to_voxel_fraction(*args, n_samples=27, open_mesh=True, implementation="warp")
    jax_ = mesh_to_voxel_fraction(*args, n_samples=27, open_mesh=True, implementation="jax")
    # Warp's winding number is the Barnes-Hut approximation: a rare sample near the threshold may differ.
    assert np.abs(np.asarray(warp) - np.asarray(jax_)).max() <= 2 / 27 + 1e-6
    exact = _volume(*_sphere(2))
    for fractions in (warp, jax_):
        assert abs(float(fractions.sum()) * 0.275**3 - exact) < 0.02 * exact
    # The centre of the holed sphere is still inside.
    centre = mesh_to_voxel_fraction(vertices, faces, [-0.05] * 3, 0.1, (1, 1, 1), open_mesh=True, implementation="warp")
    assert float(centre[0, 0, 0]) == 1.0
    # A high threshold shrinks the inside.
    strict = mesh_to_voxel_fraction(*args, n_samples=27, open_mesh=True, winding_number_threshold=0.99, implementation="jax")
    assert float(strict.sum()) <= float(jax_.sum())


@pytest.mark.parametrize("implementation", BACKENDS)
def test_jit_and_flat_indices(implementation):
    vertices, faces = _sphere(1)
    run = jax.jit(lambda v, f: mesh_to_voxel_fraction(v, f, jnp.asarray([-1.0, -1.0, -1.0]), 0.5, (4, 4, 4), n_samples=8, implementation=implementation))
    eager = mesh_to_voxel_fraction(vertices, faces.reshape(-1), [-1.0, -1.0, -1.0], 0.5, jnp.array([4, 4, 4]), n_samples=8, implementation=implementation)
    np.testing.assert_array_equal(run(vertices, faces), eager)
    np.testing.assert_array_equal(run(vertices.astype(jnp.float32), faces), eager)


def test_type_errors():
    v, f = jnp.asarray(CUBE), jnp.asarray(CUBE_FACES)
    call = lambda **kw: mesh_to_voxel_fraction(  # noqa: E731
        kw.pop("v", v), kw.pop("f", f), kw.pop("origin", [0.0, 0, 0]), kw.pop("voxel_size", 0.5), kw.pop("grid_dims", (2, 2, 2)), **kw
    )
    for kwargs, match in [
        ({"v": jnp.zeros((8, 3), jnp.int32)}, "mesh_vertices"),
        ({"f": f.astype(jnp.float32)}, "mesh_indices"),
        ({"origin": jnp.zeros(3, jnp.int32)}, "origin"),
        ({"origin": "abc"}, "origin"),
        ({"voxel_size": True}, "voxel_size"),
        ({"grid_dims": (2, 2.0, 2)}, "grid_dims"),
        ({"grid_dims": jnp.array([2.0, 2, 2])}, "grid_dims"),
        ({"n_samples": 8.0}, "n_samples"),
        ({"seed": "1"}, "seed"),
        ({"open_mesh": 1}, "open_mesh"),
        ({"winding_number_threshold": None}, "winding_number_threshold"),
        ({"origin": [0.0, 0.0]}, "origin must contain exactly 3 real values"),  # the reference's type
    ]:
        with pytest.raises(TypeError, match=match):
            call(**kwargs)
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda g: mesh_to_voxel_fraction(v, f, [0.0, 0, 0], 0.5, g))(jnp.array([2, 2, 2]))


def test_value_errors():
    v, f = jnp.asarray(CUBE), jnp.asarray(CUBE_FACES)
    call = lambda **kw: mesh_to_voxel_fraction(  # noqa: E731
        kw.pop("v", v), kw.pop("f", f), kw.pop("origin", [0.0, 0, 0]), kw.pop("voxel_size", 0.5), kw.pop("grid_dims", (2, 2, 2)), **kw
    )
    for kwargs, match in [
        ({"v": jnp.zeros((0, 3))}, "mesh_vertices must have shape"),
        ({"v": jnp.zeros((8, 2))}, "mesh_vertices must have shape"),
        ({"f": jnp.zeros((0, 3), jnp.int32)}, "mesh_indices must have shape"),
        ({"f": jnp.zeros(7, jnp.int32)}, "mesh_indices must have shape"),
        ({"f": f.at[0, 0].set(8)}, r"must lie in \[0, 8\)"),
        ({"f": f.at[0, 0].set(-1)}, r"must lie in \[0, 8\)"),
        ({"v": v.at[0, 0].set(jnp.nan)}, "must be finite"),
        ({"origin": jnp.zeros(2)}, "origin must have shape"),
        ({"voxel_size": 0.0}, "voxel_size must be positive"),
        ({"voxel_size": float("nan")}, "voxel_size must be finite"),
        ({"grid_dims": (2, 0, 2)}, "at least 1"),
        ({"grid_dims": (2, 2)}, "3 entries"),
        ({"grid_dims": (2**11, 2**11, 2**11)}, "voxels"),
        ({"n_samples": 0}, "at least 1"),
        ({"winding_number_threshold": float("inf")}, "finite"),
        ({"winding_number_accuracy": 0.0}, "positive"),
    ]:
        with pytest.raises(ValueError, match=match):
            call(**kwargs)
    with pytest.raises(KeyError):
        call(implementation="cuda")


@pytest.mark.parametrize("implementation", BACKENDS)
def test_traced_out_of_range_indices_raise_without_crashing(implementation):
    v = jnp.asarray(CUBE)
    run = jax.jit(lambda f: mesh_to_voxel_fraction(v, f, [0.0, 0, 0], 0.5, (2, 2, 2), n_samples=8, implementation=implementation))
    with pytest.raises(TRACED_ERRORS, match="mesh_indices must lie in"):
        jax.block_until_ready(run(jnp.asarray(CUBE_FACES).at[3, 1].set(100)))


@pytest.mark.parametrize("implementation", BACKENDS)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    v_shape=st.sampled_from([(8, 3), (0, 3), (8, 2), (2, 8, 3)]),
    dtype=st.sampled_from([jnp.float32, jnp.float64, jnp.float16, jnp.int32]),
    fill=st.sampled_from([0.0, np.nan, np.inf, 1e30, -1e30]),
    faces=st.sampled_from([CUBE_FACES, CUBE_FACES + 1, -CUBE_FACES, CUBE_FACES.reshape(-1)[:35], np.zeros((4, 3), int)]),
    voxel_size=st.sampled_from([0.25, 0.0, -1.0, np.nan, 1e-30, 1e30]),
    grid=st.sampled_from([(2, 3, 1), (0, 1, 1), (1, 1), (2, 2, 2)]),
    origin=st.sampled_from([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [1e30, 0.0, 0.0], [0.0]]),
)
def test_bad_input_never_crashes(implementation, v_shape, dtype, fill, faces, voxel_size, grid, origin):
    vertices = jnp.asarray(np.resize(CUBE, v_shape) if len(v_shape) == 2 else np.zeros(v_shape)).astype(dtype)
    if vertices.size:
        vertices = vertices.at[(0,) * vertices.ndim].set(jnp.asarray(fill).astype(dtype))
    try:
        out = mesh_to_voxel_fraction(vertices, jnp.asarray(faces, jnp.int32), origin, voxel_size, grid, n_samples=8, implementation=implementation)
    except (TypeError, ValueError, KeyError, RuntimeError):
        return
    assert out.shape == tuple(grid[::-1]) and out.dtype == jnp.float32
    assert np.all((np.asarray(out) >= 0) & (np.asarray(out) <= 1))
