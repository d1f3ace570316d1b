"""The mesh operators on real, imperfect meshes, against independent NumPy/SciPy computations.

The shared libigl meshes (``tests/shared_meshes.py``) are scans, CAD parts, open surfaces and
tetrahedral volumes; every answer here is checked against a computation written in this file
with NumPy and SciPy only (never another path of the library):

* exact point-to-triangle distances (Ericson's closest point, region by region, in float64);
* the generalized winding number (sum of Van Oosterom-Strackee solid angles over ``4 pi``);
* Moller-Trumbore ray/triangle intersection over every triangle;
* enclosed volumes by the divergence theorem, tetrahedron volumes and St. Venant-Kirchhoff
  energies from deformation gradients, and the Sobolev system assembled and solved with SciPy;
* meshio's own reading of each file.

References are cached per module and the query counts are shared between tests (1,000 points,
300 rays) so that the file stays fast on a two-core CI machine: few distinct array shapes, hence
few compiled programs. Tolerances are multiples of the working dtype's epsilon times the scene
scale (the meshes are normalised to the unit box) or a conditioning bound; each says why.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg
from scipy.spatial import cKDTree

import geomjax
from tests.shared_meshes import MESH_DIR, requires_shared_meshes, shared_surface, shared_volume

EPS64 = float(np.finfo(np.float64).eps)
EPS32 = float(np.finfo(np.float32).eps)
NUM_QUERIES = 1000  # query points per surface test (one shape: one compiled program per op)
NUM_RAYS = 300


# ---------------------------------------------------------------------------------------------
# Independent references (NumPy / SciPy)
# ---------------------------------------------------------------------------------------------


def _dot(u, v):
    return np.einsum("...i,...i->...", u, v)


def closest_points_on_triangles(p, a, b, c):
    """Closest point of triangle ``abc`` to ``p`` (arrays ``(..., 3)``), Ericson's region method.

    Real-Time Collision Detection, 5.1.5: the Voronoi regions of the three vertices, then of the
    three edges, else the interior, tested in that order on the same six dot products.
    """
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):  # the unselected regions may divide by 0
        on_ab = a + (d1 / (d1 - d3))[..., None] * ab
        on_ac = a + (d2 / (d2 - d6))[..., None] * ac
        on_bc = b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[..., None] * (c - b)
        total = va + vb + vc
        inside = a + (vb / total)[..., None] * ab + (vc / total)[..., None] * ac
    regions = [
        (d1 <= 0) & (d2 <= 0),  # vertex a
        (d3 >= 0) & (d4 <= d3),  # vertex b
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge ab
        (d6 >= 0) & (d5 <= d6),  # vertex c
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge ac
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),  # edge bc
    ]
    return np.select([region[..., None] for region in regions], [a, b, on_ab, c, on_ac, on_bc], inside)


def distance_to_faces(points, vertices, faces, face_ids):
    """Distance from each point to its own triangle ``faces[face_ids]``."""
    corners = vertices[faces[face_ids]]
    closest = closest_points_on_triangles(points, corners[:, 0], corners[:, 1], corners[:, 2])
    return np.linalg.norm(points - closest, axis=-1)


def nearest_on_mesh(points, vertices, faces):
    """Exact nearest face (lowest index on ties), distance and closest point of each point.

    Every point/face pair is measured with :func:`closest_points_on_triangles` unless a bound
    proves the face farther than the point's nearest mesh vertex (itself a point of the mesh):
    the face lies in the ball about its centroid ``c`` of radius ``r`` (farthest corner), so it is
    at least ``|p - c| - r`` away. Pairs are found with SciPy's k-d trees; the answer is the same
    as measuring every pair, at a fraction of the cost.
    """
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    centroids = (a + b + c) / 3
    radii = np.sqrt(np.max([_dot(corner - centroids, corner - centroids) for corner in (a, b, c)], axis=0))
    upper = cKDTree(vertices[np.unique(faces)]).query(points)[0]
    # The ball radius is widened by 1e-9 so that rounding in the bound never drops a face.
    lists = cKDTree(centroids).query_ball_point(points, upper + radii.max() + 1e-9)
    point_ids = np.repeat(np.arange(len(points)), [len(found) for found in lists])
    face_ids = np.concatenate(lists).astype(np.intp)
    keep = np.linalg.norm(points[point_ids] - centroids[face_ids], axis=1) - radii[face_ids] <= upper[point_ids] + 1e-9
    point_ids, face_ids = point_ids[keep], face_ids[keep]
    closest = closest_points_on_triangles(points[point_ids], a[face_ids], b[face_ids], c[face_ids])
    distance = np.linalg.norm(points[point_ids] - closest, axis=1)
    order = np.lexsort((face_ids, distance, point_ids))  # per point: nearest, then lowest face id
    first = order[np.r_[True, point_ids[order][1:] != point_ids[order][:-1]]]
    assert np.array_equal(point_ids[first], np.arange(len(points)))
    return distance[first], face_ids[first], closest[first]


def winding_numbers(points, vertices, faces, chunk=8):
    """Generalized winding number: the solid angles of all faces (Van Oosterom-Strackee) / 4 pi.

    ``tan(omega / 2) = a . (b x c) / (|a||b||c| + (a.b)|c| + (b.c)|a| + (c.a)|b|)`` with ``a, b,
    c`` the corners relative to the point. Every face, every point, in chunks of points.
    """
    corners = [np.ascontiguousarray(vertices[faces[:, k]].T) for k in range(3)]  # (3, F) each
    result = np.empty(len(points))
    for start in range(0, len(points), chunk):
        p = points[start : start + chunk, :, None]
        a, b, c = (corner[None] - p for corner in corners)  # (n, 3, F)
        la, lb, lc = (np.sqrt((x * x).sum(1)) for x in (a, b, c))
        triple = (
            a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1])
            + a[:, 1] * (b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2])
            + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
        )
        denominator = la * lb * lc + (a * b).sum(1) * lc + (b * c).sum(1) * la + (c * a).sum(1) * lb
        result[start : start + chunk] = np.arctan2(triple, denominator).sum(1) / (2 * np.pi)
    return result


def enclosed_volume(vertices, faces):
    """Signed volume of a closed triangle surface (divergence theorem) and its conditioning.

    Returns ``(V, sum |terms| / |V|)``: the second is the cancellation factor of the sum.
    """
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    terms = _dot(a, np.cross(b, c)) / 6
    return terms.sum(), np.abs(terms).sum() / abs(terms.sum())


def box_queries(vertices, seed, count=NUM_QUERIES):
    """``count`` uniform points in the mesh's bounding box grown by 10% (5% of each extent per side)."""
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    margin = 0.05 * (high - low)
    return np.random.default_rng(seed).uniform(low - margin, high + margin, (count, 3))


