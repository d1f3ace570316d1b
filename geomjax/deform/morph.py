"""Compact Shepard morphing with the Wendland C2 kernel: ``x' = x + w * u(x)``."""

from __future__ import annotations

import functools
import numbers

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._blocking import map_query_blocks, query_block_size
from .._dispatch import Implementation, platform_of, select_implementation
from .._errors import raises_documented_errors
from .._points import add_batch_axis, apply_point_weights, remove_batch_axis
from .._sharding import map_local_shards
from .._tiny_scale import homogeneous_at_normal_scale, tiny_problem_exponent
from .._validate import (
    as_float_array,
    check_choice,
    check_companion,
    check_coordinates,
    check_point_weights,
    check_real_scalar,
    check_same_device,
    check_same_dtype,
    check_same_shape,
    is_array,
)

__all__ = ["morph_points"]

KERNELS = ("wendland_c2",)


@raises_documented_errors
def morph_points(
    points: Float[Array, "*batch num_points num_dims"],
    control_points: Float[Array, "*batch num_controls num_dims"],
    control_displacements: Float[Array, "*batch num_controls num_dims"],
    *,
    radius: float | Float[Array, ""] | Float[Array, "*batch num_controls"],
    point_weights: Bool[Array, "*batch num_points"] | Float[Array, "*batch num_points"] | None = None,
    kernel: str = "wendland_c2",
    implementation: str | None = None,
) -> Float[Array, "*batch num_points num_dims"]:
    r"""Morph points with sparse control displacements blended by compact Shepard weights.

    For a query ``x``, control ``c_j`` with radius ``r_j`` and displacement ``d_j``, let
    ``q_j = |x - c_j| / r_j``, ``phi(q) = (1 - q)^4 (4 q + 1)`` (Wendland C2) and
    ``a_j = phi(q_j) / q_j^2`` for ``0 < q_j < 1`` (zero otherwise). A stationary background of
    weight one blends toward zero::

        u(x) = sum_j a_j d_j / (1 + sum_j a_j),      x' = x + w * u(x).

    The field is zero where no support is active and interpolates the controls: at an exact
    coincidence (every component of ``(x - c_j) / r_j`` is zero) ``u`` is the mean displacement
    of all coincident controls, overriding the others. The quotient is evaluated in a scaled
    form relative to the nearest active control (``u = d_ref + correction``), with a hypot-like
    norm and non-finite differences treated as outside the support, so values and gradients
    stay finite arbitrarily close to a control (e.g. at ``1e-30 * r`` in float64). A design
    whose lengths (points, controls, displacements, radii) are all tiny, down to subnormal
    radii such as ``1e-310``, is evaluated at a normal scale by exact powers of two (the morph is
    homogeneous in its lengths), so it keeps its values and gradients although XLA flushes
    subnormal numbers to zero.

    Args:
        points: ``(N, D)`` or aligned batched ``(B, N, D)``, float32 or float64, ``D >= 1``.
        control_points: ``(C, D)`` / ``(B, C, D)`` control locations (same rank, batch, ``D``,
            dtype and device as ``points``; never broadcast). ``C = 0`` gives the identity.
        control_displacements: displacement vectors (not destinations), exactly the shape,
            dtype and device of ``control_points``.
        radius: support radius. A Python real scalar (finite, positive, representable and not
            below ``tiny * eps`` of the dtype; the value check is skipped when ``C = 0``), or an
            array of the control dtype: 0-d, per-control ``(C,)`` (shared by a batch) or aligned
            ``(B, C)`` for batched inputs. Array values are not checked (a negative radius acts
            like its absolute value, an infinite one makes every finite point coincide with
            that control); array radii are differentiable.
        point_weights: optional ``(N,)`` / ``(B, N)`` per-point weights multiplying the field:
            bool (hard mask) or float of the points dtype (signed, above one, differentiable).
        kernel: compact radial kernel; only ``"wendland_c2"``.
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``: the registry's
            default (Warp on CPU, whose hash grid visits only nearby controls; JAX on GPU and
            without warp-lang; see "Backends and transforms" in the README).

    Returns:
        Morphed points, same shape and dtype as ``points``.

    Raises:
        TypeError: non-float arrays, mismatched dtypes (including an array ``radius``), integer
            weights, a ``bool`` or non-real scalar ``radius``.
        ValueError: bad ranks or shapes, mixed batched/unbatched inputs, a scalar ``radius``
            that is not finite, not positive, not representable or underflows (only when
            ``C > 0``), a ``radius`` array of the wrong shape, an unknown ``kernel``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiable in ``points``, ``control_points``, ``control_displacements``, an array
    ``radius`` and float ``point_weights``, with the transforms of the README's "Backends and
    transforms". The JAX path never holds more than one block of point/control pairs (1e6 points
    x 1e3 controls, value and gradient, stay under 4 GB).

    Sharding: see the README's "Sharding"; designs and points are computed shard by shard on
    both backends and the result keeps the split of ``points``.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import morph_points
        >>> x = jnp.linspace(0.0, 1.0, 9)
        >>> points = jnp.stack((x, jnp.zeros_like(x)), axis=-1)
        >>> controls = points[jnp.array([0, 8])]
        >>> displacements = jnp.array([[0.0, 0.25], [0.0, -0.15]])
        >>> radii = jnp.array([0.8, 0.8])
        >>> morphed = morph_points(points, controls, displacements, radius=radii, implementation="jax")
        >>> print(np.round(np.asarray(morphed[:, 1]), 4))
        [ 0.25    0.2428  0.2093  0.1255  0.0131 -0.0741 -0.1256 -0.1457 -0.15  ]
    """
    points, batched = check_coordinates("points", points)
    control_points = check_companion("points", points, "control_points", control_points)
    control_displacements = check_same_shape("control_points", control_points, "control_displacements", control_displacements)
    point_weights = check_point_weights(point_weights, points)
    check_choice("kernel", kernel, KERNELS)
    backend = select_implementation("morph_points", implementation, platform=platform_of(points))
    radii = _radius_array(radius, control_points, batched)

    return _morph_points(points, control_points, control_displacements, radii, point_weights, backend=backend, batched=batched)


