"""The remesher's triangle clean-up and flips on hand-made triangulations, checked with independent angle
and orientation computations."""

import numpy as np
import pytest

from benchmarks import _quality as quality
from geomjax import icosphere
from geomjax.remesh._flips import fold_flips
from geomjax.remesh._triangulation import (
    MIN_ANGLE_DEGREES,
    bending_density,
    boundary_vertices,
    overturned_vertices,
    relabelled_triangles,
    relaxation_targets,
    relocate_poor_corners,
    topology,
)


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


@pytest.mark.parametrize("with_warp", [True, False])
def test_flip_rules_on_a_grid(with_warp, monkeypatch):
    # Every interior edge of a grid (one vertex pulled across a diagonal, so that some flips
    # would fold): flippable where the other diagonal is not an edge yet, both ends keep more
    # than three edges and both new triangles face up (+z, like the grid's), checked edge by edge;
    # every pair of the plane is flat.
    from geomjax.remesh._flips import _Pairs

    if with_warp:
        pytest.importorskip("warp")
    else:
        monkeypatch.setattr("geomjax.remesh._flips.warp_available", lambda: False)

    points, faces = _grid(5)
    points[12] += [0.9, 0.9, 0.0]
    # A triangle off the grid on the other diagonal of the quad around edge 6-12 (vertices 7
    # and 11): that flip would duplicate an edge.
    points = np.concatenate([points, [[2.0, 2.0, 1.0]]])
    faces = np.concatenate([faces, [[7, 11, 25]]]).astype(np.int32)
    stride = np.int64(len(points))
    pairs = _Pairs.of(faces, stride)
    edges = {tuple(sorted(edge)) for face in faces.tolist() for edge in zip(face, face[1:] + face[:1])}
    degree = np.zeros(len(points), int)
    for a, b in edges:
        degree[[a, b]] += 1
    expected = np.array(
        [
            tuple(sorted((p, q))) not in edges and degree[u] > 3 and degree[v] > 3 and _normals_z(points, np.array([[u, q, p], [q, v, p]])).min() > 0
            for u, v, p, q in zip(pairs.u, pairs.v, pairs.p, pairs.q)
        ]
    )
    assert expected.any() and not expected.all()
    duplicating = [(min(p, q), max(p, q)) in edges and degree[u] > 3 and degree[v] > 3 for u, v, p, q in zip(pairs.u, pairs.v, pairs.p, pairs.q)]
    assert any(duplicating)
    flat, flippable = pairs.rules(points, stride)
    np.testing.assert_array_equal(flippable, expected)
    assert flat.all()