@functools.cache
def _surface_queries(name):
    """The queries of a shared surface with their exact nearest faces and winding numbers."""
    vertices, faces = shared_surface(name)
    points = box_queries(vertices, seed=sum(map(ord, name)))
    distance, face_ids, closest = nearest_on_mesh(points, vertices, faces)
    return points, distance, face_ids, closest, winding_numbers(points, vertices, faces)


def _sliver_free(vertices, faces):
    """Whether no face is a sliver by Warp's rule (``|AB x AC| < 1e-6 (|AB|^2 + |AC|^2 + |BC|^2)``),
    the faces the distance queries ignore: then the reference may measure every face."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    squares = sum(_dot(x - y, x - y) for x, y in ((b, a), (c, a), (c, b)))
    return bool(np.all(np.linalg.norm(np.cross(b - a, c - a), axis=1) >= 1e-6 * squares))


# ---------------------------------------------------------------------------------------------
# signed_distance_field
# ---------------------------------------------------------------------------------------------

# Both sides compute in float64 from the same float64 inputs: the distances differ by the
# rounding of two formulas, a few ulps of the coordinates (the unit box: scale 1).
SDF_TOLERANCE = 64 * EPS64


def _check_sdf(name, winding):
    """signed_distance_field on the shared queries of ``name``: distances, closest points, faces, signs."""
    vertices, faces = shared_surface(name)
    assert _sliver_free(vertices, faces)
    points, distance, _, _, reference_winding = _surface_queries(name)
    sdf, hit_points, hit_faces = (
        np.asarray(x) for x in geomjax.signed_distance_field(jnp.asarray(vertices), jnp.asarray(faces), jnp.asarray(points), use_sign_winding_number=winding)
    )
    assert sdf.dtype == hit_points.dtype == np.float64 and hit_faces.dtype == np.int32
    np.testing.assert_allclose(np.abs(sdf), distance, rtol=SDF_TOLERANCE, atol=SDF_TOLERANCE)
    # The closest point is at the reported distance, on the reported face, and that face is at
    # the same distance from the query.
    np.testing.assert_allclose(np.linalg.norm(points - hit_points, axis=1), distance, rtol=SDF_TOLERANCE, atol=SDF_TOLERANCE)
    assert np.all((hit_faces >= 0) & (hit_faces < len(faces)))
    np.testing.assert_allclose(distance_to_faces(points, vertices, faces, hit_faces), distance, rtol=SDF_TOLERANCE, atol=SDF_TOLERANCE)
    np.testing.assert_allclose(distance_to_faces(hit_points, vertices, faces, hit_faces), 0.0, atol=SDF_TOLERANCE)
    # The sign, wherever the inside test is unambiguous: the winding number far from 0.5 (the Warp
    # path's Barnes-Hut winding number errs far less than 0.25 there) and the point off the surface
    # (the sign of points within float32 rounding of it comes from float32).
    confident = (np.abs(reference_winding - 0.5) > 0.25) & (distance > 1e-3)
    inside = reference_winding > 0.5
    assert confident.sum() > 0.8 * len(points) and (confident & inside).sum() > 50
    wrong = np.flatnonzero(confident & ((sdf < 0) != inside))
    assert wrong.size == 0, f"{wrong.size} wrong signs, e.g. points {points[wrong[:3]]} sdf {sdf[wrong[:3]]} winding {reference_winding[wrong[:3]]}"


@requires_shared_meshes
@pytest.mark.parametrize("winding", [False, True], ids=["normal-sign", "winding-sign"])
def test_signed_distance_on_a_closed_genus_4_scan(winding):
    # fertility.off: closed, consistently and outward oriented, so both signs classify every
    # confident point as the winding number does.
    vertices, faces = shared_surface("fertility.off")
    assert enclosed_volume(vertices, faces)[0] > 0  # outward: the winding number is +1 inside
    _check_sdf("fertility.off", winding)


@requires_shared_meshes
def test_signed_distance_winding_sign_on_an_open_scan():
    # camelhead.off has a boundary loop (the neck): the winding number is fractional near it,
    # but a point far from 0.5 is unambiguous, and the winding sign must classify it.
    vertices, faces = shared_surface("camelhead.off")
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    assert np.any(np.unique(edges, axis=0, return_counts=True)[1] == 1)  # open indeed
    _check_sdf("camelhead.off", True)


# ---------------------------------------------------------------------------------------------
# ray_mesh_intersect
# ---------------------------------------------------------------------------------------------


def _screwdriver_rays():
    """Rays from a sphere around the CAD part: 2/3 aimed at points just inside the surface
    (which must hit), 1/3 in random directions (hits and misses)."""
    vertices, faces = shared_surface("screwdriver.off")
    rng = np.random.default_rng(7)
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    radius = np.linalg.norm(vertices - centre, axis=1).max() * 1.5
    origins = centre + radius * _unit(rng.normal(size=(NUM_RAYS, 3)))
    aimed = 2 * NUM_RAYS // 3
    corners = vertices[faces[rng.integers(len(faces), size=aimed)]]
    weights = rng.dirichlet(np.ones(3), size=aimed)
    normals = _unit(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
    targets = np.einsum("nk,nkd->nd", weights, corners) - 1e-3 * normals  # outward normals: 1e-3 inside
    directions = np.concatenate([targets - origins[:aimed], rng.normal(size=(NUM_RAYS - aimed, 3))])
    return vertices, faces, origins, directions


def _unit(vectors):
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def moller_trumbore(origins, directions, vertices, faces, chunk=50):
    """Every ray against every triangle (float64): ``(t, margin, cosine)``, each ``(rays, faces)``.

    ``t`` is the distance along the unit direction to the triangle's plane (NaN when parallel),
    ``margin`` the signed in-plane distance of that crossing to the triangle's boundary as
    ``min_k lambda_k h_k`` (barycentric times altitude: exact inside, and outside at most the
    true distance in magnitude), ``cosine`` the ray's ``|cos|`` to the face normal.
    """
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    normal = np.cross(e1, e2)
    twice_area = np.linalg.norm(normal, axis=1)
    altitudes = np.stack([twice_area / np.linalg.norm(c - b, axis=1), twice_area / np.linalg.norm(e2, axis=1), twice_area / np.linalg.norm(e1, axis=1)])
    units = _unit(directions)
    t, margin, cosine = (np.empty((len(origins), len(faces))) for _ in range(3))
    for s in range(0, len(origins), chunk):
        o, d = origins[s : s + chunk, None], units[s : s + chunk, None]
        pvec = np.cross(d, e2)
        determinant = _dot(e1, pvec)
        tvec = o - a
        qvec = np.cross(tvec, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = _dot(tvec, pvec) / determinant, _dot(d, qvec) / determinant
            t[s : s + chunk] = _dot(e2, qvec) / determinant
        weights = np.stack([1 - u - v, u, v])
        margin[s : s + chunk] = (weights * altitudes[:, None]).min(axis=0)
        cosine[s : s + chunk] = np.abs(determinant) / twice_area
    return t, margin, cosine


@requires_shared_meshes
def test_ray_mesh_intersect_on_a_cad_part_against_brute_force_moller_trumbore():
    vertices, faces, origins, directions = _screwdriver_rays()
    # float32 inputs: the Warp search and the replay compute in float32 (the docstring's rule);
    # the reference computes exactly (float64) on the same float32 numbers.
    v32, o32, d32 = (x.astype(np.float32) for x in (vertices, origins, directions))
    hit, distance, hit_points, hit_faces, normals = (
        np.asarray(x) for x in geomjax.ray_mesh_intersect(jnp.asarray(v32), jnp.asarray(faces), jnp.asarray(o32), jnp.asarray(d32))
    )
    v64, o64, d64 = (x.astype(np.float64) for x in (v32, o32, d32))
    t, margin, cosine = moller_trumbore(o64, d64, v64, faces)
    # float32 rounding moves a computed crossing by ~eps32 times the coordinates' scale along the
    # ray and across it, divided by the cosine of incidence (the conditioning of a ray-plane
    # intersection); 64 ulps of margin.
    scale = max(np.abs(v64).max(), np.abs(o64).max())
    tolerance = 64 * EPS32 * scale / np.maximum(cosine, 1e-3)  # (all but parallel: ambiguous anyway)
    certain = (t > tolerance) & (margin > tolerance)  # a hit whatever the rounding
    possible = (t > -tolerance) & (margin > -tolerance)  # not excluded by more than rounding
    certain_hit, possible_hit = certain.any(axis=1), possible.any(axis=1)
    assert certain_hit.sum() >= 2 * NUM_RAYS // 3 - 5 and (~possible_hit).sum() > 20  # both kinds are tested
    assert np.all(hit[certain_hit]) and not np.any(hit[~possible_hit])
    # Distances: no nearer than any possible crossing, no farther than the nearest certain one.
    lowest = np.where(possible, t - tolerance, np.inf).min(axis=1)
    highest = np.where(certain, t + tolerance, np.inf).min(axis=1)
    assert np.all(distance[~hit] == np.inf) and np.all(hit_faces[~hit] == -1)
    assert np.all((lowest[hit] <= distance[hit]) & (distance[hit] <= highest[hit]))
    # Face ids where the nearest certain hit is alone: every other possible crossing is farther
    # by more than the two tolerances.
    nearest = np.where(certain, t, np.inf).argmin(axis=1)
    rows = np.arange(NUM_RAYS)
    others = np.where(possible, t - tolerance, np.inf)
    others[rows, nearest] = np.inf
    alone = certain_hit & (others.min(axis=1) > t[rows, nearest] + tolerance[rows, nearest])
    assert alone.sum() > 0.9 * certain_hit.sum()
    np.testing.assert_array_equal(hit_faces[alone], nearest[alone])
    # The hit point is on the ray at the reported distance, the normal the hit face's unit normal.
    ray_points = o64[hit] + distance[hit, None] * _unit(d64[hit])
    np.testing.assert_allclose(hit_points[hit], ray_points, atol=64 * EPS32 * scale)
    corners = v64[faces[hit_faces[hit]]]
    face_normals = _unit(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
    # A float32 cross product errs by eps32 |e1| |e2| / |e1 x e2| relative to the unit normal.
    skew = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1) * np.linalg.norm(corners[:, 2] - corners[:, 0], axis=1)
    skew /= np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    assert np.all(np.abs(normals[hit] - face_normals) <= 64 * EPS32 * skew[:, None])


# ---------------------------------------------------------------------------------------------
# shrinkwrap_points
# ---------------------------------------------------------------------------------------------


@requires_shared_meshes
def test_shrinkwrap_onto_an_open_scan_moves_points_to_their_exact_closest_points():
    # lion.off: open, detailed. float64 is searched exactly (the docstring), so every point lands
    # on its brute-force closest point up to float64 rounding (64 ulps of the unit box); the gate
    # max_distance leaves the quarter of the points at or beyond it in place, bit for bit.
    vertices, faces = shared_surface("lion.off")
    points, distance, _, closest, _ = _surface_queries("lion.off")
    gate = float(np.quantile(distance, 0.75))
    moved = np.asarray(geomjax.shrinkwrap_points(jnp.asarray(points), jnp.asarray(vertices), jnp.asarray(faces), max_distance=gate))
    assert moved.dtype == np.float64
    near = distance < gate * (1 - 1e-9)  # away from the gate by more than rounding
    far = distance > gate * (1 + 1e-9)
    assert near.sum() > 0.7 * len(points) and far.sum() > 0.2 * len(points)
    np.testing.assert_allclose(moved[near], closest[near], rtol=0, atol=64 * EPS64)
    np.testing.assert_array_equal(moved[far], points[far])


# ---------------------------------------------------------------------------------------------
# mesh_to_voxel_fraction
# ---------------------------------------------------------------------------------------------


@requires_shared_meshes
def test_voxel_fractions_of_a_closed_genus_3_mesh():
    vertices, faces = shared_surface("3holes.off")
    volume, cancellation = enclosed_volume(vertices, faces)
    assert volume > 0 and cancellation < 10  # outward, and the sum is well conditioned
    # A grid 0.05 wider than the mesh's box on each side, voxels of h = 1/18 (20 x 11 x 8 here).
    h = 1 / 18
    origin = vertices.min(axis=0) - 0.05
    dims = tuple(int(n) for n in np.ceil((vertices.max(axis=0) + 0.05 - origin) / h))
    fractions = np.asarray(geomjax.mesh_to_voxel_fraction(jnp.asarray(vertices), jnp.asarray(faces), origin=origin, voxel_size=h, grid_dims=dims))
    assert fractions.shape == dims[::-1] and fractions.dtype == np.float32
    assert np.all((fractions >= 0) & (fractions <= 1))
    # Total volume. The default 64 samples stratify each voxel into 4^3 sub-cubes of edge
    # s = h / 4, one jittered sample each: only sub-cubes the surface crosses err, each by at
    # most s^3, independently and with mean zero. A surface of area A crosses at most about
    # sqrt(3) A / s^2 of them (doubled for curvature and edge effects), so by Hoeffding's
    # inequality the total errs by more than s^3 sqrt(N ln(2 / delta) / 2) with probability
    # below delta = 1e-6.
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    s = h / 4
    crossed = 2 * np.sqrt(3) * area / s**2
    tolerance = s**3 * np.sqrt(crossed * np.log(2 / 1e-6) / 2)
    assert abs(fractions.sum(dtype=np.float64) * h**3 - volume) < tolerance, (fractions.sum() * h**3, volume, tolerance)
    # A voxel whose centre is farther from the surface than half its diagonal holds no surface
    # (the cube lies in that ball): exactly 0 or 1, as the winding number of its centre (an
    # integer up to rounding there). The full diagonal would leave no inside voxel of this thin
    # part at a grid this coarse.
    k, j, i = np.meshgrid(*(np.arange(n) for n in dims[::-1]), indexing="ij")
    centres = origin + h * (np.stack([i, j, k], axis=-1).reshape(-1, 3) + 0.5)
    far = nearest_on_mesh(centres, vertices, faces)[0] > np.sqrt(3) / 2 * h * (1 + 1e-9)
    winding = winding_numbers(centres[far], vertices, faces)
    assert np.all(np.abs(winding - np.round(winding)) < 1e-9)
    assert far.sum() > 0.3 * len(centres) and (winding > 0.5).sum() > 100  # both states tested
    np.testing.assert_array_equal(fractions.reshape(-1)[far], (winding > 0.5).astype(np.float32))


# ---------------------------------------------------------------------------------------------
# mesh_poisson_disk_sample
# ---------------------------------------------------------------------------------------------

# Samples are float32: the vertices rounded to float32 (eps32 / 2 of the unit box), barycentric
# combinations in float32 (a few eps32) and the output rounded to float32; 16 ulps of the scale.
SURFACE_TOLERANCE = 16 * EPS32


@requires_shared_meshes
def test_poisson_disk_samples_lie_on_the_surface_and_keep_their_spacing():
    vertices, faces = shared_surface("lion.off")
    min_distance = 0.03
    samples = np.asarray(geomjax.mesh_poisson_disk_sample(jnp.asarray(vertices), jnp.asarray(faces), min_distance=min_distance))
    assert samples.dtype == np.float32 and len(samples) > 500
    samples = samples.astype(np.float64)
    assert nearest_on_mesh(samples, vertices, faces)[0].max() < SURFACE_TOLERANCE
    # The documented guarantee: any two samples at least min_distance apart, exactly, measured
    # on the returned coordinates (float64 distances of float32 numbers are exact to 1e-16).
    gaps = cKDTree(samples).query(samples, k=2)[0][:, 1]
    assert gaps.min() >= min_distance, gaps.min()
    # Dart throwing stops after an iteration that accepts nothing, i.e. whose 131,072 uniform
    # candidates all fell within min_distance of a sample (a survivor of that test would have
    # won its conflicts or lost to one that did). A vertex 2 min_distance from every sample would
    # leave a patch of area ~pi min_distance^2 (a thousandth of this surface) free of candidates:
    # probability exp(-100) or less. So every vertex is nearer than that.
    assert cKDTree(samples).query(vertices)[0].max() < 2 * min_distance


@requires_shared_meshes
def test_weighted_sample_elimination_keeps_its_relaxed_samples_on_the_surface():
    # The relaxation step moves every survivor and projects it back onto the surface.
    vertices, faces = shared_surface("lion.off")
    samples = geomjax.mesh_poisson_disk_sample(jnp.asarray(vertices), jnp.asarray(faces), mode="weighted_sample_elimination", target_num_points=NUM_QUERIES)
    assert samples.shape == (NUM_QUERIES, 3)
    samples = np.asarray(samples, np.float64)
    assert nearest_on_mesh(samples, vertices, faces)[0].max() < SURFACE_TOLERANCE
    assert len(np.unique(samples, axis=0)) == NUM_QUERIES


# ---------------------------------------------------------------------------------------------
# Energies on a tetrahedral volume
# ---------------------------------------------------------------------------------------------


@functools.cache
def _octopus():
    """The octopus's rest points, a smooth deformation of them, its tetrahedra and its boundary."""
    rest, tetrahedra = shared_volume("octopus-low.mesh")
    surface_points, triangles = shared_surface("octopus-low.mesh")
    assert np.array_equal(surface_points, rest)  # one normalisation, one point array
    current = rest + 0.05 * np.sin(4 * rest[:, [1, 2, 0]]) + 0.02 * rest
    return rest, current, tetrahedra, triangles


