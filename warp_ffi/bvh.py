"""Warp triangle-mesh BVHs for JAX: mesh handles, nearest-face, signed and ray-cast searches.

Inputs arrive validated and normalised (no checks here): float32 vertices ``(V, 3)`` for the
BVH, flat in-range int32 indices ``(3 F,)``, query arrays ``(N, 3)`` with ``N > 0``, the mesh in
the working dtype (``(V, 3)`` vertices, ``(F, 3)`` int32 faces) and small parameter arrays.
Nothing here is differentiated: searches return discrete choices (a face id, a sign) and the
geometry of the chosen face measured in the working dtype; geomjax attaches derivatives by
replaying that geometry in JAX.

Handles. ``wp.Mesh`` is float32 and is addressed by a 64-bit id. A prepared mesh enters JAX as
``mesh_words``: its id split into two uint32 words (so no 64-bit JAX types are needed), in a
zero-copy JAX view of a Warp array that holds a reference to the mesh. The mesh therefore lives
as long as that buffer, and XLA keeps an input buffer alive until every computation that reads
it has finished, so a handle dropped while a dispatched computation still uses it is never
freed too early. Kernels turn the words back into the id with :func:`mesh_id`. Closest-point
searches use an oriented-box tree instead (``_obb_tree``: about 3x faster than Warp's
axis-aligned BVH on curved surfaces), prepared as plain arrays (:func:`closest_tree`). Searches
can also build their structures inside the FFI call from (traced) vertex and index buffers and
discard them at the end of the call: then the whole query, construction included, traces under
``jit``.

Searches (``point_faces``, ``ray_hits``):

* Closest face: a float32 search of the oriented-box tree (``_nearest_kernel``; each query starts
  from the previous Morton-ordered query's face on CPU), or Warp's ``mesh_query_point_sign_winding_number``
  (accuracy 2.0 and threshold 0.5, its defaults) for winding signs, with the radius padded by
  ``2**-16`` of the coordinate magnitudes, so rounding never loses a face at the gate; the caller
  re-gates exactly.
* Refinement (``exact=True``): the first search runs in float32 and breaks ties arbitrarily. The
  refinement kernel measures the first answer in the working dtype, enumerates every face within
  that distance (plus the pad) in the tree (conservative box bounds, float32 narrow phase),
  measures each again in the working dtype and keeps the nearest, ties to the lowest index.
  Float64 queries thus get the exact float64 nearest face for the cost of one extra local
  traversal.
* Normal signs: the angle-weighted pseudo-normal of the closest feature (``_normal_sign_kernel``),
  from the faces of the tree within a small radius of the closest point.
* Rays: ``mesh_query_ray`` on the unit direction (first hit, either side), max distance padded,
  then the distance, point and normal on the hit face in the working dtype.

On CPU every launch is split over the cores (``launch_in_chunks``), and point queries are visited
in Morton order (a Warp radix sort of their keys), which keeps tree nodes in cache (1.5-3x).
"""

from __future__ import annotations

import functools
import inspect
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._kernels import WARP_SCALAR, launch_in_chunks
from ._kernels import warp as wp
from ._obb_tree import TREE_ARRAYS, Tree, build_tree, leaf_within, next_after, node_distance_sq, query_order, tree_struct

wp.set_module_options({"enable_backward": False})

__all__ = ["build_mesh", "closest_tree", "mesh_handle", "mesh_id", "refit_mesh", "point_faces", "ray_hits", "SIGN_MODES"]

PAD = wp.constant(2.0**-16)  # relative margin of every float32 search radius
SLIVER_RATIO = wp.constant(1.0e-6)  # Warp's own sliver test: |AB x AC| / sum |edge|^2 below this
FLOAT32_MAX = wp.constant(3.4028234663852886e38)
SIGN_MODES = {"none": 0, "normal": 1, "winding": 2}
WINDING_ACCURACY = wp.constant(2.0)
WINDING_THRESHOLD = wp.constant(0.5)
# Morton-consecutive queries per thread of the nearest search on CPU (on CUDA one per thread:
# queries are not sorted there, and a GPU needs the threads).
CPU_SEARCH_BATCH = 32


