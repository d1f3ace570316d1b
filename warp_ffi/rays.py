"""First hits of rays on a triangle mesh (Warp's BVH, ``mesh_query_ray``).

Inputs arrive validated and normalised (no checks here): origins and directions ``(N, 3)`` in
the working dtype with ``N > 0``, the mesh in the working dtype (``(V, 3)`` vertices, ``(F, 3)``
int32 faces) and small parameter arrays; the BVH is a prepared ``wp.Mesh`` (its ``mesh_words``)
or float32 vertices and flat indices to build one inside the call. The search runs on the unit
direction in float32 (first hit, either side) with the maximum distance padded (see ``_search``);
the distance, point and normal on the hit face are then measured in the working dtype and gated
exactly. Nothing here is differentiated: geomjax replays the hit face's geometry in JAX.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax.numpy as jnp

from ._grid import DEAD_MESH_FACE, fill_outputs, is_live_mesh, mesh_id, mesh_in_call
from ._search import face_corners, max_abs, mesh_inputs, padded_radius, search_params, unit_scaled
from ._wrap import CallableFamily, Overloads, launch_in_chunks, scalars, vectors
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["ray_hits"]


@wp.kernel
@no_type_check
def _ray_kernel(
    mesh_words: wp.array(dtype=wp.uint32), origins32: wp.array(dtype=wp.vec3), directions32: wp.array(dtype=wp.vec3),
    origins: wp.array(dtype=Any), directions: wp.array(dtype=Any), vertices: wp.array(dtype=Any), faces: wp.array(dtype=wp.vec3i),
    params32: wp.array(dtype=wp.float32), params: wp.array(dtype=Any), offset: wp.int32, faces_out: wp.array(dtype=wp.int32),
    t_out: wp.array(dtype=Any), points_out: wp.array(dtype=Any), normals_out: wp.array(dtype=Any),
):  # fmt: skip
    """First hit on the float32 BVH, then distance, point and normal on that face in the working dtype."""
    _, t = wp.tid()
    i = t + offset
    o = origins[i]
    zero = points_out.dtype()  # not o - o: a NaN or infinite origin must still miss with zeros
    faces_out[i] = -1
    t_out[i] = zero[0]
    points_out[i] = zero
    normals_out[i] = zero
    o32 = origins32[i]
    d32 = directions32[i]
    if not (wp.isfinite(o) and wp.isfinite(directions[i]) and max_abs(d32) > 0.0):
        return
    max_t = padded_radius(params32[0], params32[1] + max_abs(o32))
    query = wp.mesh_query_ray(mesh_id(mesh_words), o32, unit_scaled(d32), max_t)
    if not query.result:
        return
    unit = unit_scaled(directions[i])
    a, b, c = face_corners(faces, vertices, query.face)
    normal = wp.cross(b - a, c - a)
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
    normals_out[i] = unit_scaled(normal)


_ray = Overloads(
    _ray_kernel,
    lambda s: {"origins": vectors(s), "directions": vectors(s), "vertices": vectors(s), "params": scalars(s),
               "t_out": scalars(s), "points_out": vectors(s), "normals_out": vectors(s)},
)  # fmt: skip

_RAY_OUTPUTS = ("faces_out", "t_out", "points_out", "normals_out")


def _ray_types(scalar, build: bool) -> dict:
    vec3f: wp.array = wp.array(dtype=wp.vec3)
    ints: wp.array = wp.array(dtype=wp.int32)
    head = {"vertices32": vec3f, "faces_flat": ints} if build else {"mesh_words": wp.array(dtype=wp.uint32)}
    inputs = {"origins32": vec3f, "directions32": vec3f, "origins": vectors(scalar), "directions": vectors(scalar),
              "vertices": vectors(scalar), "faces": wp.array(dtype=wp.vec3i), "params32": scalars(wp.float32),
              "params": scalars(scalar)}  # fmt: skip
    outputs = {"faces_out": ints, "t_out": scalars(scalar), "points_out": vectors(scalar), "normals_out": vectors(scalar)}
    return {**head, **inputs, **outputs}


def _ray_search(dtype, build: bool):
    """The body of the search: ``(BVH..., origins32, ..., outputs...)``."""
    kernel = _ray(dtype)

    def run(mesh_words, *args):
        inputs, results = [mesh_words, *args[:8]], list(args[8:])
        launch_in_chunks(kernel, 1, args[0].shape[0], inputs, results)

    def search_prepared(mesh_words, *args):
        if is_live_mesh(mesh_words) is False:  # a forged or freed handle: never dereferenced
            fill_outputs(args[8:], (DEAD_MESH_FACE, 0, 0, 0))
            return
        run(mesh_words, *args)

    if not build:
        return search_prepared

    def search_built(vertices32, faces_flat, *args):
        with mesh_in_call(vertices32, faces_flat, winding_number=False) as (_, words):
            run(words, *args)

    return search_built


# Never captured in a CUDA graph: a prepared mesh's handle is checked on the host on every call,
# a built one is allocated in the call.
_ray_search_family = CallableFamily(_ray_search, _ray_types, outputs=_RAY_OUTPUTS, runs_on_host=True, module=__name__)


def ray_hits(mesh, origins, directions, vertices, faces, max_distance, extent):
    """First hit of each ray: ``(face (int32, -1 = miss), distance, point, unit normal)``.

    ``mesh``: the ``mesh_words`` of a prepared ``wp.Mesh`` (``warp_ffi.host.mesh_handle``), or
    ``(vertices32, faces_flat)`` to build one in the call; ``origins``/``directions`` ``(N, 3)``
    in the working dtype (directions normalised in the kernel; the search runs in float32, the
    hit is measured on the chosen face in the working dtype and gated by ``max_distance``);
    ``vertices``, ``faces``: the geometry ``(V, 3)`` (working dtype) and ``(F, 3)`` int32, in
    the BVH's face order; ``max_distance`` and ``extent`` (``max |vertex coordinate|``) 0-d
    arrays. Misses have zero distance, point and normal. A prepared handle whose mesh is not
    alive (forged, or freed) is not searched: every face is ``DEAD_MESH_FACE``.
    """
    dtype = origins.dtype
    params, params32 = search_params(dtype, max_distance, extent)
    num = origins.shape[0]
    # Scale each direction to unit max-norm first, so a tiny float64 direction survives float32.
    size = jnp.max(jnp.abs(directions), axis=-1, keepdims=True)
    directions32 = (directions / jnp.where(size > 0, size, jnp.ones((), dtype))).astype(jnp.float32)
    call = _ray_search_family(dtype, isinstance(mesh, tuple))
    return call(
        *mesh_inputs(mesh), origins.astype(jnp.float32), directions32, origins, directions, vertices, faces, params32, params,
        shapes=dict.fromkeys(_RAY_OUTPUTS, (num,)),
    )  # fmt: skip
