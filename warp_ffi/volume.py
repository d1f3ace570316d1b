"""Signed face volumes of a triangle surface on Warp (closed-surface volume energy).

``face_volumes(points, reference_points, triangles, origins)`` returns ``y_0 . (y_1 x y_2) / 6``
per face for the current and the rest surface, ``(B, F)`` each, with ``y = x - o`` for per-design
origins ``o`` (not differentiated); NaN for faces with an out-of-range index or non-finite
coordinates (no gradient). One launch handles both surfaces. The energy sums them in JAX; the
adjoint kernel scatters ``(y_1 x y_2) / 6`` etc. to the face's vertices.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from ._energy import finite3, flat_vectors, kernel_indices, launch
from ._kernels import WARP_SCALAR
from ._kernels import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["face_volumes"]


@wp.func
def _face(points: wp.array(dtype=Any), triangles: wp.array2d(dtype=wp.int32), origin: Any, b: int, f: int, num_points: int):
    """Vertex indices, origin-relative corners and whether the face is valid."""
    i = triangles[f, 0]
    j = triangles[f, 1]
    k = triangles[f, 2]
    valid = wp.min(wp.min(i, j), k) >= 0 and wp.max(wp.max(i, j), k) < num_points
    y0 = origin - origin
    y1 = y0
    y2 = y0
    if valid:
        base = b * num_points
        i += base
        j += base
        k += base
        y0 = points[i] - origin
        y1 = points[j] - origin
        y2 = points[k] - origin
        valid = finite3(y0, y1, y2)
    return valid, i, j, k, y0, y1, y2


@wp.kernel
def _forward_kernel(
    points: wp.array(dtype=Any),
    reference: wp.array(dtype=Any),
    triangles: wp.array2d(dtype=wp.int32),
    origins: wp.array2d(dtype=Any),
    num_points: int,
    offset: int,
    volume: wp.array(dtype=Any),
    reference_volume: wp.array(dtype=Any),
):
    b, t = wp.tid()
    f = t + offset
    num_faces = triangles.shape[0]
    if f >= num_faces:
        return
    out = b * num_faces + f
    sixth = volume.dtype(1.0) / volume.dtype(6.0)
    nan = volume.dtype(wp.nan)
    valid, i, j, k, y0, y1, y2 = _face(points, triangles, origins[b, 0], b, f, num_points)
    volume[out] = nan
    if valid:
        volume[out] = wp.dot(y0, wp.cross(y1, y2)) * sixth
    valid, i, j, k, y0, y1, y2 = _face(reference, triangles, origins[b, 1], b, f, num_points)
    reference_volume[out] = nan
    if valid:
        reference_volume[out] = wp.dot(y0, wp.cross(y1, y2)) * sixth


@wp.func
def _scatter_face(grad: wp.array(dtype=Any), g: Any, i: int, j: int, k: int, y0: Any, y1: Any, y2: Any):
    wp.atomic_add(grad, i, g * wp.cross(y1, y2))
    wp.atomic_add(grad, j, g * wp.cross(y2, y0))
    wp.atomic_add(grad, k, g * wp.cross(y0, y1))


@wp.kernel
def _adjoint_kernel(
    points: wp.array(dtype=Any),
    reference: wp.array(dtype=Any),
    triangles: wp.array2d(dtype=wp.int32),
    origins: wp.array2d(dtype=Any),
    volume_bar: wp.array(dtype=Any),
    reference_volume_bar: wp.array(dtype=Any),
    num_points: int,
    offset: int,
    points_bar: wp.array(dtype=Any),
    reference_bar: wp.array(dtype=Any),
):
    b, t = wp.tid()
    f = t + offset
    num_faces = triangles.shape[0]
    if f >= num_faces:
        return
    out = b * num_faces + f
    sixth = volume_bar.dtype(1.0) / volume_bar.dtype(6.0)
    valid, i, j, k, y0, y1, y2 = _face(points, triangles, origins[b, 0], b, f, num_points)
    if valid:
        _scatter_face(points_bar, volume_bar[out] * sixth, i, j, k, y0, y1, y2)
    valid, i, j, k, y0, y1, y2 = _face(reference, triangles, origins[b, 1], b, f, num_points)
    if valid:
        _scatter_face(reference_bar, reference_volume_bar[out] * sixth, i, j, k, y0, y1, y2)


@functools.cache
def _callables(dtype):
    """``(forward, adjoint)`` JAX callables for one float dtype."""
    scalar = WARP_SCALAR[jnp.dtype(dtype)]
    vectors = wp.array(dtype=wp.types.vector(3, scalar))
    origins_type = wp.array2d(dtype=wp.types.vector(3, scalar))
    reals = wp.array(dtype=scalar)
    faces_type = wp.array2d(dtype=wp.int32)
    forward_kernel = wp.overload(_forward_kernel, [vectors, vectors, faces_type, origins_type, int, int, reals, reals])
    adjoint_kernel = wp.overload(_adjoint_kernel, [vectors, vectors, faces_type, origins_type, reals, reals, int, int, vectors, vectors])

    def forward(points, reference, triangles, origins, volume, reference_volume):
        num_batch = origins.shape[0]
        inputs = [points, reference, triangles, origins, points.shape[0] // num_batch]
        launch(forward_kernel, num_batch, triangles.shape[0], inputs, [volume, reference_volume])

    def adjoint(points, reference, triangles, origins, volume_bar, reference_volume_bar, points_bar, reference_bar):
        num_batch = origins.shape[0]
        inputs = [points, reference, triangles, origins, volume_bar, reference_volume_bar, points.shape[0] // num_batch]
        launch(adjoint_kernel, num_batch, triangles.shape[0], inputs, [points_bar, reference_bar], accumulated=(0, 1))

    forward.__annotations__ = dict(
        points=vectors, reference=vectors, triangles=faces_type, origins=origins_type, volume=reals, reference_volume=reals
    )
    adjoint.__annotations__ = dict(
        points=vectors, reference=vectors, triangles=faces_type, origins=origins_type, volume_bar=reals,
        reference_volume_bar=reals, points_bar=vectors, reference_bar=vectors,
    )  # fmt: skip
    return (
        wp.jax_callable(forward, num_outputs=2, vmap_method="sequential"),
        wp.jax_callable(adjoint, num_outputs=2, vmap_method="sequential"),
    )


# Register both overloads now: a new overload after the module is built forces a rebuild.
for _dtype in WARP_SCALAR:
    _callables(_dtype)


@jax.jit
def face_volumes(points: jax.Array, reference_points: jax.Array, triangles: jax.Array, origins: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Signed volumes ``(B, F)`` of the tetrahedra (origin, face), current and reference.

    ``points`` and ``reference_points`` are ``(B, N, 3)``; ``origins`` ``(B, 2, 3)`` holds each
    design's current and reference origin and receives no gradient. NaN for faces with an
    out-of-range index or non-finite coordinates, which pass no gradient back. Differentiable
    once in reverse mode in both coordinate arrays; ``jit`` and ``vmap`` (sequential)
    compatible. Requires ``B, N, F > 0``.
    """
    num_batch, num_points, _ = points.shape
    indices = kernel_indices(triangles, num_points)
    volume, reference_volume = _volumes(flat_vectors(points), flat_vectors(reference_points), indices, jax.lax.stop_gradient(origins))
    return volume.reshape(num_batch, -1), reference_volume.reshape(num_batch, -1)


@jax.custom_vjp
def _volumes(points, reference, triangles, origins):
    return _volumes_fwd(points, reference, triangles, origins)[0]


def _volumes_fwd(points, reference, triangles, origins):
    forward, _ = _callables(points.dtype)
    size = (origins.shape[0] * triangles.shape[0],)
    outputs = forward(points, reference, triangles, origins, output_dims={"volume": size, "reference_volume": size})
    return tuple(outputs), (points, reference, triangles, origins)


def _volumes_bwd(residuals, cotangents):
    points, reference, triangles, origins = residuals
    _, adjoint = _callables(points.dtype)
    dims = {"points_bar": points.shape[:1], "reference_bar": points.shape[:1]}
    points_bar, reference_bar = adjoint(points, reference, triangles, origins, *cotangents, output_dims=dims)
    return points_bar, reference_bar, None, jnp.zeros_like(origins)


_volumes.defvjp(_volumes_fwd, _volumes_bwd)
