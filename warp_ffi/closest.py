"""Closest faces of query points on a triangle mesh, signed (pseudo-normal or winding number).

Inputs arrive validated and normalised (no checks here): query arrays ``(N, 3)`` with ``N > 0``,
the mesh in the working dtype (``(V, 3)`` vertices, ``(F, 3)`` int32 faces) and small parameter
arrays; the search structure is a prepared oriented-box tree (``warp_ffi.host.closest_tree``) or
float32 vertices and flat indices to build it (or Warp's mesh, for winding signs) inside the
call, which then traces under ``jit`` construction included. Nothing here is differentiated:
the search returns a face id and a sign, and geomjax replays the chosen face's geometry in JAX.

* Closest face: a float32 search of the oriented-box tree (``_nearest_kernel``; each query starts
  from the previous Morton-ordered query's face on CPU), or Warp's ``mesh_query_point_sign_winding_number``
  (accuracy 2.0 and threshold 0.5, its defaults) for winding signs, with the radius padded (see
  ``_search``); the caller re-gates exactly.
* Refinement (``exact=True``): the first search runs in float32 and breaks ties arbitrarily. The
  refinement kernel measures the first answer in the working dtype, enumerates every face within
  that distance (plus the pad) in the tree (conservative box bounds, float32 narrow phase),
  measures each again in the working dtype and keeps the nearest, ties to the lowest index.
  Float64 queries thus get the exact float64 nearest face for the cost of one extra local
  traversal.
* Normal signs: the angle-weighted pseudo-normal of the closest feature (``_normal_sign_kernel``),
  from the faces of the tree within a small radius of the closest point.

On CPU every launch is split over the cores (``launch_in_chunks``), and queries are visited in
Morton order (a Warp radix sort of their keys), which keeps tree nodes in cache (1.5-3x).
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax.numpy as jnp

from ._grid import FLOAT32_MAX, mesh_id, mesh_in_call, query_order
from ._obb_tree import Tree, build_tree, next_face_within, node_distance_sq, tree_struct
from ._search import face_corners, max_abs, mesh_inputs, padded_radius, search_params, unit_scaled
from ._wrap import CallableFamily, Overloads, launch_in_chunks, scalars, vectors
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["point_faces", "SIGN_MODES"]

SLIVER_RATIO = wp.constant(1.0e-6)  # Warp's own sliver test: |AB x AC| / sum |edge|^2 below this
SIGN_MODES = {"none": 0, "normal": 1, "winding": 2}
WINDING_ACCURACY = wp.constant(2.0)
WINDING_THRESHOLD = wp.constant(0.5)
# Morton-consecutive queries per thread of the nearest search on CPU (on CUDA one per thread:
# queries are not sorted there, and a GPU needs the threads).
CPU_SEARCH_BATCH = 32


@wp.func
@no_type_check
def closest_point_on_triangle(p: Any, a: Any, b: Any, c: Any):
    """Closest point to ``p`` on triangle ``abc``: the rule of geomjax's JAX projection.

    Interior when the three projected barycentric numerators (Lagrange identity, each around its
    own vertex) are non-negative, otherwise the best clamped edge projection (AB, AC, BC).
    """
    zero = type(p[0])(0.0)
    ab = b - a
    ac = c - a
    bc = c - b
    ap = p - a
    bp = p - b
    ab2 = wp.dot(ab, ab)
    ac2 = wp.dot(ac, ac)
    bc2 = wp.dot(bc, bc)
    ab_ac = wp.dot(ab, ac)
    weight_c = ab2 * wp.dot(ac, ap) - ab_ac * wp.dot(ab, ap)
    weight_b = ac2 * wp.dot(ab, ap) - ab_ac * wp.dot(ac, ap)
    weight_a = wp.dot(ab, bc) * wp.dot(bc, bp) - bc2 * wp.dot(ab, bp)
    total = weight_a + weight_b + weight_c
    if weight_a >= zero and weight_b >= zero and weight_c >= zero and total > zero:
        return a + (weight_b / total) * ab + (weight_c / total) * ac
    best = a
    best_d2 = type(p[0])(FLOAT32_MAX) * type(p[0])(FLOAT32_MAX)
    for k in range(3):
        start = a
        direction = ab
        length2 = ab2
        if k == 1:
            direction = ac
            length2 = ac2
        elif k == 2:
            start = b
            direction = bc
            length2 = bc2
        s = zero
        if length2 > zero:
            s = wp.clamp(wp.dot(p - start, direction) / length2, zero, type(p[0])(1.0))
        q = start + s * direction
        d2 = wp.dot(p - q, p - q)
        if d2 < best_d2:
            best_d2 = d2
            best = q
    return best


@wp.func
@no_type_check
def triangle_distance_sq(p: Any, a: Any, b: Any, c: Any):
    """Squared distance from ``p`` to triangle ``abc``."""
    offset = p - closest_point_on_triangle(p, a, b, c)
    return wp.dot(offset, offset)


@wp.func
@no_type_check
def is_sliver(a: Any, b: Any, c: Any):
    """Warp's sliver rule (its closest-point queries skip these faces)."""
    ab = b - a
    ac = c - a
    bc = c - b
    total = wp.dot(ab, ab) + wp.dot(ac, ac) + wp.dot(bc, bc)
    return not (wp.length(wp.cross(ab, ac)) >= type(total)(SLIVER_RATIO) * total and total > type(total)(0.0))


