"""Farthest-point sampling: a well-spread subset of a point set, greedily."""

from __future__ import annotations

import functools
import numbers

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._errors import raises_documented_errors
from .._points import add_batch_axis, remove_batch_axis
from .._validate import check_coordinates, check_integer, widened_to_float32

__all__ = ["farthest_point_sampling"]


@raises_documented_errors
def farthest_point_sampling(points: Float[Array, "*batch num_points num_dims"], num_samples: int, *, start_index: int = 0) -> Int[Array, "*batch num_samples"]:
    """Indices of ``num_samples`` points chosen greedily, each the farthest from those before.

    Sample 0 is ``start_index``; sample ``k`` is the point maximising the Euclidean distance to
    its nearest earlier sample (ties: the lowest index). The result is deterministic, holds
    distinct indices (coincident points are taken only once every other point is), and is a
    2-approximation of the best k-center covering. Gather the points with
    ``points[indices]`` (``jnp.take_along_axis(points, indices[..., None], axis=-2)`` for a
    batch). O(N K) work in a ``lax.fori_loop`` keeping one running distance per point.

    Args:
        points: ``(N, D)`` or batched ``(B, N, D)`` of any real floating dtype, finite (NaN
            coordinates give an unspecified order). float16, bfloat16 and float8 points are
            compared in float32 (as the reference does), float32 and float64 in their own dtype.
        num_samples: integer ``K`` with ``0 <= K <= N``.
        start_index: integer in ``[0, N)`` (when ``K > 0``), the first sample of every batch.

    Returns:
        ``(K,)`` or ``(B, K)`` int32 indices into the point axis.

    Raises:
        TypeError: non-floating points, a non-integer (or bool) ``num_samples`` or ``start_index``.
        ValueError: points not ``(N, D)`` / ``(B, N, D)``, ``K`` negative or above ``N``, a
            ``start_index`` outside ``[0, N)``.

    Works under ``jit`` (``num_samples`` and ``start_index`` are static) and ``vmap``. Not
    differentiable (the output is integer).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import farthest_point_sampling
        >>> points = jnp.array([[0.0, 0.0], [0.1, 0.0], [1.0, 0.0], [1.0, 1.0], [0.5, 0.5]])
        >>> print(np.asarray(farthest_point_sampling(points, 3)))
        [0 3 2]
    """
    # float16, bfloat16, float8: distances in float32, as the reference computes them (the
    # conversion is exact, so the order is the one of the input's values).
    points, batched = check_coordinates("points", widened_to_float32(points))
    num_samples = check_integer("num_samples", num_samples, minimum=0)
    if isinstance(start_index, (bool, np.bool_)) or not isinstance(start_index, numbers.Integral):
        raise TypeError(f"start_index must be an integer, got {type(start_index).__name__}")
    start_index = int(start_index)
    num_points = points.shape[-2]
    if num_samples > num_points:
        raise ValueError(f"num_samples must be at most the number of points {num_points}, got {num_samples}")
    if num_samples > 0 and not 0 <= start_index < num_points:
        raise ValueError(f"start_index must lie in [0, {num_points}), got {start_index}")
    x = add_batch_axis(points, batched)
    if num_samples == 0:
        return remove_batch_axis(jnp.zeros(x.shape[:1] + (0,), jnp.int32), batched)
    return remove_batch_axis(_farthest_points(x, num_samples, start_index), batched)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _farthest_points(points: jax.Array, num_samples: int, start_index: int) -> jax.Array:
    points = jax.lax.stop_gradient(points)

    def one_set(x):
        num_points = x.shape[0]
        # Chosen points get distance -1, so they never win the argmax again.
        distance = jnp.full((num_points,), jnp.inf, x.dtype).at[start_index].set(-1)
        chosen = jnp.zeros((num_samples,), jnp.int32).at[0].set(start_index)

        def step(k, state):
            chosen, distance = state
            offset = x - x[chosen[k - 1]]
            distance = jnp.minimum(distance, jnp.sum(offset * offset, axis=-1))
            pick = jnp.argmax(distance).astype(jnp.int32)
            return chosen.at[k].set(pick), distance.at[pick].set(-1)

        chosen, _ = jax.lax.fori_loop(1, num_samples, step, (chosen, distance))
        return chosen

    return jax.vmap(one_set)(points)
