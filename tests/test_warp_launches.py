"""Replayed CPU launches (``warp_ffi._wrap.launch_on_host``): each call's own arrays, sizes and
scalars, on any thread, and no silent copy of an argument the kernel writes."""

import sys
import threading

import numpy as np
import pytest

pytest.importorskip("warp")
import warp as wp  # noqa: E402

from warp_ffi._wrap import launch_on_host  # noqa: E402
from warp_ffi.host import _overturned_kernel, overturned_vertices, relaxation_sums  # noqa: E402


def _surface(rows: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ``rows`` x ``rows`` grid of triangles and a move that turns some of them over."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.arange(rows + 1.0), np.arange(rows + 1.0), indexing="ij")
    points = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    corner = (np.arange(rows)[:, None] * (rows + 1) + np.arange(rows)[None, :]).ravel()
    triangles = np.concatenate([np.stack([corner, corner + rows + 1, corner + 1], 1), np.stack([corner + 1, corner + rows + 1, corner + rows + 2], 1)])
    moved = points + rng.normal(scale=0.6, size=points.shape) * [1, 1, 0]
    return points, moved, triangles.astype(np.int32)


def _overturned(points, moved, triangles) -> np.ndarray:
    """The corners of triangles whose normal turns by 90 degrees or more (NumPy cross products)."""

    def normals(x):
        a, b, c = (x[triangles[:, k]] for k in range(3))
        return np.cross(b - a, c - a)

    mask = np.zeros(points.shape[0], bool)
    mask[triangles[np.einsum("ij,ij->i", normals(points), normals(moved)) <= 0].ravel()] = True
    return mask


def test_each_replay_reads_its_own_arrays_and_sizes():
    # Alternating sizes: a replay that kept the last call's address or size would read the
    # other surface (or past the end of a smaller one).
    cases = [_surface(rows, seed) for rows, seed in [(3, 0), (9, 1), (3, 2), (14, 3)]]
    for points, moved, triangles in cases + cases[::-1]:
        expected = _overturned(points, moved, triangles)
        assert 0 < expected.sum() < expected.size
        np.testing.assert_array_equal(overturned_vertices(points, moved, triangles), expected)


def test_replays_with_and_without_an_optional_array_sum_their_own_weights():
    points, _, triangles = _surface(4, 0)
    area = 0.5 * np.ones(triangles.shape[0])  # unit grid: every triangle has area 1/2
    rho = np.linspace(1.0, 2.0, points.shape[0])
    for weights in [None, rho, None, 2 * rho]:
        total, _ = relaxation_sums(points, triangles, weights)
        mass = area if weights is None else area * weights[triangles].mean(axis=1)
        np.testing.assert_allclose(total, np.bincount(triangles.ravel(), np.repeat(mass, 3), points.shape[0]), rtol=1e-14)


def test_threads_replay_their_own_launches():
    cases = [_surface(rows, seed) for rows, seed in [(5, 4), (11, 5)]]
    failures = []

    def work(points, moved, triangles):
        expected = _overturned(points, moved, triangles)
        for _ in range(200):
            if not np.array_equal(overturned_vertices(points, moved, triangles), expected):
                failures.append(points.shape[0])
                return

    threads = [threading.Thread(target=work, args=case) for case in cases]
    # Threads switch every microsecond (not every 5 ms): between a replay's writes and its launch.
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    finally:
        sys.setswitchinterval(interval)
    assert failures == []


def test_an_array_the_kernel_cannot_view_is_refused():
    points, moved, triangles = _surface(3, 0)
    turned = np.zeros(points.shape[0], np.int64)  # int64: Warp would write into an int32 copy
    arrays = [(points, wp.vec3d), (moved, wp.vec3d), (triangles.reshape(-1), wp.int32)]
    with pytest.raises(TypeError, match="argument 3 .* is no array of int32"):
        launch_on_host(_overturned_kernel, triangles.shape[0], [*arrays, (turned, wp.int32)])
    launch_on_host(_overturned_kernel, triangles.shape[0], [*arrays, (np.zeros(points.shape[0], np.int32), wp.int32)])
    strided = np.zeros((points.shape[0], 2), np.int32)[:, 0]
    with pytest.raises(ValueError, match="argument 3 must be C-contiguous"):
        launch_on_host(_overturned_kernel, triangles.shape[0], [*arrays, (strided, wp.int32)])
    four = np.zeros((points.shape[0], 4))  # rows of four where the kernel reads 3-vectors
    with pytest.raises(ValueError, match=r"argument 1 must be C-contiguous with elements of shape \(3,\)"):
        launch_on_host(_overturned_kernel, triangles.shape[0], [arrays[0], (four, wp.vec3d), *arrays[2:], (np.zeros(points.shape[0], np.int32), wp.int32)])