@wp.func
@no_type_check
def _start_query(order: wp.array(dtype=wp.int32), points: wp.array(dtype=wp.vec3), params: wp.array(dtype=wp.float32),
                 faces_out: wp.array(dtype=wp.int32), sign_out: wp.array(dtype=wp.float32), t: int):  # fmt: skip
    """Query ``order[t]``: its index, float32 position and padded search radius, and whether it is
    finite; its outputs start as no face and a positive sign."""
    i = order[t]
    p = points[i]
    faces_out[i] = -1
    sign_out[i] = 1.0
    return i, p, padded_radius(params[0], params[1] + max_abs(p)), wp.isfinite(p)


@wp.kernel
@no_type_check
def _winding_search_kernel(
    mesh_words: wp.array(dtype=wp.uint32), points: wp.array(dtype=wp.vec3), params: wp.array(dtype=wp.float32),
    order: wp.array(dtype=wp.int32), offset: wp.int32, faces_out: wp.array(dtype=wp.int32), sign_out: wp.array(dtype=wp.float32),
):  # fmt: skip
    """Closest face and winding-number sign from Warp's query (skips slivers, float32)."""
    _, t = wp.tid()
    i, p, radius, finite = _start_query(order, points, params, faces_out, sign_out, t + offset)
    if not finite:
        return
    query = wp.mesh_query_point_sign_winding_number(mesh_id(mesh_words), p, radius, WINDING_ACCURACY, WINDING_THRESHOLD)
    if query.result:
        faces_out[i] = query.face
        sign_out[i] = query.sign


@wp.func
@no_type_check
def _sorted_distance_sq(tree: Tree, s: int, p: wp.vec3):
    """Squared float32 distance from ``p`` to the tree's sorted face ``s``."""
    return triangle_distance_sq(p, tree.corners[3 * s], tree.corners[3 * s + 1], tree.corners[3 * s + 2])


# The nearest search's stack: one deferred sibling per level (trees are at most 31 levels deep).
_NodeStack = wp.types.vector(length=32, dtype=wp.int32)
_BoundStack = wp.types.vector(length=32, dtype=wp.float32)


