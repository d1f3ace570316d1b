"""The remesher's triangle clean-up on hand-made triangulations, checked with independent angle
and orientation computations."""

import numpy as np

from benchmarks import _quality as quality
from geomjax.remesh._triangulation import MIN_ANGLE_DEGREES, boundary_vertices, relocate_poor_corners


def _grid(n):
    """An ``n x n`` unit-step grid in the plane z = 0, two triangles per cell, counter-clockwise."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    points = np.stack([i, j, np.zeros_like(i)], axis=-1).reshape(-1, 3).astype(np.float64)
    a = (i[:-1, :-1] * n + j[:-1, :-1]).reshape(-1)
    b, c, d = a + n, a + n + 1, a + 1
    return points, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)


def _on_plane(vertices, starts, moves):
    """Surface points on z = 0 (the plane's closest points), with dummy faces and weights."""
    points = (starts + moves) * [1.0, 1.0, 0.0]
    return points, np.zeros(len(points), np.int32), np.full((len(points), 3), 1 / 3)


def _normals_z(points, faces):
    a, b, c = (points[faces[:, k]] for k in range(3))
    return np.cross(b - a, c - a)[:, 2]


def test_poor_corners_move_on_the_surface_until_their_triangles_are_fair():
    points, faces = _grid(6)
    fixed = boundary_vertices(faces, len(points))
    # Interior vertex 14 = (2, 2) pushed to 0.04 steps from its neighbour 15 = (2, 3), and
    # interior vertex 7 = (1, 1) to 0.05 steps from the boundary vertex 6 = (1, 0).
    points[14] = [2.0, 2.96, 0.0]
    points[7] = [1.0, 0.05, 0.0]
    before = quality.triangle_quality(points, faces)["min_angle_deg_min"]
    assert before < 3.0
    surface = (points, np.zeros(len(points), np.int32), np.zeros((len(points), 3)))
    moved, source_faces, weights = relocate_poor_corners(surface, faces, fixed, _on_plane)
    after = quality.triangle_quality(moved, faces)["min_angle_deg_min"]
    assert after > MIN_ANGLE_DEGREES
    assert np.array_equal(moved[fixed], points[fixed])  # the boundary stays
    assert np.all(moved[:, 2] == 0.0)  # on the surface
    assert np.all(_normals_z(moved, faces) > 0)  # nothing turned over
    changed = np.flatnonzero(np.any(moved != points, axis=1))
    assert set(changed) <= {7, 14, 15}  # only corners of the poor triangles
    assert np.all(weights[changed] == 1 / 3) and np.all(source_faces == 0)  # placed with their points
    assert surface[0] is points and np.array_equal(points[14], [2.0, 2.96, 0.0])  # inputs not modified


def test_corners_that_cannot_move_stay():
    points, faces = _grid(4)
    points[5] = [1.0, 1.96, 0.0]
    surface = (points, np.zeros(len(points), np.int32), np.zeros((len(points), 3)))

    def pinned(vertices, starts, moves):  # a tip: the surface point of any move is the start
        return starts, np.zeros(len(starts), np.int32), np.zeros((len(starts), 3))

    moved, _, _ = relocate_poor_corners(surface, faces, boundary_vertices(faces, len(points)), pinned)
    assert np.array_equal(moved, points)