# ---------------------------------------------------------------------------------------------
# Handles.


@wp.func
def mesh_id(words: wp.array(dtype=wp.uint32)):
    """The ``uint64`` mesh id stored as (low, high) uint32 words (the JAX handle format)."""
    return wp.uint64(words[0]) | (wp.uint64(words[1]) << wp.uint64(32))


def _words(mesh: wp.Mesh) -> np.ndarray:
    return np.array([mesh.id & 0xFFFFFFFF, mesh.id >> 32], dtype=np.uint32)


def build_mesh(vertices, faces_flat, *, winding_number: bool, device) -> wp.Mesh:
    """A ``wp.Mesh`` on ``device`` from float32 ``(V, 3)`` vertices and flat int32 indices.

    ``vertices``/``faces_flat`` may be NumPy arrays (copied to ``device``) or Warp arrays (used
    in place; they must outlive the mesh).
    """
    if not isinstance(vertices, wp.array):
        vertices = wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=device)
    if not isinstance(faces_flat, wp.array):
        faces_flat = wp.array(np.ascontiguousarray(faces_flat, np.int32), dtype=wp.int32, device=device)
    return wp.Mesh(points=vertices, indices=faces_flat, support_winding_number=winding_number)


def mesh_handle(mesh: wp.Mesh) -> jax.Array:
    """The JAX ``mesh_words`` of ``mesh``: uint32 ``(2,)``, zero-copy, keeping ``mesh`` alive."""
    words = wp.array(_words(mesh), dtype=wp.uint32, device=mesh.device)
    words.geomjax_mesh = mesh  # the reference that ties the mesh's lifetime to the JAX buffer
    handle = jax.dlpack.from_dlpack(words)
    if handle.unsafe_buffer_pointer() != words.ptr:  # pragma: no cover - JAX copied: no keep-alive
        raise RuntimeError("could not share the Warp mesh handle with JAX without a copy")
    return handle


def refit_mesh(mesh: wp.Mesh, vertices: np.ndarray) -> None:
    """Move the mesh's vertices (float32 ``(V, 3)``) and refit its BVH in place (same id)."""
    mesh.points.assign(wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=mesh.device))
    mesh.refit()


def closest_tree(vertices, faces_flat, device) -> tuple:
    """The oriented-box tree of a mesh as JAX arrays (``warp_ffi._obb_tree.TREE_ARRAYS`` order).

    ``vertices``: float32 ``(V, 3)``, ``faces_flat``: int32 ``(3 F,)`` NumPy arrays; the arrays
    are built on ``device`` and shared with JAX without a copy.
    """
    vertices = wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=device)
    faces_flat = wp.array(np.ascontiguousarray(faces_flat, np.int32), dtype=wp.int32, device=device)
    arrays = build_tree(vertices, faces_flat)
    return tuple(jax.dlpack.from_dlpack(arrays[name]) for name in TREE_ARRAYS)


# ---------------------------------------------------------------------------------------------
# Kernels.


@wp.func
def _max_abs(v: Any):
    return wp.max(wp.max(wp.abs(v[0]), wp.abs(v[1])), wp.abs(v[2]))


@wp.func
def _radius32(radius: Any, magnitude: Any):
    """``radius`` widened by the pad and rounded to a float32 that cannot be too small."""
    widened = radius + type(radius)(PAD) * (magnitude + radius)
    if not wp.isfinite(widened) or widened > type(radius)(FLOAT32_MAX):
        return float(FLOAT32_MAX)
    return float(widened)


@wp.func
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
def triangle_distance_sq(p: Any, a: Any, b: Any, c: Any):
    """Squared distance from ``p`` to triangle ``abc``."""
    offset = p - closest_point_on_triangle(p, a, b, c)
    return wp.dot(offset, offset)


@wp.func
def is_sliver(a: Any, b: Any, c: Any):
    """Warp's sliver rule (its closest-point queries skip these faces)."""
    ab = b - a
    ac = c - a
    bc = c - b
    total = wp.dot(ab, ab) + wp.dot(ac, ac) + wp.dot(bc, bc)
    return not (wp.length(wp.cross(ab, ac)) >= type(total)(SLIVER_RATIO) * total and total > type(total)(0.0))


