"""Mesh primitives: counts, orientation, conformity, volumes, dtypes and argument checks."""

import math
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from geomjax import Mesh, icosphere, polyline, rectangle, tetrahedralized_box


def _signed_volume(points, triangles):
    a, b, c = (points[triangles[:, i]] for i in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0


def _tet_determinants(points, tets):
    return np.linalg.det(points[tets[:, 1:]] - points[tets[:, :1]])


@pytest.mark.parametrize("subdivisions", [0, 1, 2, 3])
def test_icosphere_counts_radius_and_outward_orientation(subdivisions):
    sphere = icosphere(subdivisions, radius=1.5)
    points, faces = np.asarray(sphere.points), np.asarray(sphere.cells)
    assert sphere.n_points == 10 * 4**subdivisions + 2 and sphere.n_cells == 20 * 4**subdivisions
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 1.5, rtol=1e-14)
    normals = np.cross(points[faces[:, 1]] - points[faces[:, 0]], points[faces[:, 2]] - points[faces[:, 0]])
    assert np.all(np.einsum("ij,ij->i", normals, points[faces].mean(axis=1)) > 0)
    # No duplicate vertices: the midpoints of shared edges are welded.
    assert np.unique(np.round(points, 12), axis=0).shape[0] == sphere.n_points
    np.testing.assert_array_equal(sphere.topology.closed_surface_triangles(), faces)


def test_icosphere_six_is_large_fast_and_closed():
    start = time.perf_counter()
    sphere = icosphere(6)
    elapsed = time.perf_counter() - start
    assert (sphere.n_points, sphere.n_cells) == (40_962, 81_920)
    sphere.topology.closed_surface_triangles()  # consistently oriented, closed, connected
    points, faces = np.asarray(sphere.points), np.asarray(sphere.cells)
    volume = _signed_volume(points, faces)
    # Inscribed polyhedron: slightly below 4/3 pi and converging to it (error ~ 1 / 4**s).
    assert 0 < 4 / 3 * math.pi - volume < 1e-3
    assert elapsed < 5.0, f"icosphere(6) took {elapsed:.2f} s"


def test_icosphere_volume_converges_to_the_ball():
    errors = [4 / 3 * math.pi - _signed_volume(np.asarray(s.points), np.asarray(s.cells)) for s in map(icosphere, range(5))]
    assert all(e > 0 for e in errors)
    ratios = [errors[i] / errors[i + 1] for i in range(1, 4)]
    assert all(3.5 < r < 4.5 for r in ratios), ratios


def test_default_dtype_follows_x64_and_explicit_dtypes():
    assert icosphere(0).points.dtype == jnp.float64  # tests run with x64 enabled
    for build in (lambda d: icosphere(1, dtype=d), lambda d: rectangle(2, 2, dtype=d),
                  lambda d: tetrahedralized_box(1, 1, 1, dtype=d), lambda d: polyline(3, dtype=d)):
        assert build(jnp.float32).points.dtype == jnp.float32
        assert build("float64").points.dtype == jnp.float64
    with jax.enable_x64(False):
        assert icosphere(0).points.dtype == jnp.float32


def test_rectangle_grid_orientation_and_area():
    plate = rectangle(3, 2, origin=(-1.0, 2.0), extent=(3.0, 1.0))
    points, faces = np.asarray(plate.points), np.asarray(plate.cells)
    assert (plate.n_points, plate.n_cells, plate.n_manifold_dims) == (12, 12, 2)
    np.testing.assert_allclose(points[0], [-1.0, 2.0])
    np.testing.assert_allclose(points[1], [0.0, 2.0])  # x varies fastest
    np.testing.assert_allclose(points[-1], [2.0, 3.0])
    e1, e2 = points[faces[:, 1]] - points[faces[:, 0]], points[faces[:, 2]] - points[faces[:, 0]]
    areas = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / 2
    np.testing.assert_allclose(areas, 3.0 / 12)
    # Conforming: every interior edge has two triangles, the boundary edges one.
    hinges = np.asarray(plate.hinges)
    assert plate.edges.shape[0] - hinges.shape[0] == 2 * (3 + 2)


def _boundary_faces(tets):
    faces = np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    unique, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() <= 2
    return unique[counts == 1]


