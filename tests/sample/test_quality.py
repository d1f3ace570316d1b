"""Quality measures: exact nearest neighbours, spacing, coverage, triangle shapes, Hausdorff."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from geomjax import icosphere
from benchmarks import _quality as quality
from geomjax._hash_grid import cell_order, grid_resolution, nearest_distances, table_dims


@pytest.mark.parametrize("layout", ["surface", "volume", "clustered"])
def test_nearest_distances_exact(layout):
    rng = np.random.default_rng(0)
    if layout == "surface":
        points = rng.normal(size=(3000, 3))
        points /= np.linalg.norm(points, axis=1, keepdims=True)
    elif layout == "volume":
        points = rng.uniform(size=(3000, 3))
    else:
        points = np.concatenate([rng.normal(scale=1e-3, size=(1000, 3)), rng.normal(size=(20, 3)) * 10])
    queries = rng.normal(size=(500, 3)) * 2
    np.testing.assert_allclose(nearest_distances(queries, points), cKDTree(points).query(queries)[0], rtol=1e-12)
    expected = cKDTree(points).query(points, k=2)[0][:, 1]
    np.testing.assert_allclose(quality.nearest_neighbour_distances(points), expected, rtol=1e-12)


def test_nearest_distances_edge_cases():
    assert np.isinf(quality.nearest_neighbour_distances(np.zeros((1, 3)))).all()
    np.testing.assert_array_equal(quality.nearest_neighbour_distances(np.zeros((3, 3))), [0, 0, 0])
    assert nearest_distances(np.zeros((2, 3)), np.zeros((0, 3))).tolist() == [np.inf, np.inf]


def test_spacing_of_a_hexagonal_lattice_is_ideal():
    i, j = np.meshgrid(np.arange(60), np.arange(60))
    points = np.stack([i + 0.5 * (j % 2), j * np.sqrt(3) / 2, np.zeros_like(i, float)], axis=-1).reshape(-1, 3)
    area = points.shape[0] * np.sqrt(3) / 2  # one hexagonal cell per point
    stats = quality.spacing_statistics(points, area)
    assert stats["min_nn"] == pytest.approx(1.0) and stats["mean_nn"] == pytest.approx(1.0)
    assert stats["relative_mean"] == pytest.approx(1.0)


def test_coverage_radius():
    sphere = icosphere(3)
    vertices, faces = np.asarray(sphere.points), np.asarray(sphere.cells)
    assert 0.05 < quality.coverage_radius(vertices, vertices, faces, num_probes=2000) < 0.1  # about an edge length
    north = np.array([[0.0, 0.0, 1.0]])
    assert quality.coverage_radius(north, vertices, faces, num_probes=2000) == pytest.approx(2.0, abs=1e-3)


def test_triangle_quality():
    equilateral = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0]])
    right = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    stats = quality.triangle_quality(np.concatenate([equilateral, right]), np.array([[0, 1, 2], [3, 4, 5]]))
    assert stats["min_angle_deg_min"] == pytest.approx(45.0)
    assert stats["min_angle_deg_mean"] == pytest.approx(52.5)
    assert stats["radius_ratio_min"] == pytest.approx(2 * np.sqrt(2) - 2)  # legs 1, 1: (2 - sqrt 2) sqrt 2
    assert stats["fraction_below_30deg"] == 0.0


def test_surface_distances_and_hausdorff():
    sphere = icosphere(2)
    vertices, faces = np.asarray(sphere.points), np.asarray(sphere.cells)
    assert quality.hausdorff_distance(vertices, faces, vertices, faces, num_probes=2000) < 1e-12
    assert quality.hausdorff_distance(vertices, faces, 1.1 * vertices, faces, num_probes=2000) == pytest.approx(0.1, abs=1e-9)
    np.testing.assert_allclose(quality.surface_distances(np.array([[0, 0, 3.0]]), vertices, faces), [2.0], atol=1e-12)
    assert quality.surface_area(vertices, faces) == pytest.approx(4 * np.pi, rel=0.05)
    uniform = quality.uniform_surface_points(vertices, faces, 5000, seed=1)
    assert quality.surface_distances(uniform, vertices, faces).max() < 1e-12
    # Uniform by area: as many points in each hemisphere, up to sampling noise.
    assert abs(np.mean(uniform[:, 2] > 0) - 0.5) < 0.03


def test_grid_helpers():
    assert grid_resolution("r", 4) == (4, 4, 4)
    assert grid_resolution("r", np.array([1, 2, 3])) == (1, 2, 3)
    assert table_dims(np.zeros(3), np.ones(3), 0.1, (128, 5, 2)) == (11, 5, 3)
    points = np.random.default_rng(0).uniform(size=(100, 3))
    order = cell_order(points, 0.25)
    cells = np.floor(points[order] / 0.25)
    keys = cells[:, 2] * 16 + cells[:, 1] * 4 + cells[:, 0]
    assert np.all(np.diff(keys) >= 0) and sorted(order.tolist()) == list(range(100))


def test_closest_points_on_triangles_beat_a_dense_sample_of_each_triangle():
    # Points in every Voronoi region (vertices, edges, interior) of random, some obtuse, triangles.
    rng = np.random.default_rng(3)
    a, b, c = (rng.normal(size=(400, 3)) for _ in range(3))
    p = rng.normal(scale=2.0, size=(400, 3))
    closest = quality._closest_points_on_triangles(p, a, b, c)
    # On the triangle: barycentric coordinates (least squares) nonnegative and summing to one.
    edges = np.stack([b - a, c - a], axis=-1)  # (T, 3, 2)
    uv = np.stack([np.linalg.lstsq(e, x, rcond=None)[0] for e, x in zip(edges, closest - a)])
    assert uv.min() > -1e-9 and uv.sum(axis=1).max() < 1 + 1e-9
    np.testing.assert_allclose(np.einsum("tij,tj->ti", edges, uv) + a, closest, atol=1e-9)
    # No point of a dense barycentric sample (including the edges and vertices) is closer.
    s, t = np.meshgrid(np.linspace(0, 1, 41), np.linspace(0, 1, 41))
    keep = s + t <= 1
    s, t = s[keep], t[keep]
    samples = a[:, None] + s[None, :, None] * (b - a)[:, None] + t[None, :, None] * (c - a)[:, None]
    sampled = np.linalg.norm(samples - p[:, None], axis=-1).min(axis=1)
    exact = np.linalg.norm(closest - p, axis=1)
    assert np.all(exact <= sampled + 1e-12)
    assert np.all(sampled - exact < 0.05 * np.linalg.norm(b - a, axis=1) + 0.05 * np.linalg.norm(c - a, axis=1))