@wp.kernel
@no_type_check
def _nearest_kernel(
    tree: Tree, points: wp.array(dtype=wp.vec3), params: wp.array(dtype=wp.float32), skip_slivers: wp.int32, batch_size: wp.int32,
    order: wp.array(dtype=wp.int32), offset: wp.int32, faces_out: wp.array(dtype=wp.int32), sign_out: wp.array(dtype=wp.float32),
):  # fmt: skip
    """Closest face in float32 over the oriented-box tree, for ``batch_size`` queries in a row.

    Queries come in Morton order, so the previous query's face is usually at or next to this
    one's: its distance starts the search as the bound. Equal float32 distances go to the lowest
    face id (boxes within the bound are opened, ties included), so a query's answer does not
    depend on which queries it was searched with. The nearer child is entered first and
    the other deferred with its box distance, skipped when popped if the bound has shrunk past it.
    """
    _, batch = wp.tid()
    first = (batch + offset) * batch_size
    previous = int(-1)
    for t in range(first, wp.min(first + batch_size, points.shape[0])):
        i, p, radius, finite = _start_query(order, points, params, faces_out, sign_out, t)
        if not finite:
            continue
        bound = radius * radius
        best = int(-1)
        if previous >= 0:
            d2 = _sorted_distance_sq(tree, previous, p)
            if d2 <= bound:
                bound = d2
                best = previous
        deferred = _NodeStack()
        deferred_d2 = _BoundStack()
        depth = int(0)
        node = int(1)
        node_d2 = node_distance_sq(tree, 1, p)
        while True:
            if node_d2 <= bound:
                if node < tree.first_leaf:
                    near = 2 * node
                    far = near + 1
                    near_d2 = node_distance_sq(tree, near, p)
                    far_d2 = node_distance_sq(tree, far, p)
                    if far_d2 < near_d2:
                        near, far = far, near
                        near_d2, far_d2 = far_d2, near_d2
                    if far_d2 <= bound:
                        deferred[depth] = far
                        deferred_d2[depth] = far_d2
                        depth += 1
                    node = near
                    node_d2 = near_d2
                    continue
                j = node - tree.first_leaf
                for s in range(tree.leaf_starts[j], tree.leaf_starts[j + 1]):
                    a = tree.corners[3 * s]
                    b = tree.corners[3 * s + 1]
                    c = tree.corners[3 * s + 2]
                    if skip_slivers != 0 and is_sliver(a, b, c):
                        continue
                    d2 = triangle_distance_sq(p, a, b, c)
                    # Ties go to the lowest face id, so the answer does not depend on the warm start.
                    if d2 < bound or (d2 == bound and (best < 0 or tree.faces[s] < tree.faces[best])):
                        bound = d2
                        best = s
            if depth == 0:
                break
            depth -= 1
            node = deferred[depth]
            node_d2 = deferred_d2[depth]
        if best >= 0:
            faces_out[i] = tree.faces[best]
            previous = best


@wp.func
@no_type_check
def _query_face(
    order: wp.array(dtype=wp.int32), chosen: wp.array(dtype=wp.int32), points: wp.array(dtype=Any), faces: wp.array(dtype=wp.vec3i),
    vertices: wp.array(dtype=Any), t: int,
):  # fmt: skip
    """Query ``order[t]``: its index, the face chosen for it (``-1``: none), its position and that face's corners."""
    i = order[t]
    face = chosen[i]
    p = points[i]
    a = p
    b = p
    c = p
    if face >= 0:
        a, b, c = face_corners(faces, vertices, face)
    return i, face, p, a, b, c