def _edge_matrices(points, tetrahedra):
    """``(C, 3, 3)`` matrices whose columns are the edges ``x_k - x_0``."""
    corners = points[tetrahedra]
    return np.stack([corners[:, k] - corners[:, 0] for k in (1, 2, 3)], axis=-1)


@requires_shared_meshes
def test_tetrahedral_measure_and_strain_energies_against_deformation_gradients():
    rest, current, tetrahedra, _ = _octopus()
    rest_edges, edges = _edge_matrices(rest, tetrahedra), _edge_matrices(current, tetrahedra)
    rest_det, det = np.linalg.det(rest_edges), np.linalg.det(edges)
    volume0, ratios = np.abs(rest_det) / 6, det / rest_det
    assert np.all(rest_det > 0) and np.all(det > 0)  # the deformation inverts nothing
    # Rounding: determinants and solves of 3x3 edge matrices err relatively by about eps64 times
    # their condition numbers (Higham), which the reduced edge form of the library shares up to a
    # small factor; 16 ulps of that, per cell, carried through each term's derivative.
    conditioning = np.linalg.cond(rest_edges) + np.linalg.cond(edges)
    args = (jnp.asarray(current), jnp.asarray(rest), jnp.asarray(tetrahedra))

    target = 1.1
    measure = np.asarray(geomjax.simplex_measure_energy(*args, target_ratio=target, reduction="none"))
    expected = 0.5 * volume0 * (ratios - target) ** 2
    # d term / d q = V0 (q - q*), with q known to eps64 cond |q|.
    tolerance = 16 * EPS64 * (conditioning * volume0 * np.abs(ratios - target) * np.abs(ratios) + expected)
    assert np.all(np.abs(measure - expected) <= tolerance), np.abs(measure - expected).max()

    lame, mu = 2.0, 0.7
    strain = np.asarray(geomjax.simplex_strain_energy(*args, lame_lambda=lame, shear_modulus=mu, reduction="none"))
    gradients = edges @ np.linalg.inv(rest_edges)  # F = D_s D_m^-1
    green = 0.5 * (np.swapaxes(gradients, 1, 2) @ gradients - np.eye(3))
    trace = np.trace(green, axis1=1, axis2=2)
    expected = volume0 * (mu * (green**2).sum(axis=(1, 2)) + 0.5 * lame * trace**2)
    # dW/dF : F is at most V0 (2 mu + 3 lambda) |eps| |F|^2, with F known to eps64 cond |F|.
    sensitivity = volume0 * (2 * mu + 3 * lame) * np.linalg.norm(green, axis=(1, 2)) * np.linalg.norm(gradients, axis=(1, 2)) ** 2
    tolerance = 16 * EPS64 * (conditioning * sensitivity + expected)
    assert np.all(np.abs(strain - expected) <= tolerance), np.abs(strain - expected).max()
    total = float(geomjax.simplex_strain_energy(*args, lame_lambda=lame, shear_modulus=mu))
    np.testing.assert_allclose(total, expected.sum(), atol=tolerance.sum())