def test_flip_rules_kernel_answers_as_its_twin():
    # Pairs of a jittered icosphere (creases of every dihedral angle) with coincident corners
    # (zero normals and gaps): the kernel decides each rule as the NumPy twin does (the same
    # roundings; the grid above checks an existing diagonal).
    pytest.importorskip("warp")
    from geomjax.remesh._flips import FLAT_FACTOR, _flip_rules, _Pairs
    from warp_ffi.remesh import flip_rules

    sphere = icosphere(3)
    rng = np.random.default_rng(7)
    points = np.asarray(sphere.points, np.float64) * rng.uniform(0.7, 1.3, (len(sphere.points), 1))
    faces = np.asarray(sphere.cells, np.int32)
    points[faces[:40, 1]] = points[faces[:40, 0]]  # coincident corners
    stride = np.int64(len(points))
    pairs = _Pairs.of(faces, stride)
    u, v, p, q = pairs.u, pairs.v, pairs.p, pairs.q
    # The last pair's first triangle flat (p on uv), its second not: its normal is the pair's.
    points[[u[-1], v[-1], p[-1], q[-1]]] = [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, -1.0, 0.0]]
    degree = np.bincount(np.concatenate([pairs.edges // stride, pairs.edges % stride]), minlength=int(stride))
    kernel = flip_rules(points, u, v, p, q, pairs.edges, degree, FLAT_FACTOR)
    twin = _flip_rules(points, u, v, p, q, pairs.edges, degree, stride)
    assert twin[1][-1]
    for ours, theirs in zip(kernel, twin):
        assert 0 < theirs.sum() < theirs.size
        np.testing.assert_array_equal(ours, theirs)


@pytest.mark.parametrize("keyed", [True, False])
def test_relabelled_triangles_keep_the_first_of_each_triangle(keyed, monkeypatch):
    # Random labels on a random triangulation: many faces collapse (two equal labels) and many
    # relabel to the same triangle in either orientation; the first of each remains, in order.
    # keyed=False: labels too large for one int64 key per triangle (the row-sorting path).
    if not keyed:
        monkeypatch.setattr("geomjax.remesh._triangulation._KEYED_INDEX_LIMIT", 4)
    # Nine labels: many repeats; a label per vertex: a few; an icosphere's faces relabelled by a
    # permutation: none.
    rng = np.random.default_rng(11)
    random_corners = np.ascontiguousarray(rng.integers(0, 60, (3, 400)))
    sphere_corners = np.ascontiguousarray(np.asarray(icosphere(1).cells).T)
    cases = [(rng.integers(0, 9, 60), random_corners), (rng.permutation(60), random_corners), (rng.permutation(42), sphere_corners)]
    for labels, corners in cases:
        labels = labels.astype(np.int32)
        seen, expected = set(), []
        for face in labels[corners].T.tolist():
            if len(set(face)) == 3 and frozenset(face) not in seen:
                seen.add(frozenset(face))
                expected.append(face)
        assert len(expected) > 10
        np.testing.assert_array_equal(relabelled_triangles(labels, corners), np.array(expected))


def test_corner_angles_kernel_gives_the_twins_bits(monkeypatch):
    # Every corner of a jittered icosphere with some coincident corners (zero angles' terms):
    # the kernel's sine and cosine terms give the NumPy twin's angles to the bit, and the
    # smallest angles agree with arccos of normalised dot products.
    pytest.importorskip("warp")
    from geomjax.remesh._triangulation import corner_angles_at, min_angles

    sphere = icosphere(2)
    rng = np.random.default_rng(5)
    points = np.asarray(sphere.points, np.float64) * rng.uniform(0.8, 1.2, (len(sphere.points), 1))
    faces = np.asarray(sphere.cells, np.int64)
    points[faces[:10, 1]] = points[faces[:10, 0]]
    apex, first, second = faces.reshape(-1), np.roll(faces, -1, axis=1).reshape(-1), np.roll(faces, -2, axis=1).reshape(-1)
    kernel = corner_angles_at(points, apex, first, second)
    smallest = min_angles(points, faces)
    with monkeypatch.context() as patch:
        patch.setattr("geomjax.remesh._triangulation.warp_available", lambda: False)
        np.testing.assert_array_equal(corner_angles_at(points, apex, first, second), kernel)
        np.testing.assert_array_equal(min_angles(points, faces), smallest)
    u, v = points[first] - points[apex], points[second] - points[apex]
    lengths = np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1)
    # (A corner with a zero side has angle 0, as arctan2(0, 0) gives.)
    cosine = np.where(lengths > 0, np.einsum("ij,ij->i", u, v) / np.where(lengths > 0, lengths, 1.0), 1.0)
    expected = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))).reshape(-1, 3).min(axis=1)
    assert (smallest == 0).sum() >= 10  # (the triangles around a moved vertex too)
    np.testing.assert_allclose(smallest, expected, atol=1e-6)