@wp.kernel
def _winding_search_kernel(
    mesh_words: wp.array(dtype=wp.uint32),
    points: wp.array(dtype=wp.vec3),
    params: wp.array(dtype=wp.float32),
    order: wp.array(dtype=wp.int32),
    offset: wp.int32,
    faces_out: wp.array(dtype=wp.int32),
    sign_out: wp.array(dtype=wp.float32),
):
    """Closest face and winding-number sign from Warp's query (skips slivers, float32)."""
    _, t = wp.tid()
    i = order[t + offset]
    p = points[i]
    faces_out[i] = -1
    sign_out[i] = 1.0
    if not wp.isfinite(p):
        return
    radius = _radius32(params[0], params[1] + _max_abs(p))
    query = wp.mesh_query_point_sign_winding_number(mesh_id(mesh_words), p, radius, WINDING_ACCURACY, WINDING_THRESHOLD)
    if query.result:
        faces_out[i] = query.face
        sign_out[i] = query.sign


@wp.func
def _sorted_distance_sq(tree: Tree, s: int, p: wp.vec3):
    """Squared float32 distance from ``p`` to the tree's sorted face ``s``."""
    return triangle_distance_sq(p, tree.corners[3 * s], tree.corners[3 * s + 1], tree.corners[3 * s + 2])


# The nearest search's stack: one deferred sibling per level (trees are at most 31 levels deep).
_NodeStack = wp.types.vector(length=32, dtype=wp.int32)
_BoundStack = wp.types.vector(length=32, dtype=wp.float32)


@wp.kernel
def _nearest_kernel(
    tree: Tree,
    points: wp.array(dtype=wp.vec3),
    params: wp.array(dtype=wp.float32),
    skip_slivers: wp.int32,
    batch_size: wp.int32,
    order: wp.array(dtype=wp.int32),
    offset: wp.int32,
    faces_out: wp.array(dtype=wp.int32),
    sign_out: wp.array(dtype=wp.float32),
):
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
        i = order[t]
        p = points[i]
        faces_out[i] = -1
        sign_out[i] = 1.0
        if not wp.isfinite(p):
            continue
        radius = _radius32(params[0], params[1] + _max_abs(p))
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


@wp.kernel
def _refine_kernel(
    tree: Tree,
    points32: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=Any),
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.vec3i),
    params: wp.array(dtype=Any),
    skip_slivers: wp.int32,
    order: wp.array(dtype=wp.int32),
    offset: wp.int32,
    faces_io: wp.array(dtype=wp.int32),
):
    _, t = wp.tid()
    i = order[t + offset]
    best = faces_io[i]
    if best < 0:
        return
    p = points[i]
    tri = faces[best]
    best_d2 = triangle_distance_sq(p, vertices[tri[0]], vertices[tri[1]], vertices[tri[2]])
    max_distance = params[0]
    radius32 = _radius32(wp.min(wp.sqrt(best_d2), max_distance), params[1] + _max_abs(p))
    p32 = points32[i]
    leaf = leaf_within(tree, p32, radius32 * radius32, 1)
    while leaf != 0:
        j = leaf - tree.first_leaf
        for s in range(tree.leaf_starts[j], tree.leaf_starts[j + 1]):
            face = tree.faces[s]
            tri = faces[face]
            a = vertices[tri[0]]
            b = vertices[tri[1]]
            c = vertices[tri[2]]
            if skip_slivers != 0 and is_sliver(a, b, c):
                continue
            d2 = triangle_distance_sq(p, a, b, c)
            if d2 < best_d2 or (d2 == best_d2 and face < best):
                best_d2 = d2
                best = face
        leaf = leaf_within(tree, p32, radius32 * radius32, next_after(leaf))
    if wp.sqrt(best_d2) > max_distance:
        best = -1
    faces_io[i] = best