@requires_shared_meshes
def test_closed_surface_volume_energy_of_the_tetrahedral_boundary():
    # The boundary triangles enclose exactly the tetrahedra: the volumes (divergence theorem)
    # agree with the sum of tetrahedron determinants, and the energy follows from them.
    rest, current, tetrahedra, triangles = _octopus()
    volume0, cancellation0 = enclosed_volume(rest, triangles)
    volume, cancellation = enclosed_volume(current, triangles)
    rtol = 64 * EPS64 * max(cancellation0, cancellation)  # the sums' cancellation factors
    np.testing.assert_allclose(volume0, np.linalg.det(_edge_matrices(rest, tetrahedra)).sum() / 6, rtol=rtol)
    np.testing.assert_allclose(volume, np.linalg.det(_edge_matrices(current, tetrahedra)).sum() / 6, rtol=rtol)
    target = 1.2
    energy = float(geomjax.closed_surface_volume_energy(jnp.asarray(current), jnp.asarray(rest), jnp.asarray(triangles), target_ratio=target))
    expected = 0.5 * abs(volume0) * (volume / volume0 - target) ** 2
    np.testing.assert_allclose(energy, expected, rtol=4 * rtol / abs(volume / volume0 - target))


# ---------------------------------------------------------------------------------------------
# sobolev_deform_points
# ---------------------------------------------------------------------------------------------


