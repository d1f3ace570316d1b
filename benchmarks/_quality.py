"""Quality measures for surface samples and triangle meshes (diagnostics, NumPy results).

Test and benchmark code, not library API: used by the tests and by
``benchmarks/bench_sampling_remesh.py`` to compare samplers and remeshers. Every function takes JAX or NumPy arrays and returns NumPy floats or dicts of them;
distances are computed in float64 and are exact (no approximate nearest neighbours). Surface
distances use a Warp BVH (:func:`geomjax.build_bvh`), so the Hausdorff measure needs warp-lang.

* Sample spacing: nearest-neighbour distances, also relative to the spacing of the ideal
  hexagonal packing of ``n`` points on area ``A``, ``sqrt(2 A / (sqrt(3) n))``.
* Coverage radius: the largest distance from a dense set of surface points to the nearest sample
  (the radius of the largest empty disk, sampled).
* Triangle quality: minimum angles and radius ratios (``2 r_in / r_circ``, 1 for an equilateral
  triangle, 0 for a degenerate one).
* Symmetric Hausdorff distance between two triangle surfaces, sampled: vertices plus uniform
  points of each surface, measured against the other surface.

Example:
    >>> import numpy as np
    >>> from geomjax import icosphere
    >>> from benchmarks import _quality as quality
    >>> sphere = icosphere(2)
    >>> stats = quality.triangle_quality(sphere.points, sphere.cells)
    >>> print(round(stats["min_angle_deg_min"], 1), round(stats["radius_ratio_mean"], 3))
    54.4 0.987
"""

from __future__ import annotations

import math

import numpy as np

from geomjax._hash_grid import nearest_distances

__all__ = [
    "surface_area",
    "ideal_spacing",
    "nearest_neighbour_distances",
    "spacing_statistics",
    "uniform_surface_points",
    "coverage_radius",
    "triangle_quality",
    "surface_distances",
    "hausdorff_distance",
]


def _triangles(vertices, faces) -> np.ndarray:
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces).reshape(-1, 3)
    return vertices[faces]


def surface_area(vertices, faces) -> float:
    """Total area of a triangle surface ``(V, 3)`` / ``(F, 3)``."""
    tri = _triangles(vertices, faces)
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def ideal_spacing(area: float, count: int) -> float:
    """Nearest-neighbour distance of the hexagonal packing of ``count`` points on ``area``."""
    return math.sqrt(2.0 * area / (math.sqrt(3.0) * count))