@pytest.mark.parametrize("keyed", [True, False])
def test_degree_three_vertices_go_unless_a_tip_or_a_tetrahedron(keyed, monkeypatch):
    # A grid with a vertex added inside each of three triangles (a star of three around it):
    # a vertex in the plane goes and its star becomes the triangle it split, oriented as before;
    # one well above its triangle (a tip) stays, and so does one whose triangle was kept too
    # (its link exists already). A closed tetrahedron (every vertex of degree three) stays
    # whole. keyed=False: the path for vertex indices too large for one int64 key per triangle.
    from geomjax.remesh._triangulation import DEGREE_THREE_MAX_HEIGHT, remove_degree_three

    if not keyed:
        monkeypatch.setattr("geomjax.remesh._triangulation._KEYED_INDEX_LIMIT", 4)
    points, faces = _grid(5)
    split, tip, kept = faces[5], faces[20], faces[27]
    height = 2 * DEGREE_THREE_MAX_HEIGHT * np.sqrt(2.0)  # the longest edge of a grid triangle is sqrt(2)
    stars = []
    for face, z in ((split, 0.0), (tip, height), (kept, 0.0)):
        centre = len(points)
        points = np.concatenate([points, [points[face].mean(axis=0) + [0.0, 0.0, z]]])
        stars.append([[face[0], face[1], centre], [face[1], face[2], centre], [face[2], face[0], centre]])
    others = [f for k, f in enumerate(faces.tolist()) if k not in (5, 20)]
    triangles = np.array(others + stars[0] + stars[1] + stars[2], np.int32)
    result = remove_degree_three(points, triangles, len(points))
    expected = others + stars[1] + stars[2] + [split.tolist()]
    assert sorted(map(tuple, result.tolist())) == sorted(map(tuple, expected))

    tetrahedron = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], np.int32)
    corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    np.testing.assert_array_equal(remove_degree_three(corners, tetrahedron, 4), tetrahedron)


def test_first_occurrences_are_numpys():
    from geomjax.remesh._triangulation import first_occurrences

    rng = np.random.default_rng(3)
    for keys in (rng.integers(0, 40, 300), np.arange(7)[::-1].copy(), np.zeros(5, np.int64), np.zeros(0, np.int64)):
        first, counts = first_occurrences(keys)
        _, expected_first, expected_counts = np.unique(keys, return_index=True, return_counts=True)
        np.testing.assert_array_equal(first, expected_first)
        np.testing.assert_array_equal(counts, expected_counts)


def test_fold_heights_kernel_gives_the_twins_bits():
    # Pairs of a jittered icosphere with normals bent away from the radial direction (so the
    # sagittas differ and the flipped heights rank otherwise): the kernel's heights before and
    # after a flip equal the NumPy twin's to the bit, and some pairs would gain by a flip.
    pytest.importorskip("warp")
    from geomjax.remesh._flips import FOLD_GAIN, _fold_heights, _Pairs
    from geomjax.remesh._triangulation import unit_rows
    from warp_ffi.remesh import fold_heights

    sphere = icosphere(2)
    rng = np.random.default_rng(9)
    points = np.asarray(sphere.points, np.float64) * rng.uniform(0.9, 1.1, (len(sphere.points), 1))
    unit = unit_rows(points + rng.normal(0, 0.3, points.shape))
    faces = np.asarray(sphere.cells, np.int32)
    pairs = _Pairs.of(faces, np.int64(len(points)))
    kernel = fold_heights(points, unit, faces, pairs.first, pairs.second, pairs.u, pairs.v, pairs.p, pairs.q)
    twin = _fold_heights(points, unit, faces, pairs)
    for ours, theirs in zip(kernel, twin):
        np.testing.assert_array_equal(ours, theirs)
    assert 0 < np.sum(twin[1] < (1 - FOLD_GAIN) * twin[0]) < len(twin[0])


def test_overturned_vertices_are_the_corners_of_flipped_triangles(monkeypatch):
    # A grid whose vertex 12 moves past its neighbours: the triangles around it turn over (their
    # normals' z changes sign), and their corners are flagged; a small move flags nothing.
    points, faces = _grid(5)
    for step, expect_some in ((np.array([0.2, 0.1, 0.0]), False), (np.array([2.5, 1.5, 0.0]), True)):
        moved = points.copy()
        moved[12] += step
        flipped = _normals_z(points, faces) * _normals_z(moved, faces) <= 0
        expected = np.zeros(len(points), bool)
        expected[faces[flipped].reshape(-1)] = True
        assert expected.any() == expect_some
        np.testing.assert_array_equal(overturned_vertices(points, moved, faces), expected)
        with monkeypatch.context() as patch:
            patch.setattr("geomjax.remesh._triangulation.warp_available", lambda: False)
            np.testing.assert_array_equal(overturned_vertices(points, moved, faces), expected)