@pytest.mark.parametrize("counts", [(1, 1, 1), (2, 3, 4)])
def test_tetrahedralized_box_is_positive_and_conforming(counts):
    origin, extent = (1.0, -2.0, 0.5), (2.0, 1.0, 3.0)
    box = tetrahedralized_box(*counts, origin=origin, extent=extent)
    points, tets = np.asarray(box.points), np.asarray(box.cells)
    nx, ny, nz = counts
    assert box.n_points == (nx + 1) * (ny + 1) * (nz + 1) and box.n_cells == 6 * nx * ny * nz
    determinants = _tet_determinants(points, tets)
    assert np.all(determinants > 0)
    np.testing.assert_allclose(determinants.sum() / 6, np.prod(extent), rtol=1e-12)
    np.testing.assert_allclose(points.min(axis=0), origin)
    np.testing.assert_allclose(points.max(axis=0), np.add(origin, extent))
    # Conforming: interior faces are shared by exactly two tets, and only the box surface is
    # left: 2 triangles per boundary quad.
    boundary = _boundary_faces(tets)
    assert boundary.shape[0] == 4 * (nx * ny + ny * nz + nx * nz)
    on_box_surface = np.isclose(points[boundary], origin) | np.isclose(points[boundary], np.add(origin, extent))
    assert np.all(np.any(np.all(on_box_surface, axis=1), axis=1))


def test_polyline_from_points_and_counts():
    open_line = polyline(4)
    np.testing.assert_array_equal(open_line.cells, [[0, 1], [1, 2], [2, 3]])
    np.testing.assert_allclose(open_line.points, [[0, 0], [1 / 3, 0], [2 / 3, 0], [1, 0]])
    loop = polyline(6, closed=True)
    np.testing.assert_allclose(np.linalg.norm(loop.points, axis=1), 1.0)
    assert loop.n_cells == 6 and tuple(np.asarray(loop.cells)[-1]) == (5, 0)
    points = jnp.asarray(np.random.default_rng(0).normal(size=(5, 3)), jnp.float32)
    curve = polyline(points, closed=True)
    assert isinstance(curve, Mesh) and curve.points.dtype == jnp.float32 and curve.n_cells == 5
    assert polyline(points, dtype=jnp.float64).points.dtype == jnp.float64


@pytest.mark.parametrize(
    "build, error, match",
    [
        (lambda: icosphere(-1), ValueError, "subdivisions must be at least 0"),
        (lambda: icosphere(1.0), TypeError, "subdivisions must be an integer"),
        (lambda: icosphere(True), TypeError, "subdivisions must be an integer"),
        (lambda: icosphere(1, radius=0.0), ValueError, "radius must be positive"),
        (lambda: icosphere(1, radius=float("inf")), ValueError, "radius must be finite"),
        (lambda: icosphere(1, radius="1"), TypeError, "radius must be a real number"),
        (lambda: icosphere(1, dtype=jnp.float16), TypeError, "float32 or float64"),
        (lambda: icosphere(1, dtype="banana"), TypeError, "float32 or float64"),
        (lambda: rectangle(0, 1), ValueError, "nx must be at least 1"),
        (lambda: rectangle(1, 1, extent=(1.0, -1.0)), ValueError, "extent"),
        (lambda: rectangle(1, 1, origin=(0.0,)), TypeError, "origin must contain exactly 2 real values"),
        (lambda: tetrahedralized_box(1, 1, 0), ValueError, "nz must be at least 1"),
        (lambda: tetrahedralized_box(1, 1, 1, extent=(1.0, 1.0, float("nan"))), ValueError, "finite"),
        (lambda: polyline(1), ValueError, "at least 2"),
        (lambda: polyline(2, closed=True), ValueError, "at least 3"),
        (lambda: polyline(jnp.zeros((2, 2)), closed=True), ValueError, "at least 3 points"),
        (lambda: polyline(jnp.zeros(3)), ValueError, r"\(N, D\)"),
        (lambda: polyline(jnp.zeros((3, 2), jnp.int32)), TypeError, "float32 or float64"),
        (lambda: polyline(3, closed=1), TypeError, "closed must be a bool"),
        (lambda: polyline("abc"), TypeError, "points must be an integer"),
    ],
)
def test_argument_errors(build, error, match):
    with pytest.raises(error, match=match):
        build()
