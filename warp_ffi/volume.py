"""Signed face volumes of a triangle surface on Warp (closed-surface volume energy).

``face_volumes(points, reference_points, triangles, origins)`` returns ``y_0 . (y_1 x y_2) / 6``
per face for the current and the rest surface, ``(B, F)`` each, with ``y = x - o`` for per-design
origins ``o`` (not differentiated); NaN for faces with an out-of-range index or non-finite
coordinates (no gradient). One launch handles both surfaces. The energy sums them in JAX; the
adjoint kernel scatters ``(y_1 x y_2) / 6`` etc. to the face's vertices.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax

from . import _energy
from ._energy import Coordinates, PerItem, Topology, finite3
from ._wrap import scalars, vectors
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["face_volumes"]


@wp.func
@no_type_check
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


@wp.func
@no_type_check
def _signed_volume(points: wp.array(dtype=Any), triangles: wp.array2d(dtype=wp.int32), origin: Any, b: int, f: int, num_points: int):
    """``y_0 . (y_1 x y_2) / 6`` of face ``f``, NaN when it is invalid."""
    valid, i, j, k, y0, y1, y2 = _face(points, triangles, origin, b, f, num_points)
    sixth = type(origin[0])(1.0) / type(origin[0])(6.0)
    if valid:
        return wp.dot(y0, wp.cross(y1, y2)) * sixth
    return type(origin[0])(wp.nan)


@wp.func
@no_type_check
def _scatter_volume_gradient(
    grad: wp.array(dtype=Any), points: wp.array(dtype=Any), triangles: wp.array2d(dtype=wp.int32), origin: Any, g: Any, b: int,
    f: int, num_points: int,
):  # fmt: skip
    """Add ``g`` times the gradient of face ``f``'s signed volume to its vertices (none when invalid)."""
    valid, i, j, k, y0, y1, y2 = _face(points, triangles, origin, b, f, num_points)
    if valid:
        g = g * (type(g)(1.0) / type(g)(6.0))
        wp.atomic_add(grad, i, g * wp.cross(y1, y2))
        wp.atomic_add(grad, j, g * wp.cross(y2, y0))
        wp.atomic_add(grad, k, g * wp.cross(y0, y1))


@wp.kernel
@no_type_check
def _forward_kernel(
    points: Coordinates, reference: Coordinates, triangles: Topology, origins: wp.array2d(dtype=Any), num_points: int, offset: int,
    volume: PerItem, reference_volume: PerItem,
):  # fmt: skip
    b, t = wp.tid()
    f = t + offset
    out = b * triangles.shape[0] + f
    volume[out] = _signed_volume(points, triangles, origins[b, 0], b, f, num_points)
    reference_volume[out] = _signed_volume(reference, triangles, origins[b, 1], b, f, num_points)


@wp.kernel
@no_type_check
def _adjoint_kernel(
    points: Coordinates, reference: Coordinates, triangles: Topology, origins: wp.array2d(dtype=Any), volume_bar: PerItem,
    reference_volume_bar: PerItem, num_points: int, offset: int, points_bar: Coordinates, reference_bar: Coordinates,
):  # fmt: skip
    b, t = wp.tid()
    f = t + offset
    out = b * triangles.shape[0] + f
    _scatter_volume_gradient(points_bar, points, triangles, origins[b, 0], volume_bar[out], b, f, num_points)
    _scatter_volume_gradient(reference_bar, reference, triangles, origins[b, 1], reference_volume_bar[out], b, f, num_points)


def _types(s):
    return {name: vectors(s) for name in ("points", "reference", *_energy.GRADIENT_NAMES)} | {
        "origins": vectors(s, ndim=2),
        **{name: scalars(s) for name in ("volume", "reference_volume", "volume_bar", "reference_volume_bar")},
    }


_volumes = _energy.per_item_terms(
    _energy.energy_family(_forward_kernel, _types, outputs=("volume", "reference_volume")),
    _energy.energy_family(_adjoint_kernel, _types, outputs=_energy.GRADIENT_NAMES, accumulate=_energy.GRADIENT_NAMES),
)


@jax.jit
def face_volumes(points: jax.Array, reference_points: jax.Array, triangles: jax.Array, origins: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Signed volumes ``(B, F)`` of the tetrahedra (origin, face), current and reference.

    ``points`` and ``reference_points`` are ``(B, N, 3)``; ``origins`` ``(B, 2, 3)`` holds each
    design's current and reference origin and receives no gradient. NaN for faces with an
    out-of-range index or non-finite coordinates, which pass no gradient back. Differentiable
    once in reverse mode in both coordinate arrays; ``jit`` and ``vmap`` (sequential)
    compatible. Requires ``B, N, F > 0``.
    """
    num_batch = points.shape[0]
    extras = (jax.lax.stop_gradient(origins),)
    volume, reference_volume = _volumes(*_energy.kernel_inputs(points, reference_points, triangles), extras, num_batch, ())
    return volume.reshape(num_batch, -1), reference_volume.reshape(num_batch, -1)