def test_relaxation_targets_are_mass_weighted_circumcentres(monkeypatch):
    # A jittered icosphere (some obtuse triangles) and one vertex in no triangle: each free
    # vertex goes to the area- (times mean density-) weighted mean of its triangles'
    # circumcentres, an obtuse triangle's replaced by its longest edge's midpoint; each
    # circumcentre solved for here as the point of the triangle's plane equidistant from its
    # corners. The Warp kernel and the NumPy twin give the same bits.
    sphere = icosphere(2)
    rng = np.random.default_rng(4)
    points = np.asarray(sphere.points, np.float64) * rng.uniform(0.9, 1.1, (len(sphere.points), 1)) + rng.normal(0, 0.03, (len(sphere.points), 3))
    points = np.concatenate([points, [[5.0, 5.0, 5.0]]])
    faces = np.asarray(sphere.cells, np.int32)
    fixed = np.zeros(len(points), bool)
    fixed[[0, 7]] = True
    rho = rng.uniform(0.5, 2.0, len(points))
    for density in (None, rho):
        expected_sum, expected_mass = np.zeros((len(points), 3)), np.zeros(len(points))
        obtuse_count = 0
        for face in faces:
            a, b, c = points[face]
            ab, ac = b - a, c - a
            st = np.linalg.solve([[ab @ ab, ab @ ac], [ab @ ac, ac @ ac]], [ab @ ab / 2, ac @ ac / 2])
            centre = a + st[0] * ab + st[1] * ac
            edges = [(b, c), (a, c), (a, b)]
            lengths = [np.sum((q - p) ** 2) for p, q in edges]
            longest = int(np.argmax(lengths))
            if lengths[longest] >= sum(lengths) - lengths[longest]:
                obtuse_count += 1
                centre = (edges[longest][0] + edges[longest][1]) / 2
            mass = np.linalg.norm(np.cross(ab, ac)) / 2 * (1.0 if density is None else density[face].mean())
            expected_sum[face] += mass * centre
            expected_mass[face] += mass
        expected = points.copy()
        free = (expected_mass > 0) & ~fixed
        expected[free] = expected_sum[free] / expected_mass[free, None]
        assert obtuse_count > 0 and not free[-1]
        targets = relaxation_targets(points, faces, density, fixed)
        np.testing.assert_allclose(targets, expected, rtol=1e-12, atol=1e-12)
        with monkeypatch.context() as patch:
            patch.setattr("geomjax.remesh._triangulation.warp_available", lambda: False)
            np.testing.assert_array_equal(relaxation_targets(points, faces, density, fixed), targets)


def test_bending_density_follows_the_arc_heights_over_the_edges(monkeypatch):
    # On a sphere of radius R a chord of length L stands R - sqrt(R^2 - L^2 / 4) below its arc;
    # with the exact normals the estimate is L^2 / (8 R), the same to relative order (L / R)^2.
    sphere = icosphere(2)
    radius = 3.0
    points, faces = np.asarray(sphere.points, np.float64) * radius, np.asarray(sphere.cells)
    tail, head = faces.reshape(-1), np.roll(faces, -1, axis=1).reshape(-1)
    chord = np.linalg.norm(points[head] - points[tail], axis=1)
    height = radius - np.sqrt(radius**2 - chord**2 / 4)
    largest = np.zeros(len(points))
    np.maximum.at(largest, tail, height)
    expected = 1 + (largest / largest.mean()) ** 2
    assert np.ptp(expected) > 0.1  # the icosphere's edges differ in length
    density = bending_density(points, faces, 5.0 * points)  # normals of any length
    np.testing.assert_allclose(density, expected, rtol=2 * (chord.max() / radius) ** 2)
    # The Warp kernel's largest sagittas and the NumPy twin's: the same bits (jittered: no ties).
    jittered = points + np.random.default_rng(1).normal(0, 0.05, points.shape)
    density = bending_density(jittered, faces, jittered)
    monkeypatch.setattr("geomjax.remesh._triangulation.warp_available", lambda: False)
    np.testing.assert_array_equal(bending_density(jittered, faces, jittered), density)


