"""Penalty on the enclosed-volume change of an oriented closed triangle surface."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from .._dispatch import Implementation
from .._errors import raises_documented_errors
from .._points import remove_batch_axis
from .._sharding import map_local_shards
from .._validate import check_real_scalar
from . import _simplex as simplex
from ._simplex import Energy, SurfacePoints, Triangles

__all__ = ["closed_surface_volume_energy"]


@raises_documented_errors
def closed_surface_volume_energy(
    points: SurfacePoints,
    reference_points: SurfacePoints,
    triangles: Triangles,
    *,
    target_ratio: float = 1.0,
    reduction: str = "sum",
    implementation: str | None = None,
) -> Energy:
    r"""Penalise the change of the volume enclosed by a closed, consistently oriented surface.

    The signed volume is ``V = sum_f y_0 . (y_1 x y_2) / 6`` over faces ``(i, j, k)`` with
    ``y = x - o``, where ``o`` is the position of vertex ``triangles[0, 0]`` (not differentiated;
    taken separately for the current and the rest surface). For a closed surface the sum does
    not depend on ``o``; the local origin only avoids cancellation for large world coordinates.
    Each batch item's term is::

        (1/2) |V_0| (V / V_0 - q_*)^2,

    so either global winding works. The surface must be one edge-connected, edge-closed,
    consistently oriented component (every edge in two oppositely directed faces); this
    function assumes that contract without checking it, and local face inversions can cancel
    in the signed total.

    Args:
        points: current coordinates ``(N, 3)`` or aligned batched ``(B, N, 3)``, float32/float64.
        reference_points: rest coordinates, exactly the shape, dtype and device of ``points``.
        triangles: non-empty shared ``(F, 3)`` int32/int64 faces. Values are not checked: they
            must be distinct, in-range indices (see below).
        target_ratio: strictly positive target ``q_*`` (finite, not underflowing the dtype).
        reduction: ``"none"`` (a scalar for unbatched input, ``(B,)`` for batched), ``"sum"``
            or ``"mean"`` over the batch.
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``. ``None`` picks
            Warp on CPU when warp-lang is installed, else ``"jax"`` (also on GPU, where it is not yet
            measured). The margin is small on large meshes and reversed on small ones
            (``benchmarks/bench_energy.py``).

    Returns:
        One term per batch item or a scalar according to ``reduction``, dtype of ``points``.

    A batch item's term is NaN, and passes no gradient back, when a face has an out-of-range
    index or non-finite coordinates, or when ``V_0`` is zero or non-finite; with no points it
    is NaN.

    Raises:
        TypeError: non-float coordinates, mismatched dtypes, non-integer ``triangles``, a
            ``bool`` or non-real ``target_ratio``.
        ValueError: bad shapes (``triangles`` not ``(F, 3)``, ``D != 3``), empty ``triangles``,
            a ``target_ratio`` that is not finite, not positive or underflows, an unknown
            ``reduction``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiable in ``points`` and ``reference_points`` (the local origin is not);
    see the README's "Backends and transforms" for what each backend differentiates and
    "Sharding" for designs split over devices (the Warp kernel runs shard by shard).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import closed_surface_volume_energy
        >>> rest = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        >>> triangles = jnp.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> energy = closed_surface_volume_energy(2.0 * rest, rest, triangles, implementation="jax")
        >>> print(np.round(float(energy), 6), np.round(0.5 / 6 * 7.0**2, 6))
        4.083333 4.083333
    """
    points, reference_points, triangles, batched = simplex.check_energy_inputs(
        points, reference_points, triangles, topology_name="triangles", vertices_per_row=(3,)
    )
    simplex.require_three_dims("closed_surface_volume_energy", points)
    if triangles.shape[0] == 0:
        raise ValueError("closed_surface_volume_energy needs at least one triangle, got triangles of shape (0, 3)")
    target_ratio = check_real_scalar("target_ratio", target_ratio, points.dtype, positive=True)
    simplex.check_reduction(reduction)
    backend = simplex.select_energy_backend("closed_surface_volume_energy", implementation, points)

    num_batch, num_points, _ = points.shape
    if num_batch == 0:
        terms = jnp.zeros((0,), points.dtype)
    elif num_points == 0:
        terms = simplex.nan_terms((num_batch,), points.dtype)
    else:
        volume, reference_volume = map_local_shards(
            functools.partial(enclosed_volumes, backend=backend), (points, reference_points, triangles), (1, 1, 0), out_axes=1
        )
        valid = jnp.isfinite(volume) & jnp.isfinite(reference_volume) & (reference_volume != 0)
        volume = jnp.where(valid, volume, 0)
        reference_volume = jnp.where(valid, reference_volume, 1)
        terms = jnp.abs(reference_volume) * jnp.square(volume / reference_volume - target_ratio) / 2
        terms = jnp.where(valid, terms, jnp.nan)
    return simplex.reduce_terms(remove_batch_axis(terms, batched), reduction)


def enclosed_volumes(points: jax.Array, reference_points: jax.Array, triangles: jax.Array, backend: Implementation) -> tuple[jax.Array, jax.Array]:
    """Signed volumes ``(B,)`` enclosed by ``(F, 3)`` faces on ``(B, N, 3)`` current and rest points
    (``N > 0``); NaN when a face is invalid."""
    first = jnp.clip(triangles[0, 0], 0, points.shape[1] - 1)
    origin, reference_origin = jax.lax.stop_gradient((points[:, first], reference_points[:, first]))
    if backend.is_warp:
        from warp_ffi.volume import face_volumes as warp_face_volumes

        origins = jnp.stack([origin, reference_origin], axis=1)
        volumes = backend.run(warp_face_volumes, _face_volume_pair, points, reference_points, triangles, origins)
    else:
        # Not stacked: under a vmap over a split axis with unbatched rest points, JAX 0.12 cannot
        # type the stack of a split and an unsplit array.
        volumes = face_volumes(points, triangles, origin), face_volumes(reference_points, triangles, reference_origin)
    return jnp.sum(volumes[0], axis=-1), jnp.sum(volumes[1], axis=-1)


def _face_volume_pair(points, reference_points, triangles, origins) -> tuple[jax.Array, jax.Array]:
    """Current and rest face volumes about ``origins`` ``(B, 2, 3)``: what the Warp kernel returns."""
    return face_volumes(points, triangles, origins[:, 0]), face_volumes(reference_points, triangles, origins[:, 1])


@jax.jit
def face_volumes(points: jax.Array, triangles: jax.Array, origin: jax.Array) -> jax.Array:
    """``y_0 . (y_1 x y_2) / 6`` per face ``(B, F)`` with ``y = x - origin`` (``origin`` ``(B, 3)``).

    NaN, with no gradient, for faces with an out-of-range index or non-finite coordinates.
    """
    corners, in_range = simplex.gather_vertices(points, [triangles[:, k] for k in range(3)])
    corners = [c - origin[:, None, :] for c in corners]
    valid = in_range & simplex.all_finite(corners)
    zero = jnp.zeros(3, points.dtype)
    y0, y1, y2 = simplex.keep_or(valid, corners, [zero, zero, zero])
    return jnp.where(valid, simplex.dot(y0, simplex.cross(y1, y2)) / 6, jnp.nan)
