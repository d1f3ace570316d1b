"""Dense displacement: ``x' = x + w * d``."""

from __future__ import annotations

import jax
from jaxtyping import Array, Bool, Float

from .._dispatch import platform_of, select_implementation
from .._errors import raises_documented_errors
from .._points import apply_point_weights
from .._validate import check_coordinates, check_point_weights, check_same_shape

__all__ = ["displace_points"]


@raises_documented_errors
def displace_points(
    points: Float[Array, "*batch num_points num_dims"],
    displacement: Float[Array, "*batch num_points num_dims"],
    *,
    point_weights: Bool[Array, "*batch num_points"] | Float[Array, "*batch num_points"] | None = None,
    implementation: str | None = None,
) -> Float[Array, "*batch num_points num_dims"]:
    """Apply an aligned dense displacement field to points: ``x'_i = x_i + w_i d_i``.

    Args:
        points: ``(N, D)`` or aligned batched ``(B, N, D)``, float32 or float64, any ``D >= 1``.
        displacement: exactly the shape, dtype and device of ``points`` (never broadcast).
        point_weights: optional ``(N,)`` / ``(B, N)`` weights. Bool weights are a hard mask (a
            masked point is untouched even if its displacement is NaN); float weights must match
            the points dtype and are used as given (signed or above one).
        implementation: ``"jax"`` (also accepted as ``"torch"``) or ``None``. There is no Warp
            backend: ``"warp"`` raises ``KeyError``, as in the reference.

    Returns:
        Displaced points with the shape and dtype of ``points``.

    Raises:
        TypeError: non-float arrays, mismatched dtypes, integer weights.
        ValueError: bad ranks or shapes, mixed batched/unbatched inputs.
        KeyError: unknown ``implementation``.

    Differentiable (any order, forward and reverse mode) in ``points``, ``displacement`` and float
    ``point_weights``; ``jit`` and ``vmap`` compatible.

    Example:
        >>> import jax.numpy as jnp
        >>> from geomjax import displace_points
        >>> points = jnp.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], dtype=jnp.float32)
        >>> displacement = jnp.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]], dtype=jnp.float32)
        >>> displace_points(points, displacement, point_weights=jnp.array([0.0, 0.5, 1.0], dtype=jnp.float32))
        Array([[0. , 0. ],
               [1. , 0.5],
               [2. , 1. ]], dtype=float32)
    """
    points, _ = check_coordinates("points", points)
    displacement = check_same_shape("points", points, "displacement", displacement)
    point_weights = check_point_weights(point_weights, points)
    select_implementation("displace_points", implementation, platform=platform_of(points))
    return _displaced(points, displacement, point_weights)


# One compiled program per shape for eager calls (rather than one per operation of the weight rule).
_displaced = jax.jit(apply_point_weights)