@functools.partial(jax.jit, static_argnames=("backend", "batched"))
def _morph_points(points, control_points, control_displacements, radii, point_weights, *, backend: Implementation, batched: bool) -> jax.Array:
    """The validated op as one compiled program: an eager call compiles it once per shape, not a
    one-operation program for each step (batch axes, weights)."""
    args = (
        add_batch_axis(points, batched),
        add_batch_axis(control_points, batched),
        add_batch_axis(control_displacements, batched),
        radii,
        add_batch_axis(point_weights, batched),
    )
    out = map_local_shards(functools.partial(_morph, backend=backend), args, (2, 1, 1, 1, 2), out_axes=2)
    return remove_batch_axis(out, batched)


def _morph(x, controls, displacements, radius, weights, *, backend: Implementation) -> jax.Array:
    """Morphed ``(B, N, D)`` points from normalised inputs (independent per design and point)."""
    if controls.shape[-2] == 0 or x.shape[-2] == 0:
        return apply_point_weights(x, jnp.zeros_like(x), weights)
    # The morph is homogeneous in its lengths: a design whose lengths are all tiny (a subnormal
    # radius) runs at a normal scale, since XLA flushes subnormals to zero (k = 0 otherwise).
    exponent = tiny_problem_exponent([x, controls, displacements, radius])

    def morphed(x, controls, displacements, radius, weights):
        field = backend.run(_warp_field, morph_field_jax, x, controls, displacements, radius)
        return apply_point_weights(x, field, weights)

    return homogeneous_at_normal_scale(morphed, (x, controls, displacements, radius), (weights,), exponent)


def _warp_field(points, controls, displacements, radius):
    from warp_ffi.morph import morph_field

    return morph_field(points, controls, displacements, radius)


def _radius_array(radius, control_points: jax.Array, batched: bool) -> jax.Array | None:
    """Validate ``radius`` and return it as a ``(B, C)`` array (``None`` when ``C = 0``)."""
    dtype = control_points.dtype
    num_batch = control_points.shape[0] if batched else 1
    num_controls = control_points.shape[-2]
    shape = (num_batch, num_controls)
    if not is_array(radius):
        if num_controls == 0:
            # The scalar is unused without controls: only its type is checked, as in the reference.
            if isinstance(radius, (bool, np.bool_)) or not isinstance(radius, numbers.Real):
                raise TypeError(f"radius must be a real number or an array, got {type(radius).__name__}")
            return None
        value = check_real_scalar("radius", radius, dtype, positive=True)
        return jnp.full(shape, value, dtype)
    radius = as_float_array("radius", radius)
    check_same_dtype("control_points", control_points, "radius", radius)
    check_same_device("control_points", control_points, "radius", radius)
    if radius.ndim == 0 or (radius.ndim == 1 and radius.shape[0] == num_controls):
        return jnp.broadcast_to(radius, shape)
    if radius.ndim == 2 and batched and radius.shape == shape:
        return radius
    expected = "(), (C,) or (B, C)" if batched else "() or (C,)"
    raise ValueError(f"radius array must have shape {expected} with C={num_controls} controls, got {tuple(radius.shape)}")


# ---------------------------------------------------------------------------------------------
# Pure-JAX implementation (the specification).


@jax.jit
def morph_field_jax(points: jax.Array, controls: jax.Array, displacements: jax.Array, radius: jax.Array) -> jax.Array:
    """The field ``u`` for normalised inputs ``(B, N, D)``, ``(B, C, D)``, ``(B, C, D)``, ``(B, C)``.

    Point/control pairs are evaluated in query blocks (``map_query_blocks``) so that only one
    block of ``(block, C, D)`` temporaries is alive, in the forward and in the backward pass.
    """
    num_batch, num_points, dim = points.shape
    num_controls = controls.shape[1]
    itemsize = jnp.dtype(points.dtype).itemsize
    # About a dozen live (block, C, D) and (block, C) temporaries per query, for each batch item.
    bytes_per_query = num_batch * num_controls * (dim + 1) * itemsize * 12
    block_size = query_block_size(num_points, bytes_per_query)

    def one_design(x, c, d, r):
        return map_query_blocks(lambda xb: _shepard_block(xb, c, d, r), (x,), block_size=block_size)

    return jax.vmap(one_design)(points, controls, displacements, radius)