@wp.func
def _unit_scaled(v: Any):
    """``v / |v|`` computed on ``v / max |v_i|`` (no underflow); zero for a zero vector."""
    size = _max_abs(v)
    if size > type(size)(0.0):
        w = v / size
        return w / wp.length(w)
    return v - v


@wp.func
def _feature_weight(q: Any, a: Any, b: Any, c: Any, eps: Any):
    """Warp's weights: the angle at a vertex ``q`` sits on (within ``eps``), pi on an edge, else 2 pi."""
    e0 = b - a
    e1 = c - a
    e2 = c - b
    eps2 = eps * eps
    if wp.dot(q - a, q - a) < eps2:
        return wp.acos(wp.clamp(wp.dot(_unit_scaled(e0), _unit_scaled(e1)), type(eps)(-1.0), type(eps)(1.0)))
    if wp.dot(q - b, q - b) < eps2:
        return wp.acos(wp.clamp(wp.dot(_unit_scaled(e2), _unit_scaled(-e0)), type(eps)(-1.0), type(eps)(1.0)))
    if wp.dot(q - c, q - c) < eps2:
        return wp.acos(wp.clamp(wp.dot(_unit_scaled(-e1), _unit_scaled(-e2)), type(eps)(-1.0), type(eps)(1.0)))
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
def _normal_sign_kernel(
    tree: Tree,
    points: wp.array(dtype=Any),
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.vec3i),
    params: wp.array(dtype=Any),
    faces_in: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    offset: wp.int32,
    sign_out: wp.array(dtype=wp.float32),
):
    """Sign from the angle-weighted pseudo-normal of the closest feature.

    Every non-sliver face whose closest point to ``p`` lies within ``eps`` of the nearest face's
    closest point ``q`` (the faces sharing the closest vertex or edge) adds its unit normal with
    Warp's feature weight; the sign is that of ``(p - q) . sum``. Unlike Warp's own query, which
    also adds faces that are merely about as far away elsewhere on the mesh, this cannot be
    fooled at points equidistant from distant parts of the mesh (a sphere's centre, the middle
    of a thin slab).
    """
    _, t = wp.tid()
    i = order[t + offset]
    face = faces_in[i]
    if face < 0:
        return
    p = points[i]
    tri = faces[face]
    q = closest_point_on_triangle(p, vertices[tri[0]], vertices[tri[1]], vertices[tri[2]])
    eps = params[2]
    q32 = wp.vec3(float(q[0]), float(q[1]), float(q[2]))
    radius32 = _radius32(eps, params[1] + _max_abs(q))
    pseudo_normal = p - p
    leaf = leaf_within(tree, q32, radius32 * radius32, 1)
    while leaf != 0:
        j = leaf - tree.first_leaf
        for s in range(tree.leaf_starts[j], tree.leaf_starts[j + 1]):
            tri = faces[tree.faces[s]]
            a = vertices[tri[0]]
            b = vertices[tri[1]]
            c = vertices[tri[2]]
            if is_sliver(a, b, c):
                continue
            q_other = closest_point_on_triangle(p, a, b, c)
            if wp.dot(q_other - q, q_other - q) <= eps * eps:
                pseudo_normal += _feature_weight(q_other, a, b, c, eps) * _unit_scaled(wp.cross(b - a, c - a))
        leaf = leaf_within(tree, q32, radius32 * radius32, next_after(leaf))
    if wp.dot(pseudo_normal, p - q) > type(eps)(0.0):
        sign_out[i] = 1.0
    else:
        sign_out[i] = -1.0


