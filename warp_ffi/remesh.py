"""Nearest-centroid assignment for the clustering remesher, on a Warp hash grid.

Inputs arrive validated (no checks here) as NumPy arrays of one float dtype (float32 or float64);
labels come back as NumPy int32. The remesher runs eagerly (its output size depends on the
data), so these are plain launches on ``wp.array`` copies rather than XLA FFI calls.

Each point looks for its nearest centroid (ties: the lowest centroid index) among the centroids
in the grid cells within ``radius``. A found centroid closer than ``radius (1 - 2**-12)`` is the
nearest of all centroids (every centroid outside the visited cells is farther than ``radius``,
up to float32 rounding of the cell assignment, which the margin covers); otherwise the point
scans all centroids. The answer is therefore always the global nearest centroid, and ``radius``
only sets the speed. CPU launches are split over the cores with ``launch_in_chunks``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._kernels import WARP_SCALAR, launch_in_chunks
from ._kernels import warp as wp
from .poisson import GRID_LOCK, hash_grid

wp.set_module_options({"enable_backward": False})

__all__ = ["nearest_centroids"]

ACCEPT_MARGIN = 1.0 - 2.0**-12


@wp.func
def _closer(d2: Any, j: int, best_d2: Any, best: int):
    return d2 < best_d2 or (d2 == best_d2 and j < best)


@wp.kernel
def _nearest_kernel(
    grid: wp.uint64,
    points: wp.array(dtype=Any),
    centroids: wp.array(dtype=Any),
    params: wp.array(dtype=Any),
    offset: wp.int32,
    labels: wp.array(dtype=wp.int32),
):
    _, t = wp.tid()
    i = t + offset
    p = points[i]
    radius = params[0]
    accept = params[1]
    best = int(-1)
    best_d2 = radius * radius
    query = wp.hash_grid_query(grid, p, radius)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        d = centroids[j] - p
        d2 = wp.dot(d, d)
        if best < 0 or _closer(d2, j, best_d2, best):
            best = j
            best_d2 = d2
    if best < 0 or best_d2 >= accept * accept:
        best = int(0)
        d = centroids[0] - p
        best_d2 = wp.dot(d, d)
        for k in range(1, centroids.shape[0]):
            d = centroids[k] - p
            d2 = wp.dot(d, d)
            if _closer(d2, k, best_d2, best):
                best = k
                best_d2 = d2
    labels[i] = best


_VEC = {np.dtype(np.float32): wp.vec3f, np.dtype(np.float64): wp.vec3d}
_nearest = {
    dtype: wp.overload(
        _nearest_kernel,
        [wp.uint64, wp.array(dtype=_VEC[dtype]), wp.array(dtype=_VEC[dtype]), wp.array(dtype=scalar), wp.int32,
         wp.array(dtype=wp.int32)],
    )  # fmt: skip
    for dtype, scalar in ((np.dtype(k), v) for k, v in WARP_SCALAR.items())
}


def nearest_centroids(
    points: np.ndarray, centroids: np.ndarray, radius: float, cell_width: float, dims: tuple[int, int, int], device: str
) -> np.ndarray:
    """``(N,)`` int32: index of the nearest centroid of each point (ties: lowest index).

    Centroids are bucketed in cells of ``cell_width >= radius``.
    """
    dtype = np.dtype(points.dtype)
    vec, scalar = _VEC[dtype], WARP_SCALAR[dtype]
    points_wp = wp.array(points, dtype=vec, device=device)
    centroids_wp = wp.array(centroids, dtype=vec, device=device)
    params = wp.array(np.array([radius, radius * ACCEPT_MARGIN], dtype), dtype=scalar, device=device)
    labels = wp.empty(points.shape[0], dtype=wp.int32, device=device)
    with GRID_LOCK:
        grid = hash_grid(centroids_wp, cell_width, dims)
        launch_in_chunks(_nearest[dtype], 1, points.shape[0], [grid.id, points_wp, centroids_wp, params], [labels])
    return labels.numpy()