def wendland_c2(q):
    """``phi(q) = (1 - q)^4 (4 q + 1)``."""
    one_minus = 1 - q
    return one_minus**4 * (4 * q + 1)


@jax.custom_jvp
def _divide(a, r):
    return a / r


@_divide.defjvp
def _divide_jvp(primals, tangents):
    # d(a / r) = (da - (a / r) dr) / r: never forms 1 / r**2, which overflows for tiny radii.
    a, r = primals
    da, dr = tangents
    out = a / r
    return out, (da - out * dr) / r


def normalized_differences(diff: jax.Array, radius: jax.Array) -> jax.Array:
    """``(x - c) / r`` per component, clamped to ``[-1, 1]``; non-finite entries become ``1``.

    Anything non-finite (an infinite coordinate, a zero radius, NaN) is thus outside the support.
    An infinite radius gives exact zeros, i.e. a coincidence, like every backend.
    """
    radius = jnp.broadcast_to(radius, diff.shape)
    bad = ~jnp.isfinite(diff) | ~jnp.isfinite(diff / radius)
    one = jnp.ones((), diff.dtype)
    safe = _divide(jnp.where(bad, 0, diff), jnp.where(bad, one, radius))
    return jnp.where(bad, one, jnp.clip(safe, -one, one))


def normalized_distance(s: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Hypot-like norm of ``s`` over the last axis and the exact-coincidence mask (``s == 0``).

    Components are divided by their (non-differentiated) largest magnitude before squaring, so
    tiny differences do not underflow; at a coincidence the norm is an exact, gradient-safe zero.
    """
    scale = jax.lax.stop_gradient(jnp.max(jnp.abs(s), axis=-1))
    coincident = scale == 0
    one = jnp.ones((), s.dtype)
    scale = jnp.where(coincident, one, scale)
    sumsq = jnp.sum(jnp.square(s / scale[..., None]), axis=-1)
    sumsq = jnp.where(coincident, one, sumsq)
    q = jnp.where(coincident, 0, scale * jnp.sqrt(sumsq))
    return q, coincident


def _shepard_block(x: jax.Array, controls: jax.Array, displacements: jax.Array, radius: jax.Array) -> jax.Array:
    """Field for one block of queries ``x`` ``(M, D)`` against all controls of one design."""
    dtype = x.dtype
    one = jnp.ones((), dtype)
    s = normalized_differences(x[:, None, :] - controls[None, :, :], radius[None, :, None])
    q, coincident = normalized_distance(s)
    active = ~coincident & (q < 1)

    # Exact coincidences: mean displacement of the coincident controls.
    count = jnp.sum(coincident, axis=-1)
    coincident_sum = jnp.einsum("mc,cd->md", coincident.astype(dtype), displacements)
    coincident_mean = coincident_sum / jnp.maximum(count, 1).astype(dtype)[:, None]

    # Scaled Shepard quotient relative to the nearest active control (the reference).
    has_active = jnp.any(active, axis=-1)
    ref = jnp.argmin(jnp.where(active, q, 2 * one), axis=-1)
    q_ref = jnp.where(has_active, jnp.take_along_axis(q, ref[:, None], axis=-1)[:, 0], one / 2)
    phi_ref = wendland_c2(q_ref)
    q_safe = jnp.where(active, q, one / 2)
    ratio = q_ref[:, None] / q_safe
    # weight_j = a_j * b with b = q_ref^2 / phi_ref, so the reference has weight exactly one.
    weight = jnp.where(active, jnp.square(ratio) * wendland_c2(q_safe) / phi_ref[:, None], 0)
    background = jnp.square(q_ref) / phi_ref
    total_weight = jnp.sum(weight, axis=-1)
    denominator = (background + total_weight)[:, None]
    d_ref = displacements[ref]
    # Near the controls (background <= total weight) u = d_ref + correction keeps the small
    # correction, and its gradient, accurate; far from them (u -> 0, background huge) that form
    # would cancel, so the plain quotient is used there.
    correction = jnp.einsum("mc,mcd->md", weight, displacements[None, :, :] - d_ref[:, None, :]) - background[:, None] * d_ref
    near = d_ref + correction / denominator
    far = jnp.einsum("mc,cd->md", weight, displacements) / denominator
    shepard = jnp.where((background <= total_weight)[:, None], near, far)

    zero = jnp.zeros((), dtype)
    return jnp.where((count > 0)[:, None], coincident_mean, jnp.where(has_active[:, None], shepard, zero))