@wp.kernel
def _ray_kernel(
    mesh_words: wp.array(dtype=wp.uint32),
    origins32: wp.array(dtype=wp.vec3),
    directions32: wp.array(dtype=wp.vec3),
    origins: wp.array(dtype=Any),
    directions: wp.array(dtype=Any),
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.vec3i),
    params32: wp.array(dtype=wp.float32),
    params: wp.array(dtype=Any),
    offset: wp.int32,
    faces_out: wp.array(dtype=wp.int32),
    t_out: wp.array(dtype=Any),
    points_out: wp.array(dtype=Any),
    normals_out: wp.array(dtype=Any),
):
    """First hit on the float32 BVH, then distance, point and normal on that face in the working dtype."""
    _, t = wp.tid()
    i = t + offset
    o = origins[i]
    zero = o - o
    faces_out[i] = -1
    t_out[i] = zero[0]
    points_out[i] = zero
    normals_out[i] = zero
    o32 = origins32[i]
    d32 = directions32[i]
    if not (wp.isfinite(o) and wp.isfinite(directions[i]) and _max_abs(d32) > 0.0):
        return
    max_t = _radius32(params32[0], params32[1] + _max_abs(o32))
    query = wp.mesh_query_ray(mesh_id(mesh_words), o32, _unit_scaled(d32), max_t)
    if not query.result:
        return
    unit = _unit_scaled(directions[i])
    tri = faces[query.face]
    a = vertices[tri[0]]
    normal = wp.cross(vertices[tri[1]] - a, vertices[tri[2]] - a)
    denominator = wp.dot(normal, unit)
    distance = zero[0] + type(zero[0])(query.t)
    if denominator != zero[0]:
        distance = wp.dot(normal, a - o) / denominator
    distance = wp.max(distance, zero[0])
    if distance > params[0]:
        return
    faces_out[i] = query.face
    t_out[i] = distance
    points_out[i] = o + distance * unit
    normals_out[i] = _unit_scaled(normal)


@wp.kernel
def _measure_kernel(
    points: wp.array(dtype=Any),
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.vec3i),
    faces_in: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    offset: wp.int32,
    distance_out: wp.array(dtype=Any),
    closest_out: wp.array(dtype=Any),
):
    """Closest point on the chosen face and its distance, in the working dtype."""
    _, t = wp.tid()
    i = order[t + offset]
    p = points[i]
    face = faces_in[i]
    if face < 0:
        distance_out[i] = p[0] - p[0]
        closest_out[i] = p - p
        return
    tri = faces[face]
    q = closest_point_on_triangle(p, vertices[tri[0]], vertices[tri[1]], vertices[tri[2]])
    offset_vector = p - q
    size = _max_abs(offset_vector)
    distance = size
    if size > type(size)(0.0):
        distance = size * wp.length(offset_vector / size)
    distance_out[i] = distance
    closest_out[i] = q


def _overloads(kernel, signature):
    """Both float overloads of ``kernel`` (registered up front: each new overload set recompiles)."""
    return {dtype: wp.overload(kernel, signature(_vec[dtype], scalar)) for dtype, scalar in WARP_SCALAR.items()}


def _array(dtype):
    return wp.array(dtype=dtype)


_vec = {dtype: wp.types.vector(3, scalar) for dtype, scalar in WARP_SCALAR.items()}
_words_t, _vec3f, _faces_t, _ints = _array(wp.uint32), _array(wp.vec3), _array(wp.vec3i), _array(wp.int32)
_refine = _overloads(
    _refine_kernel,
    lambda vec, s: [Tree, _vec3f, _array(vec), _array(vec), _faces_t, _array(s), wp.int32, _ints, wp.int32, _ints],
)
_normal_sign = _overloads(
    _normal_sign_kernel,
    lambda vec, s: [Tree, _array(vec), _array(vec), _faces_t, _array(s), _ints, _ints, wp.int32, _array(wp.float32)],
)
_ray = _overloads(
    _ray_kernel,
    lambda vec, s: [_words_t, _vec3f, _vec3f, _array(vec), _array(vec), _array(vec), _faces_t, _array(wp.float32),
                    _array(s), wp.int32, _ints, _array(s), _array(vec), _array(vec)],
)  # fmt: skip
_measure = _overloads(
    _measure_kernel, lambda vec, s: [_array(vec), _array(vec), _faces_t, _ints, _ints, wp.int32, _array(s), _array(vec)]
)


# ---------------------------------------------------------------------------------------------
# FFI callables. A ``build`` variant receives the mesh's vertices and indices instead of
# ``mesh_words`` and builds (then drops) its own BVH inside the call.


