"""mesh_poisson_disk_sample: the exact minimum distance, surface membership, exact elimination,
determinism, Warp/JAX parity and validation."""

import heapq
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from geomjax import icosphere, mesh_poisson_disk_sample, rectangle
from benchmarks import _quality as quality
from geomjax.sample import poisson

pytest.importorskip("warp")

BACKENDS = ["jax", "warp"]


def _jittered_sphere(subdivisions=2, seed=0):
    """An icosphere with jittered vertices: no exact symmetric ties between backends."""
    sphere = icosphere(subdivisions)
    points = np.asarray(sphere.points)
    points = points * (1 + 0.05 * np.random.default_rng(seed).uniform(-1, 1, (points.shape[0], 1)))
    return jnp.asarray(points), jnp.asarray(np.asarray(sphere.cells), jnp.int32)


def _pair_ratios(samples, radius):
    """Smallest ``d_ij / min(r_i, r_j)`` over pairs (float64 on the returned float32 points)."""
    samples = np.asarray(samples, np.float64)
    pairs = cKDTree(samples).query_pairs(2 * float(np.max(radius)), output_type="ndarray")
    if pairs.size == 0:
        return np.inf
    d = np.linalg.norm(samples[pairs[:, 0]] - samples[pairs[:, 1]], axis=1)
    return float(np.min(d / np.minimum(radius[pairs[:, 0]], radius[pairs[:, 1]])))


def _surface_gap(samples, vertices, faces):
    return float(quality.surface_distances(np.asarray(samples), np.asarray(vertices), np.asarray(faces)).max())


@pytest.mark.parametrize("implementation", BACKENDS)
def test_dart_throwing_minimum_distance_is_exact(implementation):
    vertices, faces = _jittered_sphere()
    samples = mesh_poisson_disk_sample(vertices, faces, min_distance=0.15, batch_size=1024, implementation=implementation)
    assert samples.dtype == jnp.float32 and samples.ndim == 2 and samples.shape[1] == 3
    assert samples.shape[0] > 100
    assert _pair_ratios(samples, np.full(samples.shape[0], 0.15)) >= 1.0
    assert _surface_gap(samples, vertices, faces) < 1e-6


def test_dart_throwing_is_near_maximal():
    """With enough iterations, no surface point is much farther than the radius from a sample."""
    vertices, faces = _jittered_sphere()
    samples = mesh_poisson_disk_sample(vertices, faces, min_distance=0.2, batch_size=2048, max_iterations=32)
    coverage = quality.coverage_radius(np.asarray(samples), np.asarray(vertices), np.asarray(faces), num_probes=20000)
    assert coverage < 1.3 * 0.2


@pytest.mark.parametrize("implementation", BACKENDS)
def test_adaptive_radius_uses_min_of_the_pair(implementation):
    vertices, faces = _jittered_sphere()
    radius = jnp.asarray(0.1 + 0.15 * (np.asarray(vertices)[:, 2] + 1.05) / 2.1, jnp.float32)
    samples = mesh_poisson_disk_sample(vertices, faces, per_vertex_radius=radius, batch_size=1024, implementation=implementation)
    # The radius at a sample: barycentric interpolation on its (closest) triangle.
    host = np.asarray(samples, np.float64)
    from geomjax.query.bvh import closest_faces_brute_force
    from geomjax._geometry import closest_point_on_triangle

    v64 = jnp.asarray(np.asarray(vertices), jnp.float64)
    ids, _ = closest_faces_brute_force(jnp.asarray(host), v64, faces)
    tri = v64[faces[ids]]
    _, weights = closest_point_on_triangle(jnp.asarray(host), tri[:, 0], tri[:, 1], tri[:, 2])
    sample_radius = np.einsum("nk,nk->n", np.asarray(weights), np.asarray(radius, np.float64)[np.asarray(faces)[np.asarray(ids)]])
    assert _pair_ratios(samples, sample_radius) >= 1.0 - 1e-5
    # Denser where the radius is small (the lower hemisphere).
    assert np.sum(host[:, 2] < 0) > 1.5 * np.sum(host[:, 2] > 0)


