"""Farthest-point sampling: a well-spread subset of a point set, greedily."""

from __future__ import annotations

import functools
import numbers

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._dispatch import platform_of, select_implementation
from .._errors import raises_documented_errors, runtime_check
from .._points import add_batch_axis, remove_batch_axis
from .._sharding import map_local_shards
from .._validate import as_float32, check_coordinates, check_integer, is_array

__all__ = ["farthest_point_sampling"]


_NAME = "farthest_point_sampling"


@raises_documented_errors
def farthest_point_sampling(
    points: Float[Array, "*batch num_points num_dims"],
    num_samples: int,
    random_start: bool | jax.Array = False,
    implementation: str | None = None,
    *,
    start_index: int | Int[Array, "*batch"] | None = None,
) -> Int[Array, "*batch num_samples"]:
    """Indices of ``num_samples`` points chosen greedily, each the farthest from those before.

    Sample 0 is the start (index 0, ``start_index``, or a random index per cloud); sample ``k``
    is the point maximising the Euclidean distance to its nearest earlier sample (ties: the
    lowest index). Distances are computed in float32 whatever the input dtype, as the reference
    does (so the order is the reference's): each squared coordinate difference rounded, summed in
    coordinate order (no fused multiply-adds). The result holds distinct indices (coincident points
    are taken only once every other point is) and is a 2-approximation of the best k-center
    covering. Gather the points with ``points[indices]`` (``jnp.take_along_axis(points,
    indices[..., None], axis=-2)`` for a batch). O(N K) work in a ``lax.fori_loop`` keeping one
    running distance per point.

    Args:
        points: ``(N, D)`` or batched ``(B, N, D)`` of any real floating dtype (float16, bfloat16,
            float8, float32, float64), finite (NaN coordinates give an unspecified order).
        num_samples: integer ``K`` with ``0 <= K <= N``.
        random_start: ``False`` (start at ``start_index``, default 0), or a ``jax.random`` key:
            each cloud starts at an index drawn uniformly from ``[0, N)`` with it. ``True`` is a
            ``ValueError``: JAX has no global generator (torch_bridge draws from torch's, as the
            reference does).
        implementation: ``None``, ``"jax"`` or ``"torch"`` (the same JAX path). ``"warp"`` is a
            ``ValueError``: there is no Warp kernel (the reference's runs on CUDA only).
        start_index: the first sample, an integer in ``[0, N)`` for every cloud or an integer
            array ``()`` / ``(B,)`` (one per cloud, may be traced); ``None`` means 0. Not with a
            ``random_start`` key.

    Returns:
        ``(K,)`` or ``(B, K)`` int32 indices into the point axis (torch_bridge: int64).

    Raises:
        TypeError: non-floating points; a non-integer (or bool) ``num_samples`` or
            ``start_index``; a ``random_start`` that is neither a bool nor a key.
        ValueError: points not ``(N, D)`` / ``(B, N, D)``; ``K`` negative or above ``N``; a
            ``start_index`` outside ``[0, N)`` (checked when it runs, if traced) or of the wrong
            shape; ``random_start=True``; a key together with ``start_index``;
            ``implementation="warp"``.
        KeyError: an unknown ``implementation``.

    Works under ``jit`` (``num_samples`` static; ``start_index`` and the key may be traced) and
    ``vmap``. Not differentiable (the output is integer).

    Example:
        >>> import jax, jax.numpy as jnp, numpy as np
        >>> from geomjax import farthest_point_sampling
        >>> points = jnp.array([[0.0, 0.0], [0.1, 0.0], [1.0, 0.0], [1.0, 1.0], [0.5, 0.5]])
        >>> print(np.asarray(farthest_point_sampling(points, 3)))
        [0 3 2]
        >>> farthest_point_sampling(points, 3, random_start=jax.random.key(0)).shape
        (3,)
    """
    if implementation == "warp":
        raise ValueError(
            f"{_NAME}: implementation='warp' has no kernel in geomjax (the reference's Warp kernel runs on CUDA only); use implementation='jax' or None"
        )
    # Distances in float32 for every dtype, as the reference computes them (exact for float16,
    # bfloat16 and float8; float64 coordinates are rounded first).
    points, batched = check_coordinates("points", as_float32(points))
    select_implementation(_NAME, implementation, platform=platform_of(points))  # KeyError for unknown names
    num_samples = check_integer("num_samples", num_samples, minimum=0)
    num_points = points.shape[-2]
    if num_samples > num_points:
        raise ValueError(f"num_samples must be at most the number of points {num_points}, got {num_samples}")
    x = add_batch_axis(points, batched)
    start = _start_indices(random_start, start_index, x.shape[0], num_points, batched, check_range=num_samples > 0)
    if num_samples == 0:
        return remove_batch_axis(jnp.zeros(x.shape[:1] + (0,), jnp.int32), batched)
    # A split batch of clouds runs shard by shard (each cloud's loop is its own).
    chosen = map_local_shards(lambda x, start: _farthest_points(x, num_samples, start), (x, start), (1, 1), out_axes=1)
    return remove_batch_axis(chosen, batched)