@wp.kernel
@no_type_check
def _refine_kernel(
    tree: Tree, points32: wp.array(dtype=wp.vec3), points: wp.array(dtype=Any), vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.vec3i), params: wp.array(dtype=Any), skip_slivers: wp.int32, order: wp.array(dtype=wp.int32),
    offset: wp.int32, faces_io: wp.array(dtype=wp.int32),
):  # fmt: skip
    _, t = wp.tid()
    max_distance = params[0]
    i, best, p, a, b, c = _query_face(order, faces_io, points, faces, vertices, t + offset)
    if best < 0:
        return
    best_d2 = triangle_distance_sq(p, a, b, c)
    radius32 = padded_radius(wp.min(wp.sqrt(best_d2), max_distance), params[1] + max_abs(p))
    p32 = points32[i]
    leaf, s = next_face_within(tree, p32, radius32 * radius32, 0, 0)
    while leaf != 0:
        face = tree.faces[s]
        a, b, c = face_corners(faces, vertices, face)
        if skip_slivers == 0 or not is_sliver(a, b, c):
            d2 = triangle_distance_sq(p, a, b, c)
            if d2 < best_d2 or (d2 == best_d2 and face < best):
                best_d2 = d2
                best = face
        leaf, s = next_face_within(tree, p32, radius32 * radius32, leaf, s)
    if wp.sqrt(best_d2) > max_distance:
        best = -1
    faces_io[i] = best


@wp.func
@no_type_check
def _feature_weight(q: Any, a: Any, b: Any, c: Any, eps: Any):
    """Warp's weights: the angle at a vertex ``q`` sits on (within ``eps``), pi on an edge, else 2 pi."""
    e0 = b - a
    e1 = c - a
    e2 = c - b
    eps2 = eps * eps
    if wp.dot(q - a, q - a) < eps2:
        return wp.acos(wp.clamp(wp.dot(unit_scaled(e0), unit_scaled(e1)), type(eps)(-1.0), type(eps)(1.0)))
    if wp.dot(q - b, q - b) < eps2:
        return wp.acos(wp.clamp(wp.dot(unit_scaled(e2), unit_scaled(-e0)), type(eps)(-1.0), type(eps)(1.0)))
    if wp.dot(q - c, q - c) < eps2:
        return wp.acos(wp.clamp(wp.dot(unit_scaled(-e1), unit_scaled(-e2)), type(eps)(-1.0), type(eps)(1.0)))
    for k in range(3):
        start = a
        edge = e0
        if k == 1:
            edge = e1
        elif k == 2:
            start = b
            edge = e2
        offset = q - start
        along = wp.dot(offset, edge)
        edge2 = wp.dot(edge, edge)
        if wp.dot(offset, offset) * edge2 - along * along < eps2 * edge2:
            return type(eps)(3.141592653589793)
    return type(eps)(6.283185307179586)


@wp.kernel
@no_type_check
def _normal_sign_kernel(
    tree: Tree, points: wp.array(dtype=Any), vertices: wp.array(dtype=Any), faces: wp.array(dtype=wp.vec3i),
    params: wp.array(dtype=Any), faces_in: wp.array(dtype=wp.int32), order: wp.array(dtype=wp.int32), offset: wp.int32,
    sign_out: wp.array(dtype=wp.float32),
):  # fmt: skip
    """Sign from the angle-weighted pseudo-normal of the closest feature.

    Every non-sliver face whose closest point to ``p`` lies within ``eps`` of the nearest face's
    closest point ``q`` (the faces sharing the closest vertex or edge) adds its unit normal with
    Warp's feature weight; the sign is that of ``(p - q) . sum``. Unlike Warp's own query, which
    also adds faces that are merely about as far away elsewhere on the mesh, this cannot be
    fooled at points equidistant from distant parts of the mesh (a sphere's centre, the middle
    of a thin slab).
    """
    _, t = wp.tid()
    i, face, p, a, b, c = _query_face(order, faces_in, points, faces, vertices, t + offset)
    if face < 0:
        return
    q = closest_point_on_triangle(p, a, b, c)
    eps = params[2]
    q32 = wp.vec3(float(q[0]), float(q[1]), float(q[2]))
    radius32 = padded_radius(eps, params[1] + max_abs(q))
    pseudo_normal = p - p
    leaf, s = next_face_within(tree, q32, radius32 * radius32, 0, 0)
    while leaf != 0:
        a, b, c = face_corners(faces, vertices, tree.faces[s])
        if not is_sliver(a, b, c):
            q_other = closest_point_on_triangle(p, a, b, c)
            if wp.dot(q_other - q, q_other - q) <= eps * eps:
                pseudo_normal += _feature_weight(q_other, a, b, c, eps) * unit_scaled(wp.cross(b - a, c - a))
        leaf, s = next_face_within(tree, q32, radius32 * radius32, leaf, s)
    if wp.dot(pseudo_normal, p - q) > type(eps)(0.0):
        sign_out[i] = 1.0
    else:
        sign_out[i] = -1.0