def nearest_neighbour_distances(points) -> np.ndarray:
    """``(N,)`` distance from each point to the nearest other point (``inf`` for a lone point).

    Example:
        >>> import numpy as np
        >>> from benchmarks._quality import nearest_neighbour_distances
        >>> print(nearest_neighbour_distances(np.array([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]])))
        [1. 1. 2.]
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    return nearest_distances(points, points, exclude_self=True)


def spacing_statistics(points, area: float) -> dict[str, float]:
    """Minimum and mean nearest-neighbour distance, absolute and relative to :func:`ideal_spacing`.

    Returns a dict with ``count``, ``min_nn``, ``mean_nn``, ``ideal`` and ``relative_min``,
    ``relative_mean`` (the distances over ``ideal``; a maximal Poisson-disk set is near 0.7 to
    0.8 on average, the hexagonal packing 1).
    """
    distances = nearest_neighbour_distances(points)
    count = distances.shape[0]
    ideal = ideal_spacing(area, count) if count else float("nan")
    min_nn = float(distances.min()) if count else float("nan")
    mean_nn = float(distances.mean()) if count else float("nan")
    return {
        "count": count, "min_nn": min_nn, "mean_nn": mean_nn, "ideal": ideal,
        "relative_min": min_nn / ideal, "relative_mean": mean_nn / ideal,
    }  # fmt: skip


def uniform_surface_points(vertices, faces, count: int, *, seed: int = 0) -> np.ndarray:
    """``(count, 3)`` float64 points uniform by area on the surface (NumPy generator ``seed``)."""
    tri = _triangles(vertices, faces)
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    face = rng.choice(tri.shape[0], count, p=areas / areas.sum())
    u, v = rng.random(count), rng.random(count)
    s = np.sqrt(u)
    weights = np.stack([1 - s, s * v, s * (1 - v)], axis=1)
    return np.einsum("nk,nkd->nd", weights, tri[face])


def coverage_radius(samples, vertices, faces, *, num_probes: int = 200_000, seed: int = 0) -> float:
    """Largest distance from ``num_probes`` uniform surface points (and the vertices) to a sample."""
    probes = np.concatenate([uniform_surface_points(vertices, faces, num_probes, seed=seed), np.asarray(vertices, np.float64)])
    return float(nearest_distances(probes, np.asarray(samples, np.float64)).max())


def triangle_quality(vertices, faces) -> dict[str, float]:
    """Angle and shape statistics of the triangles.

    Returns ``min_angle_deg_min`` / ``min_angle_deg_mean`` (the smallest angle of each triangle:
    its minimum over the mesh and its mean), ``radius_ratio_min`` / ``radius_ratio_mean``
    (``2 r_in / r_circ``) and ``fraction_below_30deg`` (triangles with an angle under 30
    degrees).
    """
    tri = _triangles(vertices, faces)
    a = np.linalg.norm(tri[:, 1] - tri[:, 2], axis=1)
    b = np.linalg.norm(tri[:, 2] - tri[:, 0], axis=1)
    c = np.linalg.norm(tri[:, 0] - tri[:, 1], axis=1)
    cosines = np.stack([(b * b + c * c - a * a) / (2 * b * c), (c * c + a * a - b * b) / (2 * c * a), (a * a + b * b - c * c) / (2 * a * b)], axis=1)
    min_angle = np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0))).min(axis=1)
    # 2 r_in / r_circ = (b + c - a)(c + a - b)(a + b - c) / (a b c).
    ratio = (b + c - a) * (c + a - b) * (a + b - c) / (a * b * c)
    return {
        "min_angle_deg_min": float(min_angle.min()),
        "min_angle_deg_mean": float(min_angle.mean()),
        "radius_ratio_min": float(ratio.min()),
        "radius_ratio_mean": float(ratio.mean()),
        "fraction_below_30deg": float(np.mean(min_angle < 30.0)),
    }


def surface_distances(points, vertices, faces) -> np.ndarray:
    """``(N,)`` exact float64 distance from each point to a triangle surface (Warp BVH search)."""
    import jax
    import jax.numpy as jnp

    from geomjax.query.bvh import build_bvh, closest_faces

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces).reshape(-1, 3).astype(np.int32)
    p = np.asarray(points, np.float64).reshape(-1, 3)
    with jax.enable_x64(True):
        face = np.asarray(closest_faces(build_bvh(jnp.asarray(v), jnp.asarray(f)), jnp.asarray(p)))
    # The closest point itself in NumPy: one vectorised pass, where eager JAX compiled a dozen
    # one-operation programs for every new number of points.
    corners = v[f[face]]
    closest = _closest_points_on_triangles(p, corners[:, 0], corners[:, 1], corners[:, 2])
    return np.linalg.norm(closest - p, axis=1)


def _closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The point of each triangle ``(a, b, c)`` closest to ``p`` (rows), by its Voronoi regions:
    the three vertices, the three edges, else the interior (Ericson, Real-Time Collision
    Detection, 5.1.5), for well-scaled float64 input."""

    def dot(x, y):
        return np.einsum("ij,ij->i", x, y)

    ab, ac, bc = b - a, c - a, c - b
    d1, d2 = dot(ab, p - a), dot(ac, p - a)
    d3, d4 = dot(ab, p - b), dot(ac, p - b)
    d5, d6 = dot(ab, p - c), dot(ac, p - c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):  # the quotients of other regions are unused
        on_ab = a + ab * (d1 / (d1 - d3))[:, None]
        on_ac = a + ac * (d2 / (d2 - d6))[:, None]
        on_bc = b + bc * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None]
        total = va + vb + vc
        inside = a + ab * (vb / total)[:, None] + ac * (vc / total)[:, None]
    regions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 >= d3) & (d5 >= d6),
    ]
    choices = [a, b, on_ab, c, on_ac, on_bc]
    return np.select([r[:, None] for r in regions], choices, default=inside)


def hausdorff_distance(vertices_a, faces_a, vertices_b, faces_b, *, num_probes: int = 100_000, seed: int = 0) -> float:
    """Symmetric Hausdorff distance between two triangle surfaces, sampled.

    Each surface is probed at its vertices and ``num_probes`` uniform points, and each probe is
    measured exactly against the other surface; the result is the largest of these distances.
    """
    probes_a = np.concatenate([np.asarray(vertices_a, np.float64), uniform_surface_points(vertices_a, faces_a, num_probes, seed=seed)])
    probes_b = np.concatenate([np.asarray(vertices_b, np.float64), uniform_surface_points(vertices_b, faces_b, num_probes, seed=seed + 1)])
    return float(max(surface_distances(probes_a, vertices_b, faces_b).max(), surface_distances(probes_b, vertices_a, faces_a).max()))