def tetrahedral_stiffness(points, tetrahedra):
    """P1 stiffness ``K_ij = sum |T| grad(phi_i) . grad(phi_j)`` (SciPy CSR) and the cell volumes."""
    edges = _edge_matrices(points, tetrahedra)
    volumes = np.abs(np.linalg.det(edges)) / 6
    inverse = np.linalg.inv(edges)  # rows: gradients of the barycentric coordinates 1, 2, 3
    gradients = np.concatenate([-inverse.sum(axis=1, keepdims=True), inverse], axis=1)  # (C, 4, 3)
    local = volumes[:, None, None] * gradients @ np.swapaxes(gradients, 1, 2)
    rows = np.repeat(tetrahedra, 4, axis=1).ravel()
    columns = np.tile(tetrahedra, (1, 4)).ravel()
    stiffness = sparse.csr_matrix((local.ravel(), (rows, columns)), shape=(len(points),) * 2)
    return stiffness, volumes


@requires_shared_meshes
def test_sobolev_deform_on_a_tetrahedral_volume_against_a_sparse_direct_solve():
    rest, _, tetrahedra, _ = _octopus()
    length = 0.1
    displacement = 0.01 * np.sin(3 * rest[:, [1, 2, 0]])
    fixed = rest[:, 2] < np.quantile(rest[:, 2], 0.1)  # the lowest tenth held in place
    moved = np.asarray(
        geomjax.sobolev_deform_points(
            jnp.asarray(rest), jnp.asarray(tetrahedra), jnp.asarray(displacement), length_scale=length, fixed_points=jnp.asarray(fixed)
        )
    )
    np.testing.assert_array_equal(moved[fixed], rest[fixed])
    # (M + l^2 K) u = M d with M = m I, m the mean lumped vertex mass (every vertex is in a
    # tetrahedron here), fixed rows and columns removed.
    stiffness, volumes = tetrahedral_stiffness(rest, tetrahedra)
    assert np.all(np.bincount(tetrahedra.ravel(), minlength=len(rest)) > 0)
    mass = volumes.sum() / len(rest)
    free = np.flatnonzero(~fixed)
    system = (mass * sparse.identity(len(rest)) + length**2 * stiffness).tocsr()[free][:, free]
    rhs = mass * displacement[free]
    field = moved[free] - rest[free]
    # The solver's contract: ||b - A u|| <= 1e-10 ||b|| over the whole field (float64), plus the
    # two assemblies' rounding.
    residual = np.linalg.norm(rhs - system @ field) / np.linalg.norm(rhs)
    assert residual < 2e-10, residual
    # Hence ||u - u*|| / ||u*|| <= cond(A) 2e-10, with cond(A) <= (m + l^2 |K|_inf) / m
    # (K is positive semidefinite; Gershgorin above).
    exact = sparse_linalg.spsolve(system.tocsc(), rhs)
    bound = (mass + length**2 * abs(stiffness).sum(axis=1).max()) / mass * 2e-10
    assert np.linalg.norm(field - exact) / np.linalg.norm(exact) < bound


