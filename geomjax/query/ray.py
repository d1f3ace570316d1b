"""First hits of rays on a triangle mesh, with gradients of the hit distance and point."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._blocking import map_query_blocks, query_block_size
from .._dispatch import platform_of, select_implementation
from .._errors import raises_documented_errors
from .._geometry import ray_plane_intersection, ray_triangle_intersection, triangle_normal
from .._sharding import map_local_shards
from .._validate import as_float32, as_float_array, check_bool, check_real_scalar, check_same_shape
from .bvh import MeshBVH, _extent, build_bvh, bvh_vertices32, checked_live_handle, checked_mesh, finite_vertices, queries_in_working_dtype, replayed

__all__ = ["ray_mesh_intersect"]


_NAME = "ray_mesh_intersect"


@raises_documented_errors
def ray_mesh_intersect(
    mesh_vertices: Float[Array, "num_vertices 3"],
    mesh_indices: Int[Array, "num_faces 3"] | Int[Array, " num_indices"],
    ray_origins: Float[Array, "*batch 3"],
    ray_directions: Float[Array, "*batch 3"],
    max_distance: float = 1e8,
    warp_mesh: MeshBVH | None = None,
    return_warp_mesh: bool = False,
    *,
    implementation: str | None = None,
) -> tuple[Bool[Array, "*batch"], Float[Array, "*batch"], Float[Array, "*batch 3"], Int[Array, "*batch"], Float[Array, "*batch 3"]] | tuple:
    """Closest hit of each ray ``origin + t * direction / |direction|`` on a triangle mesh.

    Both sides of a triangle count. Directions need not be normalized: distances are Euclidean
    (along the unit direction). A hit farther than ``max_distance`` is a miss, and so is a zero
    or non-finite direction or a non-finite origin.

    Args:
        mesh_vertices: ``(V, 3)`` float32 or float64, ``V >= 1``, finite (a NaN vertex would
            corrupt results far from it).
        mesh_indices: ``(F, 3)`` or flat ``(3 F,)`` int32/int64 triangle indices in ``[0, V)``,
            ``F >= 1``, on the same device.
        ray_origins: ``(..., 3)`` of any real floating dtype (float16, bfloat16, float32,
            float64; independent of the mesh's), on the device of ``mesh_vertices``. Computed in
            float64 when origins and mesh are float64, else in float32 (as the reference).
        ray_directions: the shape and device of ``ray_origins``, any real floating dtype.
        max_distance: positive finite real.
        warp_mesh: a :class:`~geomjax.MeshBVH` of this mesh (from :func:`~geomjax.build_bvh` or an
            earlier call with ``return_warp_mesh=True``) to skip building a BVH. It is only
            used for the search: hits are replayed on ``mesh_vertices``/``mesh_indices`` (which
            must have its shapes), so pass the geometry it was built or refitted with.
        return_warp_mesh: also return the :class:`~geomjax.MeshBVH` used (built eagerly when
            ``warp_mesh`` is ``None``, which needs concrete mesh arrays).
        implementation: ``"warp"``, ``"jax"`` (also ``"torch"``) or ``None``. ``None`` picks
            Warp on every platform (when warp-lang is installed): a BVH search, with the BVH
            built inside the call when no ``warp_mesh`` is given, so the whole call traces
            under ``jit`` even with traced mesh arrays. ``"jax"`` tests every ray against
            every face (O(rays x faces), a reference for small meshes).

    Returns:
        ``(hit_mask, hit_distance, hit_points, face_ids, hit_normals)`` (plus the MeshBVH when
        ``return_warp_mesh``): bool ``(...)``; distance ``(...)`` (``+inf`` for misses); points
        ``(..., 3)`` (zero for misses); face ids ``(...)`` (``-1`` for misses; int64 when
        ``mesh_indices`` is int64, else int32); unit face normals ``(..., 3)`` following the
        winding, not flipped toward the ray (zero for misses). Distances, points and normals
        have the dtype of ``ray_origins``.

    Differentiable with respect to ``ray_origins``, ``ray_directions`` and ``mesh_vertices``:
    the intersection with the chosen face is replayed in JAX in the input dtype, so the hit
    distance, point and normal move with the ray and with the hit triangle's vertices (the
    choice of face itself has no gradient; misses have zero gradients). Both backends support
    ``jit``, ``vmap`` and reverse and forward mode.

    Float64: the Warp BVH is float32, so the hit face is chosen in float32 and the hit is then
    computed exactly on that face in float64. A ray grazing a shared edge may be assigned either
    neighbour (the hit point is the same up to rounding).

    Raises:
        TypeError: non-float or non-integer arrays, a non-real or ``bool``
            ``max_distance``, a non-bool ``return_warp_mesh``, a ``warp_mesh`` that is not a
            MeshBVH, ``return_warp_mesh`` with traced mesh arrays.
        ValueError: bad shapes, empty meshes, non-finite vertices or indices out of range
            (checked on the host for concrete arrays; traced ones raise at run time through
            ``equinox.error_if``), a non-positive or non-finite ``max_distance``, a ``warp_mesh`` of another shape.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` or ``return_warp_mesh`` without warp-lang.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import icosphere, ray_mesh_intersect
        >>> sphere = icosphere(2)
        >>> origins = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, -3.0], [5.0, 5.0, 0.0]])
        >>> directions = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
        >>> hit, distance, points, faces, normals = ray_mesh_intersect(
        ...     sphere.points, sphere.cells, origins, directions, implementation="jax")
        >>> print(np.asarray(hit), np.round(np.asarray(distance), 3))
        [ True  True False] [ 1.  2. inf]
        >>> print(np.round(np.asarray(normals[:2, 2]), 3))
        [ 0.986 -0.986]
    """
    vertices, faces = checked_mesh(_NAME, mesh_vertices, mesh_indices)
    vertices = finite_vertices(_NAME, vertices)
    origins, vertices, output_dtype = queries_in_working_dtype("ray_origins", ray_origins, vertices, op_name=_NAME)
    directions = as_float_array("ray_directions", as_float32(ray_directions, narrower_only=True))
    directions = check_same_shape("ray_origins", origins, "ray_directions", directions.astype(origins.dtype))
    dtype = origins.dtype
    max_distance = check_real_scalar("max_distance", max_distance, dtype, positive=True)
    return_warp_mesh = check_bool("return_warp_mesh", return_warp_mesh)
    if warp_mesh is not None:
        if not isinstance(warp_mesh, MeshBVH):
            raise TypeError(f"{_NAME}: warp_mesh must be None or a MeshBVH (see build_bvh), got {type(warp_mesh).__name__}")
        if warp_mesh.vertices.shape != vertices.shape or warp_mesh.faces.shape != faces.shape:
            raise ValueError(
                f"{_NAME}: warp_mesh was built for {warp_mesh.vertices.shape[0]} vertices and {warp_mesh.faces.shape[0]} faces, "
                f"got a mesh with {vertices.shape[0]} and {faces.shape[0]}"
            )
    backend = select_implementation(_NAME, implementation, platform=platform_of(vertices))
    if return_warp_mesh and warp_mesh is None:
        warp_mesh = build_bvh(mesh_vertices, mesh_indices)
    index_dtype = jnp.int64 if jnp.dtype(mesh_indices.dtype) == jnp.int64 else jnp.int32

    handle = warp_mesh.mesh_words if warp_mesh is not None else None

    def local(vertices, faces, origins, directions, handle):
        shape = origins.shape[:-1]
        hit, distance, points, hit_faces, normals = _intersect(
            vertices, faces, origins.reshape(-1, 3), directions.reshape(-1, 3), handle, max_distance=max_distance, backend=backend
        )
        return (
            hit.reshape(shape),
            distance.reshape(shape).astype(output_dtype),
            points.reshape(shape + (3,)).astype(output_dtype),
            hit_faces.astype(index_dtype).reshape(shape),
            normals.reshape(shape + (3,)).astype(output_dtype),
        )

    # Rays are independent: sharded rays are cast shard by shard against the whole mesh (an
    # opaque Warp call left to XLA's partitioner gave wrong rows across processes).
    axes = origins.ndim - 1
    result = map_local_shards(local, (vertices, faces, origins, directions, handle), (0, 0, axes, axes, 0), out_axes=axes)
    return (*result, warp_mesh) if return_warp_mesh else result


@functools.partial(jax.jit, static_argnames=("max_distance", "backend"))
def _intersect(vertices, faces, o, d, handle, *, max_distance, backend):
    """Normalised inputs (``(V, 3)``, int32 ``(F, 3)``, ``(N, 3)`` rays, optional mesh words)."""
    if o.shape[0] == 0 or not backend.is_warp:
        hit_faces = _first_hits_brute_force(o, d, vertices, faces, max_distance) if o.shape[0] else jnp.zeros((0,), jnp.int32)
        return _replay(o, d, vertices, faces, hit_faces, max_distance)
    from warp_ffi.bvh import ray_hits

    # The kernel sees no tracer of a derivative (an FFI call has no JVP rule): gradients come
    # from the replay below.
    stopped = [jax.lax.stop_gradient(x) for x in (o, d, vertices)]
    search = handle if handle is not None else (bvh_vertices32(stopped[2]), faces.reshape(-1))
    hit_faces, t, points, normals = ray_hits(search, *stopped, faces, jnp.asarray(max_distance, o.dtype), _extent(stopped[2]))
    if handle is not None:
        hit_faces = checked_live_handle(hit_faces, _NAME)
    hit = hit_faces >= 0
    values = (jnp.where(hit, t, jnp.inf), points, normals)

    def geometry(o, d, vertices, faces, hit_faces):
        _, t, points, _, normals = _replay(o, d, vertices, faces, hit_faces, max_distance)
        return t, points, normals

    t, points, normals = replayed(geometry, (o, d, vertices), (faces, hit_faces), values)
    return hit, t, points, hit_faces, normals


def _unit_directions(d: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``d / |d|`` (scaled first, so tiny and huge directions normalise exactly) and ``|d| > 0``."""
    largest = jnp.max(jnp.abs(d), axis=-1, keepdims=True)
    usable = (largest > 0) & jnp.all(jnp.isfinite(d), axis=-1, keepdims=True)
    one = jnp.ones((), d.dtype)
    scaled = d / jnp.where(usable, largest, one)
    norm = jnp.sqrt(jnp.where(usable, jnp.sum(scaled * scaled, axis=-1, keepdims=True), one))
    return jnp.where(usable, scaled / norm, 0), usable[..., 0]


def _replay(o, d, vertices, faces, hit_faces, max_distance):
    """Hit distance, point and normal of each ray on its chosen face, differentiably."""
    unit, usable = _unit_directions(d)
    tri = vertices[faces[jnp.maximum(hit_faces, 0)]]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    t, _, valid = ray_plane_intersection(o, unit, a, b, c)
    # Rounding may put a BVH-chosen hit a hair behind the origin: it is a hit at distance 0.
    hit = (hit_faces >= 0) & usable & valid & (t <= max_distance) & jnp.all(jnp.isfinite(o), axis=-1)
    t = jnp.where(hit, jnp.maximum(t, 0), jnp.inf)
    points = jnp.where(hit[:, None], o + jnp.where(hit, t, 0)[:, None] * unit, 0)
    normals = jnp.where(hit[:, None], triangle_normal(a, b, c), 0)
    return hit, t, points, jnp.where(hit, hit_faces, -1), normals


@jax.jit
def _first_hits_brute_force(o, d, vertices, faces, max_distance):
    """First-hit face of each ray over all faces (ties to the lowest index), pure JAX."""
    o, d, vertices = (jax.lax.stop_gradient(x) for x in (o, d, vertices))
    unit, usable = _unit_directions(d)
    tri = vertices[faces]

    def first_hit(ray):
        origin, direction = ray[:, :3], ray[:, 3:]
        t, _, _ = ray_triangle_intersection(origin[:, None], direction[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
        best = jnp.argmin(t, axis=1)
        best_t = jnp.take_along_axis(t, best[:, None], axis=1)[:, 0]
        return jnp.where(best_t <= max_distance, best, -1).astype(jnp.int32)

    block = query_block_size(o.shape[0], faces.shape[0] * 40 * jnp.dtype(o.dtype).itemsize)
    hits = map_query_blocks(first_hit, (jnp.concatenate([o, unit], axis=-1),), block_size=block)
    return jnp.where(usable, hits, -1)