def _start_indices(random_start, start_index, num_clouds: int, num_points: int, batched: bool, *, check_range: bool) -> jax.Array:
    """The ``(B,)`` int32 first sample of every cloud."""
    if isinstance(random_start, (bool, np.bool_)):
        if random_start:
            raise ValueError(f"{_NAME}: random_start=True needs a generator, and JAX has no global one: pass a jax.random key as random_start (or start_index)")
        key = None
    elif is_array(random_start) and jax.dtypes.issubdtype(random_start.dtype, jax.dtypes.prng_key):
        key = random_start
    elif is_array(random_start) and random_start.dtype == jnp.uint32 and random_start.shape == (2,):
        key = jax.random.wrap_key_data(random_start)  # a raw jax.random.PRNGKey
    else:
        raise TypeError(f"{_NAME}: random_start must be a bool or a jax.random key, got {type(random_start).__name__}")
    if key is not None:
        if start_index is not None:
            raise ValueError(f"{_NAME}: give random_start (a key) or start_index, not both")
        return jax.random.randint(key, (num_clouds,), 0, max(num_points, 1), dtype=jnp.int32)
    if start_index is None:
        return jnp.zeros((num_clouds,), jnp.int32)
    if is_array(start_index):
        if not jnp.issubdtype(start_index.dtype, jnp.integer):
            raise TypeError(f"start_index must be an integer or an integer array, got {jnp.dtype(start_index.dtype)}")
        if start_index.shape not in ((), (num_clouds,) if batched else ()):
            raise ValueError(f"start_index must be an integer array of shape () or (B,) = ({num_clouds},), got {tuple(start_index.shape)}")
        start = jnp.broadcast_to(start_index.astype(jnp.int32), (num_clouds,))
    else:
        if isinstance(start_index, (bool, np.bool_)) or not isinstance(start_index, numbers.Integral):
            raise TypeError(f"start_index must be an integer, got {type(start_index).__name__}")
        if check_range and not 0 <= int(start_index) < num_points:
            raise ValueError(f"start_index must lie in [0, {num_points}), got {int(start_index)}")
        return jnp.full((num_clouds,), int(start_index), jnp.int32)
    if not check_range:
        return start
    return runtime_check(start, (start < 0) | (start >= num_points), f"start_index must lie in [0, {num_points})")


def farthest_point_order(points: np.ndarray, num_samples: int, device: jax.Device) -> jax.Array:
    """:func:`farthest_point_sampling`'s ``(1, K)`` indices from index 0 for host points ``(N, D)``
    (finite, ``1 <= K <= N``: unchecked), computed on ``device`` without waiting: XLA runs the
    loop while the caller goes on (the public op blocks, to raise its runtime errors typed)."""
    cloud = jax.device_put(np.asarray(points, np.float32)[None], device)
    return _farthest_points(cloud, num_samples, np.zeros(1, np.int32))


@functools.partial(jax.jit, static_argnums=(1,))
def _farthest_points(points: jax.Array, num_samples: int, start: jax.Array) -> jax.Array:
    points = jax.lax.stop_gradient(points)

    def one_set(x, start_index):
        num_points, num_dims = x.shape
        # Coordinates as rows (D, N): the update below is then elementwise over N, which XLA's
        # CPU loops vectorise (a reduction over the short last axis of (N, D) they do not).
        rows = x.T
        index = jnp.arange(num_points, dtype=jnp.int32)
        # Chosen points get distance -1, so they never win the argmax again.
        distance = jnp.full((num_points,), jnp.inf, x.dtype).at[start_index].set(-1)
        chosen = jnp.zeros((num_samples,), jnp.int32).at[0].set(start_index)

        def step(k, state):
            chosen, distance = state
            offset = rows - x[chosen[k - 1]][:, None]
            # max(square, 0) (a no-op) keeps XLA from fusing a product into the sum: each square
            # is rounded and the sum runs in coordinate order, as NumPy rounds it.
            squares = jnp.maximum(offset * offset, 0)
            distance = jnp.minimum(distance, functools.reduce(jnp.add, [squares[d] for d in range(num_dims)]))
            # argmax as two plain reductions (XLA's CPU argmax costs several times more): the
            # first index of the largest distance, or of the first NaN, as argmax returns.
            largest = jnp.max(distance)
            pick = jnp.min(jnp.where((distance == largest) | jnp.isnan(distance), index, num_points))
            return chosen.at[k].set(pick), distance.at[pick].set(-1)

        chosen, _ = jax.lax.fori_loop(1, num_samples, step, (chosen, distance))
        return chosen

    return jax.vmap(one_set)(points, start)