@wp.kernel
@no_type_check
def _measure_kernel(
    points: wp.array(dtype=Any), vertices: wp.array(dtype=Any), faces: wp.array(dtype=wp.vec3i), faces_in: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32), offset: wp.int32, distance_out: wp.array(dtype=Any), closest_out: wp.array(dtype=Any),
):  # fmt: skip
    """Closest point on the chosen face and its distance, in the working dtype."""
    _, t = wp.tid()
    i, face, p, a, b, c = _query_face(order, faces_in, points, faces, vertices, t + offset)
    if face < 0:
        distance_out[i] = p[0] - p[0]
        closest_out[i] = p - p
        return
    q = closest_point_on_triangle(p, a, b, c)
    offset_vector = p - q
    size = max_abs(offset_vector)
    distance = size
    if size > type(size)(0.0):
        distance = size * wp.length(offset_vector / size)
    distance_out[i] = distance
    closest_out[i] = q


# ---------------------------------------------------------------------------------------------
# The FFI callable: the search pipeline for one dtype, sign mode and set of options.

_refine = Overloads(_refine_kernel, lambda s: {"points": vectors(s), "vertices": vectors(s), "params": scalars(s)})
_normal_sign = Overloads(_normal_sign_kernel, lambda s: {"points": vectors(s), "vertices": vectors(s), "params": scalars(s)})
_measure = Overloads(_measure_kernel, lambda s: {"points": vectors(s), "vertices": vectors(s), "distance_out": scalars(s), "closest_out": vectors(s)})


def _point_types(scalar, sign_mode: int, exact: bool, measure: bool, build: bool) -> dict:
    vec3f: wp.array = wp.array(dtype=wp.vec3)
    ints: wp.array = wp.array(dtype=wp.int32)
    if build:
        head = {"vertices32": vec3f, "faces_flat": ints}
    else:
        head = {"nodes": wp.array(dtype=wp.mat44), "leaf_starts": ints, "sorted_faces": ints, "corners": vec3f}
    inputs = {"points32": vec3f, "points": vectors(scalar), "vertices": vectors(scalar), "faces": wp.array(dtype=wp.vec3i),
              "params32": scalars(wp.float32), "params": scalars(scalar)}  # fmt: skip
    outputs = {"faces_out": ints, "sign_out": scalars(wp.float32), "keys_scratch": ints, "order_scratch": ints}
    if measure:
        outputs.update(distance_out=scalars(scalar), closest_out=vectors(scalar))
    return {**head, **inputs, **outputs}


def _point_outputs(sign_mode: int, exact: bool, measure: bool, build: bool) -> tuple:
    measured = ("distance_out", "closest_out") if measure else ()
    return ("faces_out", "sign_out", "keys_scratch", "order_scratch", *measured)