# ---------------------------------------------------------------------------------------------
# Mesh and meshio
# ---------------------------------------------------------------------------------------------

SHARED_FILES = sorted(path.name for path in MESH_DIR.glob("*") if path.suffix in (".off", ".obj", ".mesh")) if MESH_DIR.is_dir() else []


@requires_shared_meshes
@pytest.mark.parametrize("name", SHARED_FILES)
def test_read_mesh_matches_meshio_and_round_trips(name, tmp_path):
    meshio = pytest.importorskip("meshio")

    source = meshio.read(MESH_DIR / name)
    kind = "tetra" if any(block.type == "tetra" for block in source.cells) else "triangle"
    cells = np.concatenate([block.data for block in source.cells if block.type == kind])
    mesh = geomjax.read_mesh(MESH_DIR / name, dtype=np.float64)
    assert mesh.n_manifold_dims == (3 if kind == "tetra" else 2) and mesh.n_spatial_dims == 3
    np.testing.assert_array_equal(np.asarray(mesh.points), np.asarray(source.points, np.float64))
    np.testing.assert_array_equal(np.asarray(mesh.cells), cells)
    for key, blocks in source.cell_data.items():  # Medit's region labels of the chosen cells
        chosen = [data for block, data in zip(source.cells, blocks, strict=True) if block.type == kind]
        np.testing.assert_array_equal(np.asarray(mesh.cell_data[key]), np.concatenate(chosen))
    for key, values in source.point_data.items():
        np.testing.assert_array_equal(np.asarray(mesh.point_data[key]), values)
    # Binary VTU and legacy VTK keep float64 points, cells and data exactly.
    for suffix in (".vtu", ".vtk"):
        path = tmp_path / f"copy{suffix}"
        geomjax.write_mesh(path, mesh)
        again = geomjax.read_mesh(path, dtype=np.float64)
        np.testing.assert_array_equal(np.asarray(again.points), np.asarray(mesh.points))
        np.testing.assert_array_equal(np.asarray(again.cells), np.asarray(mesh.cells))
        assert set(again.point_data) == set(mesh.point_data) and set(again.cell_data) == set(mesh.cell_data)
        for key in mesh.cell_data:
            np.testing.assert_array_equal(np.asarray(again.cell_data[key]), np.asarray(mesh.cell_data[key]))


