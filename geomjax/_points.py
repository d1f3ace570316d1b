"""Batch normalisation and point weighting shared by the deformation ops.

Every deformation computes a displacement field ``u`` on ``(B, N, D)`` points and returns
``x + w * u``; this module owns the ``(N, D)`` <-> ``(1, N, D)`` convention and the weight rule.
"""

from __future__ import annotations

from typing import overload

import jax
import jax.numpy as jnp


# Optional inputs (weights, masks) pass through as ``None``; arrays keep their type.
@overload
def add_batch_axis(x: jax.Array, batched: bool) -> jax.Array: ...
@overload
def add_batch_axis(x: None, batched: bool) -> None: ...
@overload
def add_batch_axis(x: jax.Array | None, batched: bool) -> jax.Array | None: ...
def add_batch_axis(x: jax.Array | None, batched: bool) -> jax.Array | None:
    """Give unbatched inputs a leading batch axis of one; leave batched ones alone."""
    if x is None or batched:
        return x
    return x[None]


def remove_batch_axis(x: jax.Array, batched: bool) -> jax.Array:
    return x if batched else x[0]


def apply_point_weights(points: jax.Array, field: jax.Array, point_weights: jax.Array | None) -> jax.Array:
    """Return ``points + w * field`` with the reference's weight semantics.

    Bool weights are a hard mask applied with ``where``, so a masked-out point is untouched even if
    its field value is NaN or infinite (and no NaN reaches its gradient). Float weights multiply
    the field as given: signed and larger-than-one values are allowed and are differentiable.
    """
    if point_weights is None:
        return points + field
    if point_weights.dtype == jnp.bool_:
        return points + jnp.where(point_weights[..., None], field, jnp.zeros((), field.dtype))
    return points + point_weights[..., None] * field