def test_dart_throwing_parity_and_determinism():
    vertices, faces = _jittered_sphere()
    kwargs = dict(min_distance=0.12, batch_size=1500, max_iterations=12, random_seed=7)
    jax_samples = np.asarray(mesh_poisson_disk_sample(vertices, faces, implementation="jax", **kwargs))
    warp_samples = np.asarray(mesh_poisson_disk_sample(vertices, faces, implementation="warp", **kwargs))
    np.testing.assert_array_equal(jax_samples, warp_samples)
    again = np.asarray(mesh_poisson_disk_sample(vertices, faces, implementation="warp", **kwargs))
    np.testing.assert_array_equal(again, warp_samples)
    other = np.asarray(mesh_poisson_disk_sample(vertices, faces, implementation="warp", **{**kwargs, "random_seed": 8}))
    assert other.shape != warp_samples.shape or not np.array_equal(other, warp_samples)


def test_dart_throwing_caps_and_iterations():
    vertices, faces = _jittered_sphere()
    capped = mesh_poisson_disk_sample(vertices, faces, min_distance=0.1, batch_size=512, max_points=37)
    assert capped.shape == (37, 3)
    one = mesh_poisson_disk_sample(vertices, faces, min_distance=0.1, batch_size=64, max_iterations=1)
    assert 1 <= one.shape[0] <= 64
    full = mesh_poisson_disk_sample(vertices, faces, min_distance=0.1, batch_size=64, max_iterations=40)
    assert full.shape[0] > one.shape[0]


def test_hash_grid_resolution_is_only_a_performance_knob():
    vertices, faces = _jittered_sphere()
    kwargs = dict(min_distance=0.12, batch_size=1024, max_iterations=8, implementation="warp")
    reference = np.asarray(mesh_poisson_disk_sample(vertices, faces, **kwargs))
    for resolution in (1, (4, 5, 6), jnp.array([7, 3, 2]), 256):
        out = np.asarray(mesh_poisson_disk_sample(vertices, faces, hash_grid_resolution=resolution, **kwargs))
        np.testing.assert_array_equal(out, reference)


def test_index_dtypes_and_flat_indices():
    vertices, faces = _jittered_sphere(1)
    kwargs = dict(min_distance=0.3, batch_size=256, implementation="warp")
    reference = np.asarray(mesh_poisson_disk_sample(vertices, faces, **kwargs))
    for indices in (faces.reshape(-1), np.asarray(faces).astype(np.uint8), np.asarray(faces).astype(np.int16), faces.astype(jnp.int64)):
        np.testing.assert_array_equal(np.asarray(mesh_poisson_disk_sample(vertices, indices, **kwargs)), reference)
    float32 = np.asarray(mesh_poisson_disk_sample(vertices.astype(jnp.float32), faces, **kwargs))
    np.testing.assert_array_equal(float32, reference)


def test_open_surface():
    plate = rectangle(8, 8)
    points = jnp.concatenate([plate.points, jnp.zeros_like(plate.points[:, :1])], axis=1)
    samples = np.asarray(mesh_poisson_disk_sample(points, plate.cells, min_distance=0.1, batch_size=1024))
    assert np.all(np.abs(samples[:, 2]) == 0)
    assert np.all((samples[:, :2] >= -1e-7) & (samples[:, :2] <= 1 + 1e-7))
    assert _pair_ratios(samples, np.full(samples.shape[0], 0.1)) >= 1.0


# ---------------------------------------------------------------------------------------------
# Weighted sample elimination.


def _exact_elimination(points, target, r_min, r_max):
    """Yuksel's elimination, one sample at a time, float64 weights, lazy heapq (test reference)."""
    points = np.asarray(points, np.float64)
    tree = cKDTree(points)
    pairs = tree.query_pairs(r_max, output_type="ndarray")
    d = np.maximum(np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1), r_min)
    w = (1 - d / r_max) ** 8
    neighbours = [[] for _ in range(points.shape[0])]
    for (i, j), wij in zip(pairs, w, strict=True):
        neighbours[i].append((j, wij))
        neighbours[j].append((i, wij))
    weight = np.array([sum(x for _, x in row) for row in neighbours])
    heap = [(-weight[i], i) for i in range(points.shape[0])]
    heapq.heapify(heap)
    alive = np.ones(points.shape[0], bool)
    remaining = points.shape[0]
    while remaining > target:
        neg, i = heapq.heappop(heap)
        if not alive[i] or -neg != weight[i]:
            continue
        alive[i] = False
        remaining -= 1
        for j, wij in neighbours[i]:
            if alive[j]:
                weight[j] -= wij
                heapq.heappush(heap, (-weight[j], j))
    return alive


