"""Triangle-set operations of the remesher: relabelled triangles, clean-up, relaxation and
measures (the edge flips are in ``_flips``).

Host NumPy, shared by both backends of :func:`geomjax.remeshing` (with warp-lang installed,
the relaxation's bending measure, sums and fold check come from Warp kernels with the same bits). Triangles are ``(F, 3)``
integer arrays of vertex indices, positions ``(V, 3)`` arrays; an edge is keyed
``min * stride + max`` with ``stride`` above every vertex index.
"""

from __future__ import annotations

import numpy as np

from .._dispatch import warp_available

__all__ = [
    "bending_density",
    "boundary_vertices",
    "corner_angles",
    "corner_angles_at",
    "first_occurrences",
    "collapse_poor_triangles",
    "column_max",
    "column_min",
    "degenerate_vertices",
    "relabelled_triangles",
    "drop_crowded_edges",
    "half_edges",
    "min_angles",
    "nondegenerate",
    "overturned_vertices",
    "relaxation_targets",
    "relocate_poor_corners",
    "remove_degree_three",
    "row_cross",
    "row_dot",
    "topology",
    "unit_rows",
]

# A triangle whose doubled area is below this many dtype epsilons of its squared edge lengths
# has zero area up to rounding (coincident or collinear projected vertices).
DEGENERATE_EPSILONS = 4.0
# A degree-three vertex is removed only when it lies this close to the plane of its three
# neighbours (relative to their longest edge): further out it is a tip of the surface.
DEGREE_THREE_MAX_HEIGHT = 0.1
# Triangles with a smaller angle (degrees) lose their shortest edge in the final clean-up.
MIN_ANGLE_DEGREES = 12.0
COLLAPSE_ROUNDS = 4
# The corners of the triangles still below MIN_ANGLE_DEGREES after the collapses try moving
# these fractions of the way to each neighbour, for this many rounds.
RELOCATION_STEPS = (0.1, 0.25, 0.5)
RELOCATION_ROUNDS = 4