def _point_search(dtype, sign_mode: int, exact: bool, measure: bool, build: bool):
    """The body of the search: ``(search structure..., points32, ..., outputs...)``."""
    winding = sign_mode == SIGN_MODES["winding"]
    if winding and not build:
        raise ValueError("winding-number signs need the BVH built in the call")
    skip_slivers = int(sign_mode != SIGN_MODES["none"])

    def run(tree, mesh_words, points32, points, vertices, faces, params32, params, faces_out, sign_out, keys, order, *measured):
        num = points32.shape[0]
        query_order(points32, keys, order)
        if winding:
            launch_in_chunks(_winding_search_kernel, 1, num, [mesh_words, points32, params32, order], [faces_out, sign_out])
        else:
            batch = CPU_SEARCH_BATCH if points32.device.is_cpu else 1
            inputs = [tree, points32, params32, skip_slivers, batch, order]
            launch_in_chunks(_nearest_kernel, 1, -(-num // batch), inputs, [faces_out, sign_out], min_chunk=8)
        if exact:
            inputs = [tree, points32, points, vertices, faces, params, skip_slivers, order]
            launch_in_chunks(_refine(dtype), 1, num, inputs, [faces_out], min_chunk=256)
        if sign_mode == SIGN_MODES["normal"]:
            inputs = [tree, points, vertices, faces, params, faces_out, order]
            launch_in_chunks(_normal_sign(dtype), 1, num, inputs, [sign_out])
        if measure:
            launch_in_chunks(_measure(dtype), 1, num, [points, vertices, faces, faces_out, order], list(measured))

    if not build:

        def search_prepared(nodes, leaf_starts, sorted_faces, corners, *args):
            run(tree_struct(nodes, leaf_starts, sorted_faces, corners), None, *args)

        return search_prepared

    def search_built(vertices32, faces_flat, *args):
        # Winding signs come from Warp's mesh; every other search uses the oriented-box tree.
        if not winding:
            run(tree_struct(**build_tree(vertices32, faces_flat)), None, *args)
            return
        with mesh_in_call(vertices32, faces_flat, winding_number=True) as (_, words):
            run(tree_struct(**build_tree(vertices32, faces_flat)) if exact else None, words, *args)

    return search_built


_point_search_family = CallableFamily(
    _point_search, _point_types, outputs=_point_outputs, runs_on_host=lambda sign_mode, exact, measure, build: build, module=__name__
)


def point_faces(mesh, points, vertices, faces, max_distance, extent, *, sign_mode: str, exact: bool, sign_epsilon=None, measure=False):
    """Closest face (int32, -1 = none within the padded radius) and float32 sign (+1 / -1).

    Args:
        mesh: the oriented-box tree of a prepared mesh (``warp_ffi.host.closest_tree``), or
            ``(vertices32, faces_flat)`` to build the search structures in the call (Warp's mesh
            with winding-number support when ``sign_mode == "winding"``, else the tree).
        points: ``(N, 3)`` queries in the working dtype.
        vertices, faces: the geometry ``(V, 3)`` (working dtype) and ``(F, 3)`` int32 used by the
            refinement (the BVH's faces, same order).
        max_distance, extent: the search radius and ``max |vertex coordinate|``, 0-d arrays of
            the working dtype.
        sign_mode: ``"none"``, ``"normal"`` (pseudo-normal of the closest feature, faces
            within ``sign_epsilon`` of the closest point) or ``"winding"`` (Warp's winding
            number; needs ``mesh`` built in the call).
        exact: run the refinement (slivers are kept when ``sign_mode == "none"``, skipped
            otherwise, like Warp's signed queries; the first search does the same).
        sign_epsilon: 0-d array of the working dtype, for ``sign_mode == "normal"``.
        measure: also return the distance ``(N,)`` and closest point ``(N, 3)`` on the chosen
            face in the working dtype (zeros where there is none).
    """
    dtype = points.dtype
    if sign_epsilon is None:
        sign_epsilon = jnp.zeros((), dtype)
    params, params32 = search_params(dtype, max_distance, extent, sign_epsilon)
    build = len(mesh) == 2
    num = points.shape[0]
    shapes = {"faces_out": (num,), "sign_out": (num,), "keys_scratch": (2 * num,), "order_scratch": (2 * num,),
              "distance_out": (num,), "closest_out": (num,)}  # fmt: skip
    faces_out, sign_out, _, _, *measured = _point_search_family(dtype, SIGN_MODES[sign_mode], exact, measure, build)(
        *mesh_inputs(mesh), points.astype(jnp.float32), points, vertices, faces, params32, params, shapes=shapes
    )
    return (faces_out, sign_out, *measured)