@requires_shared_meshes
@pytest.mark.parametrize("name", ["fertility.off", "camelhead.off", "octopus-low.mesh"])
def test_mesh_connectivity_against_numpy(name):
    # Edges and (for surfaces) hinges of a closed surface, an open one and a tetrahedral volume.
    points, cells = shared_volume(name) if name.endswith(".mesh") else shared_surface(name)
    mesh = geomjax.Mesh(jnp.asarray(points), cells)
    assert (mesh.n_points, mesh.n_cells, mesh.n_spatial_dims, mesh.n_manifold_dims) == (len(points), len(cells), 3, cells.shape[1] - 1)
    pairs = [(i, j) for i in range(cells.shape[1]) for j in range(i + 1, cells.shape[1])]
    all_edges = np.sort(np.concatenate([cells[:, [i, j]] for i, j in pairs]), axis=1)
    edges, counts = np.unique(all_edges, axis=0, return_counts=True)
    np.testing.assert_array_equal(np.asarray(mesh.edges), edges)
    if cells.shape[1] != 3:
        return
    # Every interior edge (two triangles) once, with the opposite corners of its two triangles
    # in cell order; boundary edges (one triangle) dropped.
    hinges = np.asarray(mesh.hinges)
    np.testing.assert_array_equal(hinges[:, :2], edges[counts == 2])
    keys = all_edges[:, 0].astype(np.int64) * len(points) + all_edges[:, 1]
    owners = np.tile(np.arange(len(cells)), len(pairs))
    order = np.lexsort((owners, keys))  # by edge, then by triangle: cell order within an edge
    interior = counts[np.searchsorted(np.unique(keys), keys[order])] == 2
    first, second = owners[order][interior].reshape(-1, 2).T
    for column, triangle in ((2, first), (3, second)):
        opposite = cells[triangle].sum(axis=1) - hinges[:, 0] - hinges[:, 1]
        np.testing.assert_array_equal(hinges[:, column], opposite)
