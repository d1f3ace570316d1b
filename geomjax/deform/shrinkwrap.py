"""Shrinkwrap: move points onto (or to an offset of) the nearest triangle of a target surface."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._blocking import map_query_blocks, query_block_size
from .._dispatch import platform_of, select_implementation
from .._errors import raises_documented_errors
from .._geometry import closest_point_on_triangle, overflow_safe_norm, scaled_triangle, triangle_normal
from .._points import add_batch_axis, apply_point_weights, remove_batch_axis
from .._sharding import map_local_shards
from .._validate import (
    as_float_array,
    check_coordinates,
    check_index_range,
    check_point_weights,
    check_real_scalar,
    check_same_device,
    check_same_dtype,
    check_topology,
    is_array,
    require,
)

__all__ = ["shrinkwrap_points", "valid_triangles", "face_features", "nearest_faces_jax"]

_NAME = "shrinkwrap_points"


# Far queries are clipped to this search-frame magnitude so squared float32 distances stay finite.
_SEARCH_CLIP = 2.0**60
_NO_GATE = 1e30


@raises_documented_errors
def shrinkwrap_points(
    points: Float[Array, "*batch num_points 3"],
    target_points: Float[Array, "num_target_points 3"],
    target_faces: Int[Array, "num_target_faces 3"],
    *,
    offset: float | Float[Array, ""] = 0.0,
    max_distance: float | None = None,
    point_weights: Bool[Array, "*batch num_points"] | Float[Array, "*batch num_points"] | None = None,
    implementation: str | None = None,
    bvh=None,
) -> Float[Array, "*batch num_points 3"]:
    """Project points onto the nearest triangle of a target surface, optionally offset.

    Each point ``x`` moves to ``x' = x + w (p + offset n - x)``, where ``p`` is the closest point
    on the nearest *valid* target triangle and ``n`` that triangle's unit normal
    ``normalize((b - a) x (c - a))`` (it follows the winding). Float weights give
    ``(1 - w) x + w (p + offset n)``; bool weights are a hard mask (``where``).

    * Invalid triangles are ignored: non-finite vertices, zero extent, or
      ``|AB x AC| <= eps (longest edge)^2`` on edge-normalised coordinates (``eps`` of the
      dtype). At least one triangle must be valid.
    * ``max_distance`` gates strictly on the distance to the un-offset surface: a point at
      distance ``>= max_distance`` is returned unchanged.
    * Any finite coordinates: the validity test, both searches and the projection are scaled
      by powers of two, so triangles with opposite-sign vertices near the largest float,
      queries 1e20 triangle sizes away and distances whose squares overflow keep their
      projections, finite derivatives and the nearest-face order. A skinny valid triangle
      (aspect ratio up to about ``1 / eps``) keeps its interior projections, with the in-plane
      identity as derivative.
    * The nearest face minimises the distance in the working dtype; faces sharing the nearest
      edge or vertex tie and the lowest index wins (the brute-force rule). float64 inputs are
      searched exactly by both backends; in float32 two distinct features equally near up to
      rounding may resolve differently between backends.

    Args:
        points: ``(N, 3)`` or batched ``(B, N, 3)``, float32 or float64, finite.
        target_points: ``(M, 3)`` target vertices, shared by every batch (same dtype and device).
        target_faces: ``(F, 3)`` int32/int64 triangles, ``F >= 1``, indices in ``[0, M)``.
        offset: distance along the selected face's normal: a finite Python real, or a 0-d array
            of the points' dtype (differentiable; finiteness checked eagerly, or by
            ``equinox.error_if`` under ``jit``).
        max_distance: ``None`` (no gate) or a positive finite real that does not underflow.
        point_weights: optional ``(N,)`` / ``(B, N)`` bool or float (points' dtype) weights.
        implementation: ``"warp"``, ``"jax"`` (also ``"torch"``) or ``None``; it selects the
            nearest-face *search*, the projection itself is always replayed in JAX.
            ``"warp"``: a float32 Warp BVH (``wp.Mesh``, built on each call from the valid
            faces mapped into ``[-1, 1]^3``, or the prebuilt ``bvh``) finds the nearest face;
            for float64 every face within its distance is then measured again in float64
            (see ``warp_ffi/shrinkwrap.py``), so the answer is the exact brute-force answer at
            about twice the cost of one BVH query. ``"jax"``: brute force over every
            point/face pair, ``O(N F)``, blocked to bounded memory; meant as the reference for
            small meshes. ``None`` picks the BVH (``"warp"``) on every platform when warp-lang
            is installed, ``"jax"`` otherwise (``benchmarks/bench_shrinkwrap_voxel.py`` compares
            it with Open3D's ``compute_closest_points``; brute force is quadratic).
        bvh: optional :class:`geomjax.MeshBVH` built from ``(target_points, target_faces)``
            (an addition to the reference API): the Warp search reuses it instead of building a
            BVH per call, e.g. in optimisation loops (``bvh.refit`` after moving the target).
            It must describe the same geometry; differentiation still goes through
            ``target_points``. Ignored by ``implementation="jax"``.

    Returns:
        The moved points, shape and dtype of ``points``. ``N = 0`` gives an empty result.

    Raises:
        TypeError: non-float points or targets, mismatched dtypes, non-integer faces, integer
            weights, a ``bool``/non-real ``offset`` or ``max_distance``, an ``offset`` array of
            another dtype, a ``bvh`` that is not a ``MeshBVH``.
        ValueError: points not ``(N, 3)``/``(B, N, 3)``, a batched or non-``(M, 3)`` target,
            faces not ``(F, 3)`` or empty, indices out of range, non-finite points, no valid
            triangle, a non-finite ``offset``, a non-positive, non-finite or underflowing
            ``max_distance``, a ``bvh`` of other sizes. The value checks (index range,
            finiteness, a valid triangle) run eagerly on concrete arrays; under ``jit`` they are
            ``equinox.error_if`` checks raising at run time.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiable in ``points``, ``target_points`` (the vertices of each selected face), float
    ``point_weights`` and an array ``offset``: the discrete face choice has no derivative and the
    closest point is replayed on the selected face in JAX (piecewise smooth; on a region or tie
    boundary the derivative of the selected side is returned). Gated and masked points have zero
    derivatives. Both backends support ``jit``, ``vmap``, reverse and forward mode (the replay is
    plain JAX) and give identical results in float64 (in float32, up to distinct features equally
    near within rounding).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import shrinkwrap_points
        >>> square = jnp.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
        >>> faces = jnp.array([[0, 1, 2], [0, 2, 3]])
        >>> points = jnp.array([[0.25, 0.5, 2.0], [2.0, 0.5, -1.0]])
        >>> moved = shrinkwrap_points(points, square, faces, offset=0.1, implementation="jax")
        >>> print(np.round(np.asarray(moved), 3))
        [[0.25 0.5  0.1 ]
         [1.   0.5  0.1 ]]
    """
    points, batched = check_coordinates("points", points)
    if points.shape[-1] != 3:
        raise ValueError(f"points must have 3 coordinates, got shape {tuple(points.shape)}")
    target_points = as_float_array("target_points", target_points)
    check_same_dtype("points", points, "target_points", target_points)
    check_same_device("points", points, "target_points", target_points)
    if target_points.ndim != 2 or target_points.shape[1] != 3:
        raise ValueError(f"target_points must have shape (M, 3) (one target shared by every batch), got {tuple(target_points.shape)}")
    target_faces = check_topology("target_faces", target_faces, points, vertices_per_row=(3,))
    if target_faces.shape[0] == 0:
        raise ValueError("target_faces must hold at least one triangle, got shape (0, 3)")
    point_weights = check_point_weights(point_weights, points)
    dtype = points.dtype
    offset = _offset_array(offset, points)
    if max_distance is not None:
        max_distance = check_real_scalar("max_distance", max_distance, dtype, positive=True)
    backend = select_implementation(_NAME, implementation, platform=platform_of(points))
    if bvh is not None:
        _check_bvh(bvh, target_points, target_faces)

    num_targets = target_points.shape[0]
    faces = check_index_range(target_faces, num_targets, f"{_NAME}: target_faces indices must be in [0, {num_targets}) for {num_targets} target points")
    points = require(points, lambda x: jnp.all(jnp.isfinite(x)), f"{_NAME}: points must be finite")
    valid = require(
        valid_triangles(target_points, faces), jnp.any, f"{_NAME}: target_points/target_faces hold no valid triangle (all are degenerate or non-finite)"
    )
    if points.shape[-2] == 0:
        return points
    gate = None if max_distance is None else jnp.asarray(max_distance, dtype)

    def local(points, target_points, faces, valid, offset, point_weights, gate):
        return _shrinkwrap(points, target_points, faces, valid, offset, point_weights, gate, bvh, backend=backend, batched=batched)

    # Points are independent: sharded points (and their weights) are projected shard by shard
    # onto the whole target (the Warp search's sort refuses a sharded axis).
    lead = points.ndim - 1
    arrays = (points, target_points, faces, valid, offset, point_weights, gate)
    return map_local_shards(local, arrays, (lead, 0, 0, 0, 0, lead, 0), out_axes=lead)


@functools.partial(jax.jit, static_argnames=("backend", "batched"))
def _shrinkwrap(points, target_points, faces, valid, offset, point_weights, max_distance, bvh, *, backend, batched):
    """Search (no gradient) and replay, normalised to ``(B, N, 3)`` points inside the compiled
    program (``max_distance``: 0-d or None)."""
    x = add_batch_axis(points, batched)
    weights = add_batch_axis(point_weights, batched)
    queries = x.reshape(-1, 3)
    if backend.is_warp:
        nearest = _nearest_faces_warp(queries, target_points, faces, valid, max_distance, bvh)
    else:
        nearest = nearest_faces_jax(queries, target_points, faces, valid)
    nearest = jax.lax.stop_gradient(nearest).reshape(x.shape[:-1])
    fallback = jnp.argmax(valid).astype(nearest.dtype)
    field = _projection_field(x, target_points, faces, nearest, fallback, offset, max_distance)
    return remove_batch_axis(apply_point_weights(x, field, weights), batched)


def _offset_array(offset, points: jax.Array) -> jax.Array:
    dtype = points.dtype
    if not is_array(offset):
        return jnp.asarray(check_real_scalar("offset", offset, dtype), dtype)
    offset = as_float_array("offset", offset)
    check_same_dtype("points", points, "offset", offset)
    check_same_device("points", points, "offset", offset)
    if offset.ndim != 0:
        raise ValueError(f"offset must be a Python real or a 0-d array, got shape {tuple(offset.shape)}")
    return require(offset, jnp.isfinite, f"{_NAME}: offset must be finite")


def _check_bvh(bvh, target_points: jax.Array, target_faces: jax.Array) -> None:
    from ..query.bvh import MeshBVH

    if not isinstance(bvh, MeshBVH):
        raise TypeError(f"bvh must be None or a geomjax.MeshBVH, got {type(bvh).__name__}")
    if tuple(bvh.vertices.shape) != tuple(target_points.shape) or tuple(bvh.faces.shape) != tuple(target_faces.shape):
        raise ValueError(
            f"bvh was built for {bvh.vertices.shape[0]} vertices and {bvh.faces.shape[0]} faces, but the target has "
            f"{target_points.shape[0]} and {target_faces.shape[0]}"
        )


@jax.jit
def valid_triangles(vertices: jax.Array, faces: jax.Array) -> jax.Array:
    """``(F,)`` bool: finite, non-zero extent and ``|AB x AC| > eps (longest edge)^2``.

    Edges are taken in triangle units (coordinates quartered near the float maximum, then
    differences scaled by a power of two near the triangle's size: the projection's own
    scaling), so the test does not depend on the triangle's scale and cannot overflow or
    underflow, even for vertices of opposite sign near the largest float.
    """
    vertices = jax.lax.stop_gradient(vertices)
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    finite = jnp.all(jnp.isfinite(jnp.concatenate([a, b, c], axis=-1)), axis=-1)
    ab, ac, bc, _, _ = scaled_triangle(a, b, c)
    extent = jnp.max(jnp.abs(jnp.concatenate([ab, ac, bc], axis=-1)), axis=-1)
    usable = finite & (extent > 0)
    normal = jnp.cross(ab, ac)
    longest2 = jnp.maximum(jnp.maximum(jnp.sum(ab * ab, -1), jnp.sum(ac * ac, -1)), jnp.sum(bc * bc, -1))
    eps = jnp.finfo(vertices.dtype).eps
    return usable & (jnp.sqrt(jnp.sum(normal * normal, -1)) > eps * longest2)


# ---------------------------------------------------------------------------------------------
# Nearest-face searches (no gradient).


def face_features(x: jax.Array, a: jax.Array, b: jax.Array, c: jax.Array, faces: jax.Array, face_index: jax.Array):
    """Squared distance from ``x`` to triangles ``(a, b, c)`` and the nearest feature of each.

    The search key of both backends (``warp_ffi.shrinkwrap.face_feature`` is the same
    computation). ``faces`` ``(..., 3)`` holds the vertex indices and ``face_index`` the face
    numbers. Returns ``(d2, first, second)``: the plane distance and feature ``(-1 - face, -1)``
    when ``x`` projects inside the triangle, else the nearest edge's distance and its feature:
    the vertex ``(i, i)`` or the edge ``(min index, max index)``, measured from the lower-indexed
    endpoint. Faces sharing the nearest edge or vertex report the same feature whatever the
    rounding of their distances, which is how exact ties are recognised. Not differentiated (the
    projection itself is :func:`~geomjax.query._triangle.closest_point_on_triangle`).
    """
    a, b, c = a - x, b - x, c - x
    zero = jnp.zeros((), x.dtype)
    one = jnp.ones((), x.dtype)

    def segment(u, v, iu, iv):
        swap = iv < iu
        lo, hi = jnp.where(swap[..., None], v, u), jnp.where(swap[..., None], u, v)
        lo_index, hi_index = jnp.where(swap, iv, iu), jnp.where(swap, iu, iv)
        d = hi - lo
        length2 = jnp.sum(d * d, -1)
        t = -jnp.sum(lo * d, -1)
        at_lo = (t <= 0) | (length2 == 0)
        at_hi = ~at_lo & (t >= length2)
        p = lo + (t / jnp.where(at_lo, one, length2))[..., None] * d
        d2 = jnp.where(at_lo, jnp.sum(lo * lo, -1), jnp.where(at_hi, jnp.sum(hi * hi, -1), jnp.sum(p * p, -1)))
        first = jnp.where(at_hi, hi_index, lo_index)
        second = jnp.where(at_lo, lo_index, hi_index)
        return d2, first, second

    ia, ib, ic = faces[..., 0], faces[..., 1], faces[..., 2]
    d2, first, second = segment(a, b, ia, ib)
    for u, v, iu, iv in ((b, c, ib, ic), (c, a, ic, ia)):
        d2_e, first_e, second_e = segment(u, v, iu, iv)
        closer = d2_e < d2
        d2, first, second = jnp.where(closer, d2_e, d2), jnp.where(closer, first_e, first), jnp.where(closer, second_e, second)
    n = jnp.cross(b - a, c - a)
    n2 = jnp.sum(n * n, -1)
    inside = (n2 > 0) & jnp.all(jnp.stack([jnp.sum(n * jnp.cross(u, v), -1) >= zero for u, v in ((a, b), (b, c), (c, a))]), axis=0)
    plane = jnp.square(jnp.sum(n * a, -1)) / jnp.where(n2 > 0, n2, one)
    d2 = jnp.where(inside, plane, d2)
    first = jnp.where(inside, -1 - face_index, first)
    second = jnp.where(inside, -1, second)
    return d2, first, second


def nearest_faces_jax(points: jax.Array, vertices: jax.Array, faces: jax.Array, valid: jax.Array) -> jax.Array:
    """Brute force: index of the nearest valid face of each ``(Q, 3)`` point.

    Every point/face pair is measured with :func:`face_features` (in query blocks so memory
    stays bounded); among the faces sharing the nearest feature the lowest index wins.

    Coordinates so large that a difference or a squared distance would overflow (beyond about
    ``sqrt(max)``: 1e19 in float32, 1e154 in float64) are first scaled down, per query, by a
    power of two: exact, so the order of the faces is kept, where overflowing distances would
    all tie at infinity.
    """
    points, vertices = jax.lax.stop_gradient(points), jax.lax.stop_gradient(vertices)
    dtype = points.dtype
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    face_index = jnp.arange(faces.shape[0], dtype=faces.dtype)
    inf = jnp.asarray(jnp.inf, dtype)
    itemsize = jnp.dtype(dtype).itemsize
    block = query_block_size(points.shape[0], faces.shape[0] * 3 * itemsize * 30)
    # Per query, the power of two 2^-k that keeps |x|, |vertex|, their differences and the
    # squared distances finite: k = 0 (no change at all) below 2^(maxexp / 2 - 2).
    largest_vertex = jnp.max(jnp.where(valid[:, None, None], jnp.abs(jnp.stack([a, b, c], axis=1)), 0))
    safe_exponent = jnp.finfo(dtype).maxexp // 2 - 2

    def block_nearest(p):
        _, exponent = jnp.frexp(jnp.max(jnp.abs(p), axis=-1) / 2 + largest_vertex / 2)
        shrink = jnp.maximum(exponent + 1 - safe_exponent, 0)[:, None, None]
        scaled = [jnp.ldexp(v[None], -shrink) for v in (a, b, c)]
        d2, first, second = face_features(jnp.ldexp(p[:, None, :], -shrink), *scaled, faces, face_index)
        nearest = jnp.argmin(jnp.where(valid, d2, inf), axis=-1)[:, None]
        same = (first == jnp.take_along_axis(first, nearest, -1)) & (second == jnp.take_along_axis(second, nearest, -1))
        return jnp.argmax(same & valid, axis=-1).astype(jnp.int32)

    return map_query_blocks(block_nearest, (points,), block_size=block)


def _search_frame(vertices: jax.Array, faces: jax.Array, valid: jax.Array):
    """Centre and power-of-two inverse scale mapping the valid geometry into ``[-1, 1]^3``."""
    dtype = vertices.dtype
    used = jnp.zeros(vertices.shape[0], bool).at[faces].max(jnp.broadcast_to(valid[:, None], faces.shape))
    inf = jnp.asarray(jnp.inf, dtype)
    low = jnp.min(jnp.where(used[:, None], vertices, inf), axis=0)
    high = jnp.max(jnp.where(used[:, None], vertices, -inf), axis=0)
    # Halves first: ``high - low`` overflows for coordinates of opposite signs near the float max.
    half = jnp.max(high / 2 - low / 2)
    ok = jnp.isfinite(half) & (half > 0)
    one = jnp.ones((), dtype)
    centre = jnp.where(ok, low / 2 + high / 2, 0)
    _, exponent = jnp.frexp(jnp.where(ok, half, one))
    inv_scale = jnp.ldexp(one, -exponent)
    return used, centre, inv_scale


def _nearest_faces_warp(points, vertices, faces, valid, max_distance, bvh) -> jax.Array:
    from warp_ffi.shrinkwrap import nearest_valid_faces

    from ..query.bvh import checked_live_handle

    points, vertices = jax.lax.stop_gradient(points), jax.lax.stop_gradient(vertices)
    dtype = vertices.dtype
    if bvh is None:
        used, centre, inv_scale = _search_frame(vertices, faces, valid)
        # Invalid faces collapse onto a vertex of a valid face: the float32 BVH then bounds only
        # valid geometry (and never sees their non-finite coordinates).
        anchor = faces[jnp.argmax(valid), 0]
        search_faces = jnp.where(valid[:, None], faces, anchor)
        search_vertices = jnp.where(used[:, None], (vertices - centre) * inv_scale, jnp.zeros((), dtype)).astype(jnp.float32)
        mesh = search_vertices
    else:
        # The prebuilt BVH holds every face in its own (identity) frame; Warp's float32 query
        # skips the degenerate ones, and the exact pass skips the others that are invalid.
        centre, inv_scale = jnp.zeros(3, dtype), jnp.ones((), dtype)
        search_faces, mesh = faces, bvh.mesh_words
        search_vertices = jax.lax.stop_gradient(bvh.vertices).astype(jnp.float32)
        search_vertices = jnp.where(valid[:, None, None], search_vertices[faces], 0)
    search_points = jnp.clip((points - centre) * inv_scale, -_SEARCH_CLIP, _SEARCH_CLIP).astype(jnp.float32)
    extent = jnp.max(jnp.abs(search_vertices))
    gate = _NO_GATE if max_distance is None else jnp.minimum(max_distance * inv_scale, _NO_GATE)
    limits = jnp.stack([extent, jnp.asarray(gate, jnp.float32)])
    # Searching in Morton order lets consecutive queries reuse the same BVH nodes in cache.
    order = jnp.argsort(_morton_codes(search_points / jnp.maximum(extent, jnp.finfo(jnp.float32).tiny)))
    nearest = nearest_valid_faces(
        mesh, points[order], vertices, search_faces.reshape(-1), valid.astype(jnp.int32), search_points[order], inv_scale[None], limits
    )
    if bvh is not None:
        nearest = checked_live_handle(nearest, _NAME)
    return jnp.zeros_like(nearest).at[order].set(nearest)


def _morton_codes(unit_points: jax.Array) -> jax.Array:
    """30-bit Morton codes of points in ``[-1, 1]^3`` (clamped outside)."""
    cells = jnp.clip(jnp.floor((unit_points + 1) * 512), 0, 1023).astype(jnp.uint32)

    def spread(v):
        v = (v | (v << 16)) & jnp.uint32(0x030000FF)
        v = (v | (v << 8)) & jnp.uint32(0x0300F00F)
        v = (v | (v << 4)) & jnp.uint32(0x030C30C3)
        return (v | (v << 2)) & jnp.uint32(0x09249249)

    return spread(cells[:, 0]) | (spread(cells[:, 1]) << 1) | (spread(cells[:, 2]) << 2)


# ---------------------------------------------------------------------------------------------
# The projection, replayed in JAX on the selected faces (this is what is differentiated).


def _projection_field(x, vertices, faces, nearest, fallback, offset, max_distance):
    """``p + offset n - x`` on the selected faces, zero for misses and gated points."""
    hit = nearest >= 0
    # Misses are replayed on a valid face so their (discarded) branch has finite derivatives.
    face = faces[jnp.where(hit, nearest, fallback)]
    a, b, c = vertices[face[..., 0]], vertices[face[..., 1]], vertices[face[..., 2]]
    closest, _ = closest_point_on_triangle(x, a, b, c)
    if max_distance is not None:
        # The gate is configuration, not differentiated.
        hit = hit & (overflow_safe_norm(jax.lax.stop_gradient(x - closest)) < max_distance)
    target = closest + offset * triangle_normal(a, b, c)
    return jnp.where(hit[..., None], target - x, jnp.zeros((), x.dtype))