def _pool(vertices, faces, target, seed):
    surface = poisson._surface(vertices, np.asarray(faces).astype(np.int64), None, 0.02)
    pool_size = max(target + 1, round(poisson.POOL_FACTOR * target))
    r_max = 2 * np.sqrt(surface.area / (2 * np.sqrt(3) * target))
    points, _, _ = poisson._candidates(surface, seed, pool_size)
    points = points[poisson.cell_order(points, r_max)]
    r_min = r_max * 0.65 * (1 - (target / pool_size) ** 1.5)
    return points, float(np.float32(r_min)), float(np.float32(r_max))


@pytest.mark.parametrize("implementation", BACKENDS)
def test_elimination_matches_the_exact_algorithm(implementation, monkeypatch):
    vertices, faces = _jittered_sphere()
    target = 120
    monkeypatch.setattr(poisson, "RELAXATION_STEPS", 0)
    ours = np.asarray(mesh_poisson_disk_sample(vertices, faces, mode="weighted_sample_elimination", target_num_points=target,
                                               random_seed=3, implementation=implementation))  # fmt: skip
    pool, r_min, r_max = _pool(vertices, faces, target, 3)
    expected = pool[_exact_elimination(pool, target, r_min, r_max)]
    assert ours.shape == (target, 3)
    np.testing.assert_array_equal(ours, expected)


def test_elimination_quality_at_least_the_exact_one():
    vertices, faces = _jittered_sphere(3)
    area = quality.surface_area(np.asarray(vertices), np.asarray(faces))
    target = 400
    exact_stats, ours_stats = [], []
    for seed in range(3):
        pool, r_min, r_max = _pool(vertices, faces, target, seed)
        exact_stats.append(quality.spacing_statistics(pool[_exact_elimination(pool, target, r_min, r_max)], area))
        ours = mesh_poisson_disk_sample(vertices, faces, mode="weighted_sample_elimination", target_num_points=target, random_seed=seed)
        assert ours.shape == (target, 3)
        ours_stats.append(quality.spacing_statistics(np.asarray(ours), area))
    for key in ("relative_mean", "relative_min"):
        assert np.mean([s[key] for s in ours_stats]) >= np.mean([s[key] for s in exact_stats])


def test_elimination_parity_surface_and_determinism():
    vertices, faces = _jittered_sphere()
    kwargs = dict(mode="weighted_sample_elimination", target_num_points=150, random_seed=11)
    jax_samples = np.asarray(mesh_poisson_disk_sample(vertices, faces, implementation="jax", **kwargs))
    warp_samples = np.asarray(mesh_poisson_disk_sample(vertices, faces, implementation="warp", **kwargs))
    np.testing.assert_array_equal(jax_samples, warp_samples)
    np.testing.assert_array_equal(np.asarray(mesh_poisson_disk_sample(vertices, faces, **kwargs)), warp_samples)
    assert _surface_gap(warp_samples, vertices, faces) < 1e-6


def test_elimination_defaults_to_max_points_and_warns_on_radius():
    vertices, faces = _jittered_sphere(1)
    out = mesh_poisson_disk_sample(vertices, faces, mode="weighted_sample_elimination", max_points=25)
    assert out.shape == (25, 3)
    with pytest.warns(UserWarning, match="per_vertex_radius is ignored"):
        mesh_poisson_disk_sample(vertices, faces, per_vertex_radius=jnp.ones(vertices.shape[0]),
                                 mode="weighted_sample_elimination", target_num_points=10)  # fmt: skip
    single = mesh_poisson_disk_sample(vertices, faces, mode="weighted_sample_elimination", target_num_points=1)
    assert single.shape == (1, 3)


# ---------------------------------------------------------------------------------------------
# Validation.


