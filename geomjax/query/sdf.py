"""Signed distance to a triangle mesh, differentiable in the query points and the vertices."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._blocking import map_query_blocks, query_block_size
from .._dispatch import platform_of, select_implementation
from .._errors import raises_documented_errors
from .._geometry import closest_point_on_triangle, overflow_safe_norm, winding_numbers
from .._sharding import map_local_shards
from .._validate import check_bool, check_real_scalar
from .bvh import (
    _extent,
    bvh_vertices32,
    checked_mesh,
    closest_faces_brute_force,
    consistently_oriented_faces,
    finite_vertices,
    queries_in_working_dtype,
    replayed,
    sliver_faces,
)

__all__ = ["signed_distance_field"]


_NAME = "signed_distance_field"
NORMAL_SIGN_EPSILON = 1e-3  # Warp's: faces within 1e-3 average edge lengths of the nearest share its sign


@raises_documented_errors
def signed_distance_field(
    mesh_vertices: Float[Array, "num_vertices 3"],
    mesh_indices: Int[Array, "num_faces 3"] | Int[Array, " num_indices"],
    input_points: Float[Array, "*batch 3"],
    max_dist: float = 1e8,
    use_sign_winding_number: bool = False,
    *,
    implementation: str | None = None,
) -> tuple[Float[Array, "*batch"], Float[Array, "*batch 3"], Int[Array, "*batch"]]:
    """Signed distance from each point to a triangle mesh: negative inside, positive outside.

    The value is ``sign * |p - q|`` with ``q`` the closest point of the mesh. Faces that Warp
    treats as slivers (``|AB x AC| < 1e-6 (|AB|^2 + |AC|^2 + |BC|^2)``) are ignored, as in the
    reference. The sign comes from

    * the closest feature's normal (default): the angle-weighted pseudo-normal of the faces
      sharing the closest point (within ``1e-3`` average edge lengths, Warp's tolerance and
      weights), so a closest point on an edge or a vertex is classified correctly; exact for a
      watertight, consistently oriented mesh. Unlike the reference (Warp's query), faces that
      are merely about as far away elsewhere on the mesh do not take part, so points equidistant
      from distant parts of the surface (a sphere's centre, the middle of a thin slab) keep the
      right sign;
    * or, with ``use_sign_winding_number``, the generalized winding number (inside where it
      exceeds 0.5), computed on the mesh with its face orientations made consistent first
      (:func:`~geomjax.query.bvh.consistently_oriented_faces`, majority orientation per
      connected piece). This classifies points correctly on open meshes (holes) and on meshes
      with some faces flipped, where the winding number of the raw faces (what other libraries
      use) is wrong near every flipped face. The orientation repair runs on the host (NumPy,
      through ``jax.pure_callback`` under ``jit``): about 0.2 s per call for 80,000 faces.

    Args:
        mesh_vertices: ``(V, 3)`` float32 or float64, ``V >= 1``, finite (a NaN vertex would
            corrupt results far from it).
        mesh_indices: ``(F, 3)`` or flat ``(3 F,)`` int32/int64 indices in ``[0, V)``,
            ``F >= 1``, same device.
        input_points: ``(..., 3)`` queries of any real floating dtype (float16, bfloat16, float32,
            float64; independent of the mesh's), on the device of ``mesh_vertices``. Computed in
            float64 when queries and mesh are float64, else in float32 (as the reference); the
            distances and closest points have the queries' dtype.
        max_dist: positive finite real: points with no face strictly closer get NaN.
        use_sign_winding_number: bool, see above.
        implementation: ``"warp"``, ``"jax"`` (also ``"torch"``) or ``None``. ``None`` picks
            Warp on every platform (when warp-lang is installed): search structures built inside
            the call (so it traces under ``jit`` even with traced mesh arrays), an oriented-box
            tree for the closest face and the normal sign, Warp's ``wp.Mesh`` winding-number
            query for winding signs (Barnes-Hut, accuracy 2.0). ``"jax"``
            measures every point against every face and sums exact winding numbers (a reference
            for small meshes).

    Returns:
        ``(sdf, hit_points, hit_faces)``: ``(...)`` signed distances, ``(..., 3)`` closest
        points and ``(...)`` face ids (int64 when ``mesh_indices`` is int64, else int32);
        NaN, NaN and ``-1`` where no face is within ``max_dist`` (or the point is not finite).

    Differentiable with respect to ``input_points`` (``sign * (p - q) / |p - q|``) and
    ``mesh_vertices`` (through the closest point on the chosen face, replayed in JAX in the input
    dtype, as in shrinkwrap); the face choice and the sign have no gradient. At a point exactly
    on the surface the distance is not differentiable and the gradient is zero. Supports
    ``jit``, ``vmap`` and reverse and forward mode.

    Float64: the Warp search is float32; the nearest face is then refined exactly in float64 (every
    face within the float32 answer's distance is measured again in float64), while the sign of
    points within float32 rounding of the surface (where the distance is ~0) comes from float32.

    Sharding: see the README's "Sharding"; each device measures its own ``input_points``
    against the whole (replicated) mesh; with winding signs every device repairs the face
    orientations itself (host callback).

    Raises:
        TypeError: non-float or non-integer arrays, a non-real or ``bool``
            ``max_dist``, a non-bool ``use_sign_winding_number``.
        ValueError: bad shapes, empty meshes, non-finite vertices or indices out of range
            (checked on the host for concrete arrays; traced ones raise at run time through
            ``equinox.error_if``), a non-positive or non-finite ``max_dist``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import icosphere, signed_distance_field
        >>> sphere = icosphere(3)
        >>> points = jnp.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.5, 0.0]])
        >>> sdf, closest, faces = signed_distance_field(sphere.points, sphere.cells, points, implementation="jax")
        >>> print(np.round(np.asarray(sdf), 3))
        [-0.995  1.    -0.498]
        >>> print(np.round(np.asarray(closest[1]), 3))
        [1. 0. 0.]
    """
    vertices, faces = checked_mesh(_NAME, mesh_vertices, mesh_indices)
    vertices = finite_vertices(_NAME, vertices)
    points, vertices, output_dtype = queries_in_working_dtype("input_points", input_points, vertices, op_name=_NAME)
    dtype = points.dtype
    max_dist = check_real_scalar("max_dist", max_dist, dtype, positive=True)
    winding = check_bool("use_sign_winding_number", use_sign_winding_number)
    backend = select_implementation(_NAME, implementation, platform=platform_of(vertices))
    index_dtype = jnp.int64 if jnp.dtype(mesh_indices.dtype) == jnp.int64 else jnp.int32

    def local(vertices, faces, points):
        shape = points.shape[:-1]
        sdf, closest, face_ids = _signed_distance(vertices, faces, points.reshape(-1, 3), max_dist=max_dist, winding=winding, backend=backend)
        return sdf.reshape(shape).astype(output_dtype), closest.reshape(shape + (3,)).astype(output_dtype), face_ids.astype(index_dtype).reshape(shape)

    # Queries are independent: sharded points are measured shard by shard against the whole mesh.
    return map_local_shards(local, (vertices, faces, points), (0, 0, points.ndim - 1), out_axes=points.ndim - 1)


@functools.partial(jax.jit, static_argnames=("max_dist", "winding", "backend"))
def _signed_distance(vertices, faces, points, *, max_dist, winding, backend):
    """Normalised inputs (``(V, 3)``, int32 ``(F, 3)``, ``(N, 3)``) -> sdf, closest points, int32 faces."""
    dtype = points.dtype
    if points.shape[0] == 0:
        return _replay(points, vertices, faces, jnp.zeros((0,), jnp.int32), jnp.zeros((0,), dtype), max_dist)
    sign_faces = consistently_oriented_faces(faces) if winding else faces
    if not backend.is_warp:
        face_ids, _ = closest_faces_brute_force(points, vertices, faces, skip_slivers=True)
        if winding:
            sign = _winding_sign_brute_force(points, vertices, sign_faces)
        else:
            sign = _normal_sign_brute_force(points, vertices, faces, face_ids)
        return _replay(points, vertices, faces, face_ids, sign, max_dist)

    from warp_ffi.bvh import point_faces

    # The kernel sees no tracer of a derivative (an FFI call has no JVP rule): gradients come
    # from the replay below.
    stopped_points, stopped_vertices = (jax.lax.stop_gradient(x) for x in (points, vertices))
    face_ids, sign, distance, closest = point_faces(
        (bvh_vertices32(stopped_vertices), sign_faces.reshape(-1)), stopped_points, stopped_vertices, faces,
        jnp.asarray(max_dist, dtype), _extent(stopped_vertices),
        sign_mode="winding" if winding else "normal", exact=dtype == jnp.float64,
        sign_epsilon=_sign_epsilon(stopped_vertices, faces), measure=True,
    )  # fmt: skip
    sign = sign.astype(dtype)
    hit = (face_ids >= 0) & (distance < max_dist)
    nan = jnp.asarray(jnp.nan, dtype)
    values = (jnp.where(hit, sign * distance, nan), jnp.where(hit[:, None], closest, nan))

    def geometry(points, vertices, faces, face_ids, sign):
        sdf, closest, _ = _replay(points, vertices, faces, face_ids, sign, max_dist)
        return sdf, closest

    sdf, closest = replayed(geometry, (points, vertices), (faces, face_ids, sign), values)
    return sdf, closest, jnp.where(hit, face_ids, -1)


def _replay(points, vertices, faces, face_ids, sign, max_dist):
    """Signed distance and closest point on each chosen face (differentiable), gated by ``max_dist``."""
    tri = vertices[faces[jnp.maximum(face_ids, 0)]]
    closest, _ = closest_point_on_triangle(points, tri[:, 0], tri[:, 1], tri[:, 2])
    distance = overflow_safe_norm(points - closest)
    hit = (face_ids >= 0) & (distance < max_dist)
    nan = jnp.asarray(jnp.nan, points.dtype)
    return (jnp.where(hit, sign * distance, nan), jnp.where(hit[:, None], closest, nan), jnp.where(hit, face_ids, -1))


# ---------------------------------------------------------------------------------------------
# Pure-JAX signs (brute force over all faces, for small meshes).


def _block_size(num_points, num_faces, dtype):
    return query_block_size(num_points, num_faces * 64 * jnp.dtype(dtype).itemsize)


def _sign_epsilon(vertices, faces):
    """``1e-3`` average edge lengths (Warp's feature tolerance), not differentiated."""
    p0, p1, p2 = (jax.lax.stop_gradient(vertices)[faces[:, k]] for k in range(3))
    lengths = jnp.linalg.norm(p1 - p0, axis=-1) + jnp.linalg.norm(p2 - p0, axis=-1) + jnp.linalg.norm(p2 - p1, axis=-1)
    return NORMAL_SIGN_EPSILON * jnp.sum(lengths) / (3 * faces.shape[0])


@jax.jit
def _normal_sign_brute_force(points, vertices, faces, nearest):
    """Sign from the angle-weighted pseudo-normal of the closest feature, over all faces.

    Every non-sliver face whose closest point lies within ``epsilon`` (:func:`_sign_epsilon`) of
    the nearest face's closest point ``q`` adds its unit normal weighted by the angle of the
    vertex its closest point sits on (within epsilon), by ``pi`` if it sits on an edge, else by
    ``2 pi`` (Warp's weights); the sign is that of ``(p - q) . sum``. The same rule as the Warp
    kernel.
    """
    points, vertices = jax.lax.stop_gradient(points), jax.lax.stop_gradient(vertices)
    p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
    e0, e1, e2 = p1 - p0, p2 - p0, p2 - p1
    eps = _sign_epsilon(vertices, faces)
    ignored = sliver_faces(vertices, faces)

    def unit(v):
        n = jnp.linalg.norm(v, axis=-1, keepdims=True)
        return v / jnp.where(n > 0, n, 1)

    normal = unit(jnp.cross(e0, e1))
    angles = jnp.stack(
        [
            jnp.arccos(jnp.clip(jnp.sum(unit(e0) * unit(e1), -1), -1, 1)),
            jnp.arccos(jnp.clip(jnp.sum(unit(e2) * unit(-e0), -1), -1, 1)),
            jnp.arccos(jnp.clip(jnp.sum(unit(-e1) * unit(-e2), -1), -1, 1)),
        ],
        axis=-1,
    )

    def on_line(c, start, edge):
        offset = c - start
        along = jnp.sum(offset * edge, -1)
        edge2 = jnp.sum(edge * edge, -1)
        return jnp.sum(offset * offset, -1) * edge2 - along * along < eps * eps * edge2

    def block_sign(p, best):
        c, _ = closest_point_on_triangle(p[:, None], p0[None], p1[None], p2[None])
        closest = jnp.take_along_axis(c, jnp.maximum(best, 0)[:, None, None], axis=1)
        near = jnp.stack([jnp.sum((c - x[None]) ** 2, -1) < eps * eps for x in (p0, p1, p2)], axis=-1)
        on_edge = on_line(c, p0[None], e0[None]) | on_line(c, p1[None], e2[None]) | on_line(c, p0[None], e1[None])
        weight = jnp.where(
            near[..., 0], angles[None, :, 0],
            jnp.where(near[..., 1], angles[None, :, 1], jnp.where(near[..., 2], angles[None, :, 2], jnp.where(on_edge, math.pi, 2 * math.pi))),
        )  # fmt: skip
        shares_feature = ~ignored[None] & (jnp.sum((c - closest) ** 2, -1) <= eps * eps)
        pseudo_normal = jnp.einsum("mf,fd->md", jnp.where(shares_feature, weight, 0), normal)
        return jnp.where(jnp.sum(pseudo_normal * (p - closest[:, 0]), -1) > 0, 1.0, -1.0).astype(p.dtype)

    block = _block_size(points.shape[0], faces.shape[0], points.dtype)
    return map_query_blocks(block_sign, (points, nearest), block_size=block)


@jax.jit
def _winding_sign_brute_force(points, vertices, faces):
    """``-1`` where the exact generalized winding number exceeds 0.5, else ``+1``.

    Solid angles by Van Oosterom and Strackee: ``tan(omega / 2) = det(a, b, c) / (|a||b||c| +
    (a.b)|c| + (b.c)|a| + (c.a)|b|)`` with ``a, b, c`` the vertices relative to the point.
    """
    points, vertices = jax.lax.stop_gradient(points), jax.lax.stop_gradient(vertices)
    tri = vertices[faces]

    def block_sign(p):
        w = winding_numbers(p, tri)
        return jnp.where(w > 0.5, -1.0, 1.0).astype(p.dtype)

    block = _block_size(points.shape[0], faces.shape[0], points.dtype)
    return map_query_blocks(block_sign, (points,), block_size=block)