def row_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``(...)`` dot products of the rows of two ``(..., 3)`` arrays.

    Column by column: NumPy's reductions along a length-3 axis (``np.sum(u * v, axis=1)``,
    ``np.linalg.norm(axis=1)``) and ``np.cross`` cost several times more on the remesher's
    vertex- and face-sized arrays (the same products and sums, so the same results).
    """
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def column_min(u: np.ndarray) -> np.ndarray:
    """``(D,)`` smallest entry of each column of ``(N, D)`` ``u`` (``u.min(axis=0)``, column by
    column: NumPy's reduction across the rows of a narrow array costs twenty times more)."""
    return np.array([u[:, k].min() for k in range(u.shape[1])], u.dtype)


def column_max(u: np.ndarray) -> np.ndarray:
    """``(D,)`` largest entry of each column of ``(N, D)`` ``u`` (see :func:`column_min`)."""
    return np.array([u[:, k].max() for k in range(u.shape[1])], u.dtype)


def row_norm(u: np.ndarray) -> np.ndarray:
    """``(...)`` Euclidean norms of the rows of a ``(..., 3)`` array (see :func:`row_dot`)."""
    return np.sqrt(row_dot(u, u))


def row_cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``(..., 3)`` cross products of the rows of two ``(..., 3)`` arrays (see :func:`row_dot`).

    Written into one output column by column: stacking the three columns costs four times
    more on face-sized arrays.
    """
    out = np.empty(np.broadcast_shapes(u.shape, v.shape), np.result_type(u, v))
    np.subtract(u[..., 1] * v[..., 2], u[..., 2] * v[..., 1], out=out[..., 0])
    np.subtract(u[..., 2] * v[..., 0], u[..., 0] * v[..., 2], out=out[..., 1])
    np.subtract(u[..., 0] * v[..., 1], u[..., 1] * v[..., 0], out=out[..., 2])
    return out


# Column orders of the corners shifted by 0, 1 and 2 places (see rotated_corners).
_ROTATIONS = (np.array([0, 1, 2]), np.array([1, 2, 0]), np.array([2, 0, 1]))


def rotated_corners(triangles: np.ndarray, shift: int) -> np.ndarray:
    """``(F, 3)``: each corner replaced by the one ``shift`` (1 or 2) places after it, i.e.
    ``np.roll(triangles, -shift, axis=1)`` as a gather of columns (a fifth of np.roll's cost on
    the remesher's triangle arrays)."""
    return triangles[:, _ROTATIONS[shift]]


def half_edges(triangles: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per half-edge (3 per triangle, in order): tail, head and the undirected edge key
    ``min * stride + max`` (``stride`` above every vertex index)."""
    tail = triangles.reshape(-1).astype(np.int64)
    head = rotated_corners(triangles, 1).reshape(-1).astype(np.int64)
    return tail, head, np.minimum(tail, head) * stride + np.maximum(tail, head)


def first_occurrences(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per distinct value of ``keys`` ``(N,)`` (ascending): the index of its first occurrence and
    its count, as ``np.unique(keys, return_index=True, return_counts=True)[1:]`` gives them
    (a stable sort and the runs of equal values, without np.unique's overhead: a fifth less on
    the remesher's edge keys)."""
    if keys.size == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    starts = np.flatnonzero(np.concatenate([[True], ordered[1:] != ordered[:-1]]))
    return order[starts], np.diff(np.append(starts, keys.size))


# Vertex indices below this: a triangle's three sorted corners make one int64 key (2**21 cubed
# is 2**63).
_KEYED_INDEX_LIMIT = 2**21 - 1


def triangle_keys(a: np.ndarray, b: np.ndarray, c: np.ndarray, top: int) -> np.ndarray | None:
    """``(F,)`` int64: one key per triangle of corners ``a``, ``b``, ``c`` ``(F,)`` (indices
    below ``top``), equal for the same three corners in any order; None if ``top`` is too
    large for the key to fit (above ``_KEYED_INDEX_LIMIT``)."""
    if top > _KEYED_INDEX_LIMIT:
        return None
    low = np.minimum(np.minimum(a, b), c).astype(np.int64)
    high = np.maximum(np.maximum(a, b), c).astype(np.int64)
    middle = a.astype(np.int64) + b + c - low - high
    return (low * top + middle) * top + high


def relabelled_triangles(labels: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The triangles ``corners`` (``(3, F)``: each face's first, second and third corner, e.g.
    ``faces.T`` made contiguous, so that each corner's labels are read and compared in
    sequence) relabelled by ``labels``: those with three distinct labels, each once (in any
    orientation, the first occurrence)."""
    a, b, c = np.take(labels, corners)
    keep = np.flatnonzero((a != b) & (b != c) & (a != c))
    triangles = np.stack([a[keep], b[keep], c[keep]], axis=1)
    if triangles.shape[0] == 0:
        return triangles
    # Duplicates in any orientation: keep the first occurrence (one key per triangle costs a
    # third of sorting rows).
    key = triangle_keys(a[keep], b[keep], c[keep], int(labels.max()) + 1)
    if key is not None:
        ordered = np.sort(key)
        if not np.any(ordered[1:] == ordered[:-1]):
            return triangles
        _, first = np.unique(key, return_index=True)  # the first occurrence of each key
        return triangles[np.sort(first)]
    ordered = np.sort(triangles, axis=1)
    order = np.lexsort(ordered.T[::-1])  # stable: the first occurrence leads
    ordered = ordered[order]
    first = np.ones(order.size, bool)
    first[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    return triangles[np.sort(order[first])]


def degenerate_vertices(triangles: np.ndarray, positions: np.ndarray, num_vertices: int) -> np.ndarray:
    """``(num_vertices,)`` bool: the corners of triangles of zero area (up to rounding)."""
    keep, _ = _area_check(triangles, positions)
    mask = np.zeros(num_vertices, bool)
    mask[triangles[~keep].reshape(-1)] = True
    return mask


def nondegenerate(triangles: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of non-zero area (up to rounding) and their doubled areas."""
    keep, area2 = _area_check(triangles, positions)
    return triangles[keep], area2[keep]


def _area_check(triangles: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle: non-zero area up to rounding (bool), and the doubled area."""
    a, b, c = (positions[triangles[:, k]] for k in range(3))
    ab, ac, bc = b - a, c - a, c - b
    area2 = row_norm(row_cross(ab, ac))
    edge2 = row_dot(ab, ab) + row_dot(ac, ac) + row_dot(bc, bc)
    return area2 > DEGENERATE_EPSILONS * np.finfo(positions.dtype).eps * edge2, area2


def drop_crowded_edges(triangles: np.ndarray, area2: np.ndarray) -> np.ndarray:
    """Remove triangles until every edge has at most two.

    Each round removes, for every edge with more than two triangles, the triangle touching the
    most such edges (then the smallest, then the lowest index).
    """
    index = np.arange(triangles.shape[0])
    while triangles.shape[0]:
        _, _, key = half_edges(triangles, int(triangles.max()) + 1)
        owner = np.repeat(np.arange(triangles.shape[0]), 3)
        _, edge, counts = np.unique(key, return_inverse=True, return_counts=True)
        crowded = counts[edge] > 2
        if not np.any(crowded):
            break
        touching = np.bincount(owner[crowded], minlength=triangles.shape[0])
        candidates = np.flatnonzero(crowded)
        # Per crowded edge, the first after sorting by (edge, -touching, area, index).
        faces = owner[candidates]
        ranked = candidates[np.lexsort((index[faces], area2[faces], -touching[faces], edge[candidates]))]
        head = np.ones(ranked.size, bool)
        head[1:] = edge[ranked[1:]] != edge[ranked[:-1]]
        keep = np.ones(triangles.shape[0], bool)
        keep[owner[ranked[head]]] = False
        triangles, area2, index = triangles[keep], area2[keep], index[keep]
    return triangles


def corner_angles(apex: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    u, v = a - apex, b - apex
    return np.arctan2(row_norm(row_cross(u, v)), row_dot(u, v))


def corner_angles_at(x: np.ndarray, apex: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """``(M,)`` :func:`corner_angles` at ``x[apex]`` between ``x[first]`` and ``x[second]``
    (``x`` ``(V, 3)`` float64, indices ``(M,)``). With warp-lang the sine and cosine terms come
    from a kernel (``warp_ffi.remesh.corner_terms``, the same bits), without the gathers."""
    if warp_available():
        from warp_ffi.remesh import corner_terms

        return np.arctan2(*corner_terms(x, apex, first, second))
    return corner_angles(x[apex], x[first], x[second])


def min_angles(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(F,)`` smallest angle of each triangle, in degrees."""
    x = positions.astype(np.float64)
    # The corners in order (a at a between b and c, b between c and a, c between a and b).
    angles = corner_angles_at(x, triangles.reshape(-1), rotated_corners(triangles, 1).reshape(-1), rotated_corners(triangles, 2).reshape(-1)).reshape(-1, 3)
    return np.degrees(np.minimum(np.minimum(angles[:, 0], angles[:, 1]), angles[:, 2]))


def unit_rows(v: np.ndarray) -> np.ndarray:
    norm = row_norm(v)[..., None]
    return v / np.where(norm > 0, norm, 1.0)


def boundary_vertices(triangles: np.ndarray, num_vertices: int) -> np.ndarray:
    """``(num_vertices,)`` bool: vertices on an edge of only one triangle."""
    tail, head, key = half_edges(triangles, num_vertices)
    _, edge, counts = np.unique(key, return_inverse=True, return_counts=True)
    boundary = counts[edge] == 1
    fixed = np.zeros(num_vertices, bool)
    fixed[tail[boundary]] = True
    fixed[head[boundary]] = True
    return fixed


def bending_density(positions: np.ndarray, triangles: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``(V,)`` relaxation density ``1 + (s / mean s)^2`` that gathers vertices where the surface
    bends away from the triangles.

    ``s`` is the largest sagitta estimate ``|(b - a) . (n_b - n_a)| / 8`` of a vertex's edges
    (the height of an arc through ``a`` and ``b`` with unit normals ``n_a``, ``n_b`` over its
    chord, exact to second order on a circle); ``normals`` ``(V, 3)`` are surface normals at the
    vertices, of any length. The mean is over the vertices of ``triangles``; a flat surface has
    density 1 everywhere. With warp-lang the largest sagittas come from a kernel
    (``warp_ffi.remesh.largest_sagittas``, the same bits).
    """
    x = positions.astype(np.float64)
    unit = unit_rows(normals.astype(np.float64))
    if warp_available():
        from warp_ffi.remesh import largest_sagittas

        largest, used = largest_sagittas(x, unit, triangles)
    else:
        tail, head = triangles.reshape(-1), rotated_corners(triangles, 1).reshape(-1)
        sagitta = np.abs(row_dot(x[head] - x[tail], unit[head] - unit[tail])) / 8
        largest = np.zeros(x.shape[0])
        np.maximum.at(largest, tail, sagitta)
        np.maximum.at(largest, head, sagitta)
        # The vertices the triangles use (a mask: no sort).
        used = np.bincount(triangles.reshape(-1), minlength=x.shape[0]) > 0
    mean = largest[used].mean()
    return 1 + (largest / mean) ** 2 if mean > 0 else np.ones(x.shape[0])


def relaxation_targets(positions: np.ndarray, triangles: np.ndarray, vertex_rho: np.ndarray | None, fixed: np.ndarray) -> np.ndarray:
    """One optimal-Delaunay-triangulation step: each vertex to the mass-weighted mean of the
    circumcentres of its triangles.

    A triangle's mass is its area (times its mean density). The circumcentre of an obtuse
    triangle, which can lie far outside it, is replaced by the midpoint of its longest edge (the
    closest point of the triangle to it). ``fixed`` vertices (on a boundary) and vertices in no
    triangle stay where they are. With warp-lang the sums come from a kernel
    (``warp_ffi.remesh.relaxation_sums``: the same roundings in the same order, the same bits).
    """
    x = positions.astype(np.float64)
    if warp_available():
        from warp_ffi.remesh import relaxation_sums

        total, sums = relaxation_sums(x, triangles, vertex_rho)
    else:
        total, sums = _relaxation_sums(x, triangles, vertex_rho)
    move = (total > 0) & ~fixed
    out = x.copy()
    out[move] = sums[move] / total[move, None]
    return out


def _relaxation_sums(x: np.ndarray, triangles: np.ndarray, vertex_rho: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, the masses of its triangles ``(V,)`` and their mass-weighted circumcentres
    ``(V, 3)``, summed (the NumPy twin of ``warp_ffi.remesh.relaxation_sums``)."""
    a, b, c = (x[triangles[:, k]] for k in range(3))
    ab, ac = b - a, c - a
    normal = row_cross(ab, ac)
    normal2 = row_dot(normal, normal)
    ab2, ac2, bc2 = row_dot(ab, ab), row_dot(ac, ac), row_dot(c - b, c - b)
    safe = np.where(normal2 > 0, normal2, 1.0)
    centre = a + (row_cross(normal, ab) * ac2[:, None] + row_cross(ac, normal) * ab2[:, None]) / (2 * safe[:, None])
    # Obtuse at a (bc^2 > ab^2 + ac^2) puts the circumcentre beyond edge bc, and so on.
    excess = np.stack([bc2 - ab2 - ac2, ac2 - ab2 - bc2, ab2 - ac2 - bc2], axis=1)
    longest = np.argmax(excess, axis=1)
    obtuse = excess[np.arange(a.shape[0]), longest] >= 0
    midpoints = np.stack([(b + c) / 2, (a + c) / 2, (a + b) / 2], axis=1)[np.arange(a.shape[0]), longest]
    centre = np.where(obtuse[:, None], midpoints, centre)
    mass = 0.5 * np.sqrt(normal2)
    if vertex_rho is not None:
        corner_rho = vertex_rho.astype(np.float64, copy=False)[triangles]
        mass = mass * ((corner_rho[:, 0] + corner_rho[:, 1] + corner_rho[:, 2]) / 3)
    num = x.shape[0]
    corners = triangles.reshape(-1)
    total = np.bincount(corners, weights=np.repeat(mass, 3), minlength=num)
    sums = np.stack([np.bincount(corners, weights=np.repeat(mass * centre[:, k], 3), minlength=num) for k in range(3)], axis=1)
    return total, sums


def overturned_vertices(old: np.ndarray, new: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(V,)`` bool: vertices of triangles whose normal turns by 90 degrees or more (with
    warp-lang from a kernel, ``warp_ffi.remesh.overturned_vertices``: the same answer)."""
    if warp_available():
        from warp_ffi.remesh import overturned_vertices as kernel

        return kernel(old, new, triangles)

    def normals(x):
        return row_cross(x[triangles[:, 1]] - x[triangles[:, 0]], x[triangles[:, 2]] - x[triangles[:, 0]])

    turned = row_dot(normals(old.astype(np.float64)), normals(new.astype(np.float64))) <= 0
    mask = np.zeros(old.shape[0], bool)
    mask[triangles[turned].reshape(-1)] = True
    return mask


def remove_degree_three(positions: np.ndarray, triangles: np.ndarray, num_vertices: int) -> np.ndarray:
    """Replace the three triangles around each interior vertex of degree three by one.

    Such a vertex sits inside the triangle of its neighbours and makes three poor triangles
    (their angles at it sum to 360 degrees); flips cannot remove it. Its star becomes the
    triangle of its neighbours, oriented like the star (the Euler characteristic is kept), unless
    that triangle exists already (a tetrahedron). Vertices are removed in independent sets (no
    two sharing a triangle), until none is left.
    """
    while True:
        corners = triangles.reshape(-1)
        incident = np.bincount(corners, minlength=num_vertices)
        tail, head, key = half_edges(triangles, num_vertices)
        first, counts = first_occurrences(key)
        degree = np.bincount(np.concatenate([tail[first], head[first]]), minlength=num_vertices)
        # The boundary vertices (see boundary_vertices): the ends of the edges of one triangle.
        single = first[counts == 1]
        fixed = np.zeros(num_vertices, bool)
        fixed[tail[single]] = True
        fixed[head[single]] = True
        candidate = (incident == 3) & (degree == 3) & ~fixed
        # The triangles around each candidate; a triangle with two candidates is left alone.
        owner = np.repeat(np.arange(triangles.shape[0]), 3)
        hit = candidate[corners]
        shared = np.bincount(owner[hit], minlength=triangles.shape[0]) > 1
        blocked = np.zeros(num_vertices, bool)
        blocked[corners[hit & shared[owner]]] = True
        centre = np.flatnonzero(candidate & ~blocked)
        if centre.size == 0:
            return triangles
        slots = np.flatnonzero(hit & ~shared[owner])
        order = np.argsort(corners[slots], kind="stable")
        star_faces = owner[slots[order]].reshape(-1, 3)  # (n, 3): the triangles of each centre
        star_slots = (slots[order] % 3).reshape(-1, 3)
        # The first triangle rotated to (centre, a, b); the third neighbour d is the one of the
        # second triangle that is neither the centre nor a nor b.
        face = triangles[star_faces[:, 0]]
        k = star_slots[:, 0]
        rows = np.arange(face.shape[0])
        a, b = face[rows, (k + 1) % 3], face[rows, (k + 2) % 3]
        other = triangles[star_faces[:, 1]]
        d = np.max(np.where((other == centre[:, None]) | (other == a[:, None]) | (other == b[:, None]), -1, other), axis=1)
        link = np.stack([a, b, d], axis=1)
        link_keys = triangle_keys(a, b, d, num_vertices)
        keys = triangle_keys(triangles[:, 0], triangles[:, 1], triangles[:, 2], num_vertices)
        if link_keys is not None and keys is not None:
            keys.sort()
            new = keys[np.minimum(np.searchsorted(keys, link_keys), keys.size - 1)] != link_keys
        else:
            existing = {tuple(t) for t in np.sort(triangles, axis=1).tolist()}
            new = np.array([tuple(t) not in existing for t in np.sort(link, axis=1).tolist()], bool)
        # A vertex standing out of its link's plane is a tip of the surface: it stays.
        x = positions.astype(np.float64)
        la, lb, ld = x[a], x[b], x[d]
        height = np.abs(row_dot(x[centre] - la, unit_rows(row_cross(lb - la, ld - la))))
        longest = np.sqrt(np.max(np.stack([np.sum((lb - la) ** 2, 1), np.sum((ld - lb) ** 2, 1), np.sum((la - ld) ** 2, 1)]), axis=0))
        new &= height <= DEGREE_THREE_MAX_HEIGHT * longest
        if not np.any(new):
            return triangles
        keep = np.ones(triangles.shape[0], bool)
        keep[star_faces[new].reshape(-1)] = False
        triangles = np.concatenate([triangles[keep], link[new].astype(triangles.dtype)])


def collapse_poor_triangles(positions: np.ndarray, triangles: np.ndarray, fixed: np.ndarray, strength: np.ndarray) -> np.ndarray:
    """Collapse the shortest edge of each triangle whose smallest angle is below ``MIN_ANGLE_DEGREES``.

    The few needles and caps that flips and moves leave (a vertex pinned on a crease or a tip,
    or next to the boundary) go by an edge collapse: the endpoint with the weaker feature
    (``strength``, the crease or corner weight of its cluster) joins the other, which stays
    where it is, so features keep their vertices. A collapse is made only when it keeps the
    topology (the link condition: the edge's endpoints share exactly its opposite vertices),
    turns no triangle over and leaves every new triangle better than the one it removes;
    ``fixed`` (boundary) vertices never move.
    """
    x = positions.astype(np.float64)
    triangles = triangles.copy()
    alive = np.ones(triangles.shape[0], bool)
    for _ in range(COLLAPSE_ROUNDS):
        live = np.flatnonzero(alive)
        angles = min_angles(positions, triangles[live])
        poor = live[np.argsort(angles)][np.sort(angles) < MIN_ANGLE_DEGREES]
        if poor.size == 0:
            break
        # The triangles around the poor triangles' corners: all that the collapses below read.
        star = {vertex: set(live[faces].tolist()) for vertex, faces in _faces_of(triangles[live], np.unique(triangles[poor])).items()}
        touched: set[int] = set()
        for face in poor:
            if not alive[face] or int(face) in touched:
                continue
            collapse = _first_collapse(x, triangles, star, triangles[face], fixed, strength, touched)
            if collapse is not None:
                moved, new, shared = collapse
                triangles[moved] = new
                alive[shared] = False
                touched.update(moved, shared)
    return triangles[alive]


def _first_collapse(x, triangles, star, corners, fixed, strength, touched):
    """The first admissible collapse of an edge of the triangle ``corners``: ``(moved faces,
    their new corners, removed faces)``, or None.

    Edges are tried from the shortest; on each, the endpoint with the weaker feature goes
    first, the other second; a ``fixed`` endpoint never goes.
    """
    poor_angle = min_angles(x, corners[None])[0]
    lengths = [np.sum((x[corners[(k + 1) % 3]] - x[corners[k]]) ** 2) for k in range(3)]
    for k in np.argsort(lengths, kind="stable"):
        a, b = int(corners[k]), int(corners[(k + 1) % 3])
        for gone, keep in sorted([(a, b), (b, a)], key=lambda pair: strength[pair[0]]):
            if fixed[gone] or touched & (star[gone] | star[keep]):
                continue
            shared = star[gone] & star[keep]
            # The link condition: the endpoints' common neighbours are the edge's opposite corners.
            common = (_neighbours(triangles, star[gone]) - {gone}) & (_neighbours(triangles, star[keep]) - {keep})
            if common != _neighbours(triangles, shared) - {a, b}:
                continue
            moved = sorted(star[gone] - shared)
            if not moved:  # all of its triangles are on the edge: not a surface around it
                continue
            old = triangles[moved]
            new = np.where(old == gone, keep, old)
            old_normal = row_cross(x[old[:, 1]] - x[old[:, 0]], x[old[:, 2]] - x[old[:, 0]])
            new_normal = row_cross(x[new[:, 1]] - x[new[:, 0]], x[new[:, 2]] - x[new[:, 0]])
            if np.all(row_dot(old_normal, new_normal) > 0) and np.min(min_angles(x, new)) > poor_angle:
                return moved, new, sorted(shared)
    return None


def relocate_poor_corners(surface_points: tuple[np.ndarray, ...], triangles: np.ndarray, fixed: np.ndarray, place) -> tuple[np.ndarray, ...]:
    """Move the corners of the triangles whose smallest angle is below ``MIN_ANGLE_DEGREES`` to
    where their triangles are better.

    What the collapses leave is a needle that no collapse can improve, such as one across a thin
    strip of the surface (the end of a tapered blade) whose two long edges start at the same
    vertex: the fix is to move the short edge's ends apart along the strip. Each corner tries the
    points ``RELOCATION_STEPS`` of the way to each of its neighbours, put back on the surface by
    ``place(vertices (M,), starts (M, 3), moves (M, 3)) -> (points, source faces, weights)``;
    it takes the one that makes the smallest angle of its triangles largest, if that is better
    than where it is and turns no triangle over. The moving corners of a round share no
    triangle (a move changes only its own triangles, so each is judged exactly); ``fixed``
    (boundary) corners stay.

    ``surface_points`` is ``(positions (V, 3), source faces (V,), weights (V, 3))``; returns them
    updated.
    """
    positions, *rest = surface_points
    for _ in range(RELOCATION_ROUNDS):
        angles = min_angles(positions, triangles)
        poor = np.flatnonzero(angles < MIN_ANGLE_DEGREES)
        poor = poor[np.argsort(angles[poor])]
        corners = np.setdiff1d(triangles[poor], np.flatnonzero(fixed))
        if corners.size == 0:
            break
        corner_faces = _faces_of(triangles, corners)
        # Every (corner, neighbour, step) candidate.
        owners, start, move = [], [], []
        for corner in corners.tolist():
            neighbours = np.setdiff1d(triangles[corner_faces[corner]], [corner])
            for step in RELOCATION_STEPS:
                owners += [corner] * neighbours.size
                start.append(np.broadcast_to(positions[corner], (neighbours.size, 3)))
                move.append(step * (positions[neighbours] - positions[corner]))
        vertex = np.asarray(owners)
        placed = place(vertex, np.concatenate(start), np.concatenate(move))
        # Each corner's best candidate, if it beats the corner's current position.
        best: dict[int, tuple[float, int]] = {}
        for corner in corners.tolist():
            star = triangles[corner_faces[corner]]
            rows = np.flatnonzero(vertex == corner)
            score = _star_min_angle(positions, star, corner, placed[0][rows])
            if score.max() > angles[corner_faces[corner]].min():
                best[corner] = (float(score.max()), int(rows[np.argmax(score)]))
        # Worst triangle first, its corner with the best move; no two movers in one triangle.
        blocked: set[int] = set()
        chosen = []
        for face in poor.tolist():
            options = [corner for corner in triangles[face].tolist() if corner in best and corner not in blocked]
            if options:
                corner = max(options, key=lambda c: best[c][0])
                chosen.append(corner)
                blocked.update(triangles[corner_faces[corner]].reshape(-1).tolist())
        if not chosen:
            break
        rows = np.array([best[corner][1] for corner in chosen], int)
        surface_points = tuple(np.array(array) for array in (positions, *rest))
        for array, new in zip(surface_points, placed):
            array[chosen] = new[rows]
        positions, *rest = surface_points
    return (positions, *rest)


def _faces_of(triangles: np.ndarray, vertices: np.ndarray) -> dict[int, np.ndarray]:
    """Each of ``vertices``: the indices of its triangles."""
    face, slot = np.nonzero(np.isin(triangles, vertices))
    corner = triangles[face, slot]
    order = np.argsort(corner, kind="stable")
    keys, starts = np.unique(corner[order], return_index=True)
    return {int(key): part for key, part in zip(keys, np.split(face[order], starts[1:]))}


def _star_min_angle(positions: np.ndarray, star: np.ndarray, corner: int, candidates: np.ndarray) -> np.ndarray:
    """``(C,)``: the smallest angle (degrees) of the triangles ``star`` with ``corner`` at each
    candidate position, or -1 where one of them turns over."""
    x = positions.astype(np.float64)
    old = x[star]  # (S, 3, 3)
    new = np.broadcast_to(old, (candidates.shape[0], *old.shape)).copy()
    at = star == corner
    new[:, at] = candidates.astype(np.float64)[:, None]
    old_normal = row_cross(old[:, 1] - old[:, 0], old[:, 2] - old[:, 0])
    new_normal = row_cross(new[..., 1, :] - new[..., 0, :], new[..., 2, :] - new[..., 0, :])
    flat = new.reshape(-1, 3, 3)
    angles = np.degrees(np.minimum.reduce([corner_angles(flat[:, k], flat[:, (k + 1) % 3], flat[:, (k + 2) % 3]) for k in range(3)])).reshape(new.shape[:2])
    turned = np.any(np.einsum("csd,sd->cs", new_normal, old_normal) <= 0, axis=1)
    return np.where(turned, -1.0, angles.min(axis=1))


def _neighbours(triangles: np.ndarray, faces: set[int]) -> set[int]:
    """The vertices of ``faces``."""
    return {int(vertex) for face in faces for vertex in triangles[face]}


def topology(triangles: np.ndarray) -> tuple[int, int]:
    """``(Euler characteristic, number of boundary edges)`` of the vertices used by ``triangles``."""
    _, _, key = half_edges(triangles, int(triangles.max()) + 1)
    _, counts = np.unique(key, return_counts=True)
    return np.unique(triangles).size - counts.size + triangles.shape[0], int(np.sum(counts == 1))