def test_bending_density_ignores_flat_directions():
    plane, faces = _grid(5)
    np.testing.assert_array_equal(bending_density(plane, faces, np.tile([0.0, 0.0, 2.0], (len(plane), 1))), 1.0)
    # A quarter cylinder, unevenly divided around its axis (grid columns), evenly along it
    # (grid rows): it bends across the axis only, so stretching it along the axis changes nothing.
    around = np.array([0.0, 0.1, 0.3, 0.8, np.pi / 2])[plane[:, 1].astype(int)]
    normals = np.stack([np.cos(around), np.sin(around), np.zeros_like(around)], axis=1)
    densities = [bending_density(normals + [0.0, 0.0, step] * plane[:, :1], faces, normals) for step in (0.2, 5.0)]
    assert np.ptp(densities[0]) > 0.5
    np.testing.assert_allclose(densities[0], densities[1], rtol=1e-12)


def _ridge(points_xy):
    """Points on the parabolic ridge z = -x^2 / 2 (running along y), and its unit normals."""
    x = points_xy[:, 0]
    points = np.stack([x, points_xy[:, 1], -(x**2) / 2], axis=1)
    normals = np.stack([x, np.zeros_like(x), np.ones_like(x)], axis=1)
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _distance_to_ridge(points, _vertices=None):
    """Distance to z = -x^2 / 2 by a dense search over x (the surface is invariant along y)."""
    grid = np.linspace(-3, 3, 3001)  # steps of 0.002: distances within 1e-5
    dx = points[:, :1] - grid
    dz = points[:, 2:] + grid**2 / 2
    return np.sqrt(np.min(dx**2 + dz**2, axis=1))


def _sampled_height(points, faces):
    a, b, c = (points[faces[:, k]] for k in range(3))
    w = np.random.default_rng(0).dirichlet(np.ones(3), 60)
    samples = np.einsum("sk,fkd->fsd", w, np.stack([a, b, c], axis=1)).reshape(-1, 3)
    return _distance_to_ridge(samples).max()


def test_fold_flips_turn_diagonals_along_the_ridge():
    # A grid turned by 45 degrees over the ridge: each cell's diagonal runs across the ridge
    # (along x) or along it (along y). Cut every cell across: the cells on the ridge then pass
    # 1/8 below it, and turning their diagonals along the ridge brings the whole mesh within
    # 0.09 (the next cells out, where the ridge bends less).
    i, j = np.meshgrid(np.arange(-3, 4), np.arange(-3, 4), indexing="ij")
    xy = np.stack([(i + j) * 0.5, (i - j) * 0.5], axis=-1).reshape(-1, 2)
    n = 7
    a = ((i[:-1, :-1] + 3) * n + (j[:-1, :-1] + 3)).reshape(-1)
    b, c, d = a + n, a + n + 1, a + 1  # corners (i+1, j), (i+1, j+1), (i, j+1)
    # Corners a and c differ in x only (the across diagonal): triangles (a, b, c) and (a, c, d).
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    points, normals = _ridge(xy)
    orientation = np.cross(points[faces[:, 1]] - points[faces[:, 0]], points[faces[:, 2]] - points[faces[:, 0]])[:, 2]
    faces[orientation < 0] = faces[orientation < 0][:, ::-1]
    before = _sampled_height(points, faces)
    flipped = fold_flips(points, faces, 3.0 * normals, _distance_to_ridge)
    after = _sampled_height(points, flipped)
    assert before > 0.12 and after < 0.09
    assert topology(flipped) == topology(faces)  # a disk still
    changed = np.flatnonzero(np.any(np.sort(flipped, axis=1) != np.sort(faces, axis=1), axis=1))
    assert changed.size >= 2
    # Every changed triangle has its new edge along the ridge (the two corners with equal x).
    for face in flipped[changed]:
        assert any(np.isclose(points[face[k], 0], points[face[(k + 1) % 3], 0]) for k in range(3))


def test_fold_flips_leave_a_plane_alone():
    points, faces = _grid(5)
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    np.testing.assert_array_equal(fold_flips(points, faces, normals, lambda p, v: np.abs(p[:, 2])), faces)
