"""Nearest-valid-face search on a Warp BVH, for shrinkwrap (no gradient).

Inputs arrive validated and normalised (no checks here): query points ``(Q, 3)`` and target
vertices ``(V, 3)`` in the working dtype (float32 or float64), flat in-range triangle indices
``(3 F,)`` int32 and a validity flag per face.

Warp's meshes are float32, and its closest-point query breaks ties arbitrarily and skips faces
it considers slivers, so its answer is a starting point. Faces are compared by
``face_feature``: the distance in the working dtype and the nearest feature (interior, edge or
vertex), so faces sharing the nearest edge or vertex tie exactly and the lowest index wins.

1. ``mesh_query_point_no_sign`` in the float32 *search frame* gives a face and its distance
   ``d0`` (an upper bound of the distance to the nearest face, up to float32 rounding).
2. float32 queries: the faces within a pad (``2**-16`` times the coordinate magnitudes, far
   above float32 rounding) of Warp's closest point are measured and the best kept, which settles
   the ties at shared edges and vertices. Two distinct features equally near up to float32
   rounding keep Warp's choice.
3. float64 queries (and a float32 query whose step 2 disagrees with Warp): ``mesh_query_sphere``
   enumerates every face within ``d0 + 2 pad`` and measures each valid one in the working dtype;
   the best is accepted when the ball reaches a pad beyond its distance (then every nearer face
   was enumerated), otherwise the radius grows to that (or doubles while nothing valid was met,
   up to the gate or the whole mesh) and the enumeration repeats. The answer is the brute-force
   answer in float64, at the cost of a second local traversal; a wrong first guess (an invalid
   face in a prebuilt BVH, a skipped sliver) costs time, never correctness.

The search frame is ``(x - centre) * inv_scale`` with a power-of-two ``inv_scale``: geomjax maps
the valid geometry into ``[-1, 1]^3`` so float64 coordinates of any magnitude fit a float32
BVH; for a prebuilt BVH the frame is the identity. Distances are measured on
``(vertex - query) * inv_scale`` in the working dtype. On CPU, launches are split over the cores
(``launch_in_chunks``).
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax
import jax.numpy as jnp

from ._grid import DEAD_MESH_FACE, fill_outputs, is_live_mesh, mesh_id, mesh_in_call
from ._wrap import CallableFamily, Overloads, launch_in_chunks, scalars, vectors
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["nearest_valid_faces"]

SEARCH_PAD = wp.constant(2.0**-16)  # relative margin of every float32 radius
SQRT3 = wp.constant(1.7320508075688772)
GROWTH = wp.constant(1.0 + 2.0**-20)  # rounds a float64 distance up to float32 safely
MAX_PASSES = 160  # radius doublings from float32's smallest normal to its largest finite value


@wp.func
@no_type_check
def _segment_feature(u: Any, v: Any, u_index: int, v_index: int):
    """Squared distance from the origin to segment ``uv`` and its nearest feature.

    Returns ``(d2, first, second)``: the feature is the vertex ``(i, i)`` or the edge
    ``(min index, max index)``, measured from the lower-indexed endpoint.
    """
    lo = u
    hi = v
    lo_index = u_index
    hi_index = v_index
    if v_index < u_index:
        lo = v
        hi = u
        lo_index = v_index
        hi_index = u_index
    d = hi - lo
    length2 = wp.dot(d, d)
    t = -wp.dot(lo, d)
    if t <= type(length2)(0.0) or length2 == type(length2)(0.0):
        return wp.dot(lo, lo), lo_index, lo_index
    if t >= length2:
        return wp.dot(hi, hi), hi_index, hi_index
    p = lo + (t / length2) * d
    return wp.dot(p, p), lo_index, hi_index


@wp.func
@no_type_check
def face_feature(a: Any, b: Any, c: Any, ia: int, ib: int, ic: int, face: int):
    """Squared distance from the origin to triangle ``abc`` and the nearest feature.

    The feature is ``(-1 - face, -1)`` for the interior (the origin projects inside: plane
    distance), else that of the nearest edge (``_segment_feature``). Faces sharing the nearest
    edge or vertex thus report the same feature whatever the rounding of their distances, which
    is how ties are recognised. ``geomjax.deform.shrinkwrap.face_features`` is the same
    computation in JAX.
    """
    zero = type(a[0])(0.0)
    n = wp.cross(b - a, c - a)
    n2 = wp.dot(n, n)
    if n2 > zero and wp.dot(n, wp.cross(a, b)) >= zero and wp.dot(n, wp.cross(b, c)) >= zero and wp.dot(n, wp.cross(c, a)) >= zero:
        h = wp.dot(n, a)
        return h * h / n2, -1 - face, -1
    d2, first, second = _segment_feature(a, b, ia, ib)
    d2_bc, first_bc, second_bc = _segment_feature(b, c, ib, ic)
    if d2_bc < d2:
        d2 = d2_bc
        first = first_bc
        second = second_bc
    d2_ca, first_ca, second_ca = _segment_feature(c, a, ic, ia)
    if d2_ca < d2:
        d2 = d2_ca
        first = first_ca
        second = second_ca
    return d2, first, second


@wp.func
@no_type_check
def _nearest_in_ball(
    mesh: wp.uint64, centre: wp.vec3, radius: float, x: Any, s: Any, vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32), valid: wp.array(dtype=wp.int32),
):  # fmt: skip
    """Nearest valid face to ``x`` among the faces within ``radius`` of ``centre`` (search frame).

    Returns ``(face, d2)`` (``-1`` when there is none), ``d2`` in search-frame units. Faces at the
    same feature tie exactly (see ``face_feature``); then, and on equal distances, the lowest
    index wins.
    """
    best = int(-1)
    best_d2 = type(s)(0.0)
    best_first = int(0)
    best_second = int(0)
    query = wp.mesh_query_sphere(mesh, centre, radius)
    f = int(0)
    while wp.mesh_query_next(query, f):
        if valid[f] != 0:
            ia = faces[3 * f]
            ib = faces[3 * f + 1]
            ic = faces[3 * f + 2]
            d2, first, second = face_feature((vertices[ia] - x) * s, (vertices[ib] - x) * s, (vertices[ic] - x) * s, ia, ib, ic, f)
            if best >= 0 and first == best_first and second == best_second:
                best = wp.min(best, f)
                best_d2 = wp.min(best_d2, d2)
            elif best < 0 or d2 < best_d2 or (d2 == best_d2 and f < best):
                best = f
                best_d2 = d2
                best_first = first
                best_second = second
    return best, best_d2


@wp.kernel
@no_type_check
def _nearest_kernel(
    mesh_words: wp.array(dtype=wp.uint32), points: wp.array(dtype=Any), vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32), valid: wp.array(dtype=wp.int32), search_points: wp.array(dtype=wp.vec3),
    inv_scale: wp.array(dtype=Any), limits: wp.array(dtype=wp.float32), exact: int, offset: int, nearest: wp.array(dtype=wp.int32),
):  # fmt: skip
    _b, item = wp.tid()
    i = item + offset
    mesh = mesh_id(mesh_words)
    x = points[i]
    q = search_points[i]
    s = inv_scale[0]
    extent = limits[0]
    base = extent + wp.max(wp.abs(q))
    # Every vertex lies within sqrt(3) * extent of the frame origin.
    limit = wp.min(limits[1], wp.length(q) + SQRT3 * extent)
    limit = limit + SEARCH_PAD * (base + limit)
    radius = limit
    guess = wp.mesh_query_point_no_sign(mesh, q, limit)
    if guess.result:
        closest = wp.mesh_eval_position(mesh, guess.face, guess.u, guess.v)
        d0 = wp.length(closest - q)
        # Two pads: the exact distance may exceed Warp's float32 one by rounding (less than one
        # pad) and the enumeration must still reach one pad beyond it.
        radius = wp.min(d0 + 2.0 * SEARCH_PAD * (base + d0), limit)
        if exact == 0:
            # Only the faces touching Warp's closest point: they settle ties at shared edges and
            # vertices; equally near faces elsewhere stay Warp's float32 choice.
            local, local_d2 = _nearest_in_ball(mesh, closest, SEARCH_PAD * base, x, s, vertices, faces, valid)
            if local >= 0 and wp.float32(wp.sqrt(local_d2)) <= radius:
                nearest[i] = local
                return
    best = int(-1)
    for _pass in range(MAX_PASSES):
        best, best_d2 = _nearest_in_ball(mesh, q, radius, x, s, vertices, faces, valid)
        if best >= 0:
            d = wp.float32(wp.sqrt(best_d2)) * GROWTH
            reach = d + SEARCH_PAD * (base + d)
            if reach <= radius or radius >= limit:
                break
            radius = wp.min(reach + SEARCH_PAD * (base + d), limit)
        else:
            if radius >= limit:
                break
            radius = wp.min(2.0 * radius + SEARCH_PAD * base, limit)
    nearest[i] = best


_nearest = Overloads(_nearest_kernel, lambda s: {"points": vectors(s), "vertices": vectors(s), "inv_scale": scalars(s)})


def _search_types(scalar, build: bool) -> dict:
    head: dict[str, wp.array] = {"search_vertices": wp.array(dtype=wp.vec3)} if build else {"mesh_words": wp.array(dtype=wp.uint32)}
    ints: wp.array = wp.array(dtype=wp.int32)
    inputs = {"points": vectors(scalar), "vertices": vectors(scalar), "faces": ints, "valid": ints,
              "search_points": wp.array(dtype=wp.vec3), "inv_scale": scalars(scalar), "limits": scalars(wp.float32)}  # fmt: skip
    return {**head, **inputs, "nearest": ints}


def _search(dtype, build: bool):
    """The body of the search of a prebuilt mesh (``mesh_words``), or of one built from its inputs first."""
    kernel = _nearest(dtype)
    exact = int(dtype == jnp.float64)

    def search(mesh_words, points, vertices, faces, valid, search_points, inv_scale, limits, nearest):
        inputs = [mesh_words, points, vertices, faces, valid, search_points, inv_scale, limits, exact]
        launch_in_chunks(kernel, 1, points.shape[0], inputs, [nearest], min_chunk=1024)

    def search_prepared(mesh_words, *args):
        if is_live_mesh(mesh_words) is False:  # a forged or freed handle: never dereferenced
            fill_outputs(args[-1:], (DEAD_MESH_FACE,))
            return
        search(mesh_words, *args)

    if not build:
        return search_prepared

    def search_built(search_vertices, points, vertices, faces, valid, search_points, inv_scale, limits, nearest):
        with mesh_in_call(search_vertices, faces, winding_number=False) as (_, words):
            search(words, points, vertices, faces, valid, search_points, inv_scale, limits, nearest)

    return search_built


# Never captured in a CUDA graph: a prepared mesh's handle is checked on the host on every call,
# a built one is allocated in the call.
_search_family = CallableFamily(_search, _search_types, outputs=("nearest",), runs_on_host=True, module=__name__)


def nearest_valid_faces(
    mesh: jax.Array,
    points: jax.Array,
    vertices: jax.Array,
    faces: jax.Array,
    valid: jax.Array,
    search_points: jax.Array,
    inv_scale: jax.Array,
    limits: jax.Array,
) -> jax.Array:
    """Index of the nearest valid face of each query (``-1``: none within the gate).

    Args:
        mesh: the ``(2,)`` uint32 ``mesh_words`` of a prebuilt BVH (see ``warp_ffi.host``), or
            the float32 ``(V, 3)`` search-frame vertices to build one from in the call.
        points: ``(Q, 3)`` queries in the working dtype.
        vertices: ``(V, 3)`` target vertices, same dtype.
        faces: ``(3 F,)`` int32 in-range indices, in the BVH's face order; invalid faces may hold
            any in-range indices (they are in the BVH but never selected).
        valid: ``(F,)`` int32, nonzero for faces that may be selected.
        search_points: the queries in the float32 search frame ``(x - centre) * inv_scale``,
            finite (the frame the BVH was built in).
        inv_scale: ``(1,)`` power of two in the working dtype.
        limits: ``(2,)`` float32: the largest absolute search-frame coordinate of a vertex of a
            valid face, and the gate radius in the search frame (a huge value for none).

    Faces farther than the gate may be returned; callers re-gate on the exact distance. A
    prepared handle whose mesh is not alive (forged, or freed) is not searched: every query
    gets ``DEAD_MESH_FACE``.
    """
    build = mesh.dtype != jnp.uint32
    (nearest,) = _search_family(points.dtype, build)(
        mesh, points, vertices, faces, valid, search_points, inv_scale, limits, shapes={"nearest": points.shape[:1]}
    )
    return nearest