def _words_of_built(vertices32, faces_flat, winding_number: bool):
    mesh = build_mesh(vertices32, faces_flat, winding_number=winding_number, device=vertices32.device)
    return mesh, wp.array(_words(mesh), dtype=wp.uint32, device=vertices32.device)


def _jax_callable(body, annotations: dict, num_outputs: int, *, build: bool):
    """``wp.jax_callable`` of ``body``, whose argument names and Warp types are ``annotations``.

    ``build``: the body allocates (a BVH built in the call), so it cannot be graph-captured.
    """
    # jax_callable reads the argument names and types from the signature (as for Warp's own wrappers).
    body.__signature__ = inspect.Signature([inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD) for name in annotations])
    body.__annotations__ = annotations
    body.__module__ = __name__
    mode = wp.JaxCallableGraphMode.NONE if build else wp.JaxCallableGraphMode.JAX
    return wp.jax_callable(body, num_outputs=num_outputs, graph_mode=mode, vmap_method="sequential")


_BUILD_HEAD = {"vertices32": _vec3f, "faces_flat": _ints}
_TREE_HEAD = {"nodes": _array(wp.mat44), "leaf_starts": _ints, "sorted_faces": _ints, "corners": _vec3f}


@functools.cache
def _point_callable(dtype, sign_mode: int, exact: bool, measure: bool, build: bool):
    dtype = jnp.dtype(dtype)
    vec, scalar = _array(_vec[dtype]), _array(WARP_SCALAR[dtype])
    names = {"points32": _vec3f, "points": vec, "vertices": vec, "faces": _faces_t, "params32": _array(wp.float32), "params": scalar}
    outputs = {"faces_out": _ints, "sign_out": _array(wp.float32), "keys_scratch": _ints, "order_scratch": _ints}
    if measure:
        outputs.update(distance_out=scalar, closest_out=vec)
    winding = sign_mode == SIGN_MODES["winding"]
    if winding and not build:
        raise ValueError("winding-number signs need the BVH built in the call")

    def run(tree, mesh_words, points32, points, vertices, faces, params32, params, faces_out, sign_out, keys, order, *measured):
        num = points32.shape[0]
        query_order(points32, keys, order)
        if winding:
            launch_in_chunks(_winding_search_kernel, 1, num, [mesh_words, points32, params32, order], [faces_out, sign_out])
        else:
            batch = CPU_SEARCH_BATCH if points32.device.is_cpu else 1
            inputs = [tree, points32, params32, int(sign_mode != SIGN_MODES["none"]), batch, order]
            launch_in_chunks(_nearest_kernel, 1, -(-num // batch), inputs, [faces_out, sign_out], min_chunk=256)
        if exact:
            inputs = [tree, points32, points, vertices, faces, params, int(sign_mode != SIGN_MODES["none"]), order]
            launch_in_chunks(_refine[dtype], 1, num, inputs, [faces_out])
        if sign_mode == SIGN_MODES["normal"]:
            inputs = [tree, points, vertices, faces, params, faces_out, order]
            launch_in_chunks(_normal_sign[dtype], 1, num, inputs, [sign_out])
        if measure:
            launch_in_chunks(_measure[dtype], 1, num, [points, vertices, faces, faces_out, order], list(measured))

    if build:

        def body(vertices32, faces_flat, *args):
            # Winding signs come from Warp's mesh; every other search uses the oriented-box tree.
            mesh, words = _words_of_built(vertices32, faces_flat, True) if winding else (None, None)
            tree = tree_struct(**build_tree(vertices32, faces_flat)) if exact or not winding else None
            run(tree, words, *args)
            del mesh

    else:

        def body(nodes, leaf_starts, sorted_faces, corners, *args):
            run(tree_struct(nodes, leaf_starts, sorted_faces, corners), None, *args)

    head = _BUILD_HEAD if build else _TREE_HEAD
    return _jax_callable(body, {**head, **names, **outputs}, len(outputs), build=build)


@functools.cache
def _ray_callable(dtype, build: bool):
    dtype = jnp.dtype(dtype)
    vec, scalar = _array(_vec[dtype]), _array(WARP_SCALAR[dtype])
    names = {"origins32": _vec3f, "directions32": _vec3f, "origins": vec, "directions": vec, "vertices": vec,
             "faces": _faces_t, "params32": _array(wp.float32), "params": scalar}  # fmt: skip
    outputs = {"faces_out": _ints, "t_out": scalar, "points_out": vec, "normals_out": vec}

    def run(mesh_words, *args):
        inputs, results = [mesh_words, *args[:8]], list(args[8:])
        launch_in_chunks(_ray[dtype], 1, args[0].shape[0], inputs, results)

    if build:

        def body(vertices32, faces_flat, *args):
            mesh, words = _words_of_built(vertices32, faces_flat, False)
            run(words, *args)
            del mesh

        head = _BUILD_HEAD
    else:
        body, head = run, {"mesh_words": _words_t}
    return _jax_callable(body, {**head, **names, **outputs}, len(outputs), build=build)


def _mesh_inputs(mesh):
    """``mesh`` is a prepared handle (one array, or a tuple of tree arrays), or ``(vertices32, faces_flat)``."""
    return mesh if isinstance(mesh, tuple) else (mesh,)


def _params(dtype, *values):
    params = jnp.stack(values).astype(dtype)
    return params, jnp.minimum(params, jnp.asarray(np.finfo(np.float32).max, dtype)).astype(jnp.float32)


def point_faces(mesh, points, vertices, faces, max_distance, extent, *, sign_mode: str, exact: bool, sign_epsilon=None, measure=False):
    """Closest face (int32, -1 = none within the padded radius) and float32 sign (+1 / -1).

    Args:
        mesh: the oriented-box tree of a prepared mesh (:func:`closest_tree`), or ``(vertices32,
            faces_flat)`` to build the search structures in the call (Warp's mesh with
            winding-number support when ``sign_mode == "winding"``, else the tree).
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
    params, params32 = _params(dtype, max_distance, extent, sign_epsilon)
    callable_ = _point_callable(jnp.dtype(dtype), SIGN_MODES[sign_mode], exact, measure, len(mesh) == len(_BUILD_HEAD))
    num = points.shape[0]
    points32 = points.astype(jnp.float32)
    dims = {"faces_out": (num,), "sign_out": (num,), "keys_scratch": (2 * num,), "order_scratch": (2 * num,),
            "distance_out": (num,), "closest_out": (num,)}  # fmt: skip
    faces_out, sign_out, _, _, *measured = callable_(
        *_mesh_inputs(mesh), points32, points, vertices, faces, params32, params, output_dims=dims
    )
    return (faces_out, sign_out, *measured)


def ray_hits(mesh, origins, directions, vertices, faces, max_distance, extent):
    """First hit of each ray: ``(face (int32, -1 = miss), distance, point, unit normal)``.

    ``mesh`` as in :func:`point_faces`; ``origins``/``directions`` ``(N, 3)`` in the working
    dtype (directions normalised in the kernel; the search runs in float32, the hit is measured
    on the chosen face in the working dtype and gated by ``max_distance``); ``vertices``,
    ``faces`` as in :func:`point_faces`; ``max_distance`` and ``extent`` 0-d arrays. Misses
    have zero distance, point and normal.
    """
    dtype = origins.dtype
    params, params32 = _params(dtype, max_distance, extent)
    num = origins.shape[0]
    # Scale each direction to unit max-norm first, so a tiny float64 direction survives float32.
    size = jnp.max(jnp.abs(directions), axis=-1, keepdims=True)
    directions32 = (directions / jnp.where(size > 0, size, jnp.ones((), dtype))).astype(jnp.float32)
    dims = {"faces_out": (num,), "t_out": (num,), "points_out": (num,), "normals_out": (num,)}
    return tuple(
        _ray_callable(jnp.dtype(dtype), isinstance(mesh, tuple))(
            *_mesh_inputs(mesh), origins.astype(jnp.float32), directions32, origins, directions,
            vertices, faces, params32, params, output_dims=dims,
        )
    )  # fmt: skip