def test_errors():
    vertices, faces = _jittered_sphere(1)
    call = mesh_poisson_disk_sample
    with pytest.raises(TypeError, match="mesh_vertices"):
        call(faces, faces)
    with pytest.raises(TypeError, match="mesh_indices"):
        call(vertices, faces.astype(jnp.float32))
    with pytest.raises(TypeError, match="mesh_indices"):
        call(vertices, faces > 0)
    with pytest.raises(ValueError, match="mesh_vertices"):
        call(vertices[:, :2], faces)
    with pytest.raises(ValueError, match="mesh_indices"):
        call(vertices, faces.reshape(-1)[:-1])
    with pytest.raises(ValueError, match="mesh_indices"):
        call(vertices, faces.at[0, 0].set(vertices.shape[0]))
    with pytest.raises(ValueError, match="finite"):
        call(vertices.at[0, 0].set(jnp.nan), faces)
    with pytest.raises(ValueError, match="zero area"):
        call(jnp.zeros_like(vertices), faces)
    with pytest.raises(ValueError, match="min_distance"):
        call(vertices, faces, min_distance=0.0)
    with pytest.raises(TypeError, match="min_distance"):
        call(vertices, faces, min_distance=True)
    with pytest.raises(ValueError, match="per_vertex_radius"):
        call(vertices, faces, per_vertex_radius=jnp.ones(3))
    with pytest.raises(ValueError, match="per_vertex_radius"):
        call(vertices, faces, per_vertex_radius=-jnp.ones(vertices.shape[0]))
    with pytest.raises(TypeError, match="per_vertex_radius"):
        call(vertices, faces, per_vertex_radius=jnp.ones(vertices.shape[0], jnp.int32))
    for name in ("batch_size", "max_points", "max_iterations"):
        with pytest.raises(ValueError, match=name):
            call(vertices, faces, **{name: 0})
        with pytest.raises(TypeError, match=name):
            call(vertices, faces, **{name: 1.5})
    with pytest.raises(TypeError, match="random_seed"):
        call(vertices, faces, random_seed=False)
    with pytest.raises(ValueError, match="hash_grid_resolution"):
        call(vertices, faces, hash_grid_resolution=(1, 2))
    with pytest.raises(ValueError, match="hash_grid_resolution"):
        call(vertices, faces, hash_grid_resolution=0)
    with pytest.raises(TypeError, match="hash_grid_resolution"):
        call(vertices, faces, hash_grid_resolution=2.0)
    with pytest.raises(ValueError, match="mode"):
        call(vertices, faces, mode="lloyd")
    with pytest.raises(ValueError, match="target_num_points"):
        call(vertices, faces, mode="weighted_sample_elimination", target_num_points=0)
    with pytest.raises(ValueError, match="too small"):
        call(vertices, faces, min_distance=1e-12)
    with pytest.raises(KeyError):
        call(vertices, faces, implementation="cuda")
    with pytest.raises(TypeError, match="eagerly"):
        jax.jit(lambda v: call(v, faces))(vertices)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        call(vertices, faces, min_distance=0.5, batch_size=64, implementation="torch")


def test_candidate_counts_beyond_the_device_are_value_errors(monkeypatch):
    # XLA aborted the process when the candidate pool could not be allocated; the request must
    # fail with the documented ValueError first, on every backend and through torch_bridge.
    sphere = icosphere(1)
    for implementation in ("jax", "warp"):
        with pytest.raises(ValueError, match=r"target_num_points=1000000000 \(a candidate pool of 5x\) needs 5000000000 items, more than 2147483647"):
            mesh_poisson_disk_sample(sphere.points, sphere.cells, mode="weighted_sample_elimination", target_num_points=10**9, implementation=implementation)
    with pytest.raises(ValueError, match="batch_size=4294967296 needs 4294967296 items"):
        mesh_poisson_disk_sample(sphere.points, sphere.cells, batch_size=2**32)
    # Below the index limit, memory decides: as if the device had 1 GiB left.
    from geomjax import _validate

    monkeypatch.setattr(_validate, "available_bytes", lambda device: 2**30)
    with pytest.raises(ValueError, match=r"batch_size=10000000 needs about 1\.2 GiB, more than the 1\.0 GiB available"):
        mesh_poisson_disk_sample(sphere.points, sphere.cells, batch_size=10**7)
    assert mesh_poisson_disk_sample(sphere.points, sphere.cells, min_distance=0.5, batch_size=1000).shape[1] == 3
    torch = pytest.importorskip("torch")
    import torch_bridge

    with pytest.raises(ValueError, match="needs 5000000000 items"):
        torch_bridge.mesh_poisson_disk_sample(torch.tensor(np.asarray(sphere.points)), torch.tensor(np.asarray(sphere.cells)),
                                              mode="weighted_sample_elimination", target_num_points=10**9)  # fmt: skip
