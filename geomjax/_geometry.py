"""Shared geometry in pure JAX: closest point on a triangle, ray-triangle hits, winding numbers,
the overflow-safe norm.

This is the one projection helper of the package (DESIGN.md): shrinkwrap, the signed distance
field and remeshing all replay their closest points through :func:`closest_point_on_triangle`,
ray casting replays its hits through :func:`ray_triangle_intersection`, and the signed distance
field and voxel fractions share :func:`winding_numbers`. Every function broadcasts over leading
axes (``(..., 3)`` inputs), works in float32 and float64, and is differentiable with finite
gradients everywhere: branches are selected with ``where`` and every division has a guarded
denominator, so no NaN or infinity leaks into a gradient from a branch that was not taken
(degenerate triangles, zero directions, points exactly on an edge).

Robust scaling: coordinates are quartered when they come near the float maximum (so differences
cannot overflow), then every difference is divided by a power of two close to the triangle's
size (exact in floating point, and not differentiated since the results are scale-invariant).
The region tests therefore never overflow or underflow for triangles of any size, from 1e-30 to
1e30 in float64 and over most of the float32 range; only a query farther than about 2**60
triangle sizes from the triangle (float32) can overflow the squared distances used to compare
edge candidates.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

__all__ = [
    "closest_point_on_triangle",
    "overflow_safe_norm",
    "scaled_triangle",
    "ray_plane_intersection",
    "ray_triangle_intersection",
    "triangle_normal",
    "winding_numbers",
]

# One point or vector per leading index; the ray functions take five of them.
Vector = Float[Array, "*batch 3"]
RayHit = tuple[Float[Array, "*batch"], Float[Array, "*batch 3"], Bool[Array, "*batch"]]


def _dot(x, y):
    return jnp.sum(x * y, axis=-1)


def _power_of_two_below(x):
    """``2**-e`` with ``x * 2**-e`` in ``[0.5, 1)``, ``e`` clamped so the factor stays a normal number.

    ``1`` where ``x`` is zero or not finite. (XLA flushes subnormals to zero, so the factor must
    never be one; triangles below ``2**-(maxexp-4)`` are left partly unnormalised.)
    """
    _, exponent = jnp.frexp(jnp.where(jnp.isfinite(x) & (x > 0), x, 1))
    limit = jnp.finfo(x.dtype).maxexp - 4
    return jnp.ldexp(jnp.ones_like(x), -jnp.clip(exponent, -limit, limit))


def _prescale(*coordinates):
    """A factor (1 or 1/4) that keeps differences of the coordinates finite, not differentiated."""
    dtype = coordinates[0].dtype
    largest = jnp.max(jnp.stack([jnp.max(jnp.abs(x), axis=-1) for x in jnp.broadcast_arrays(*coordinates)]), axis=0)
    big = largest > jnp.finfo(dtype).max / 4
    return jax.lax.stop_gradient(jnp.where(big, jnp.asarray(0.25, dtype), jnp.asarray(1.0, dtype)))


def scaled_triangle(a, b, c, *extra):
    """Triangle edges in triangle units: ``(ab, ac, bc, pre, unit)``.

    ``pre`` (1 or 1/4) and ``unit`` (a power of two) are ``(..., 1)`` factors, not differentiated;
    :func:`_to_units` maps other coordinate differences into the same units. ``extra``
    coordinates only take part in the prescale.
    """
    pre = _prescale(a, b, c, *extra)[..., None]
    ab, ac, bc = b * pre - a * pre, c * pre - a * pre, c * pre - b * pre
    size = jnp.maximum(jnp.max(jnp.abs(ab), axis=-1), jnp.maximum(jnp.max(jnp.abs(ac), axis=-1), jnp.max(jnp.abs(bc), axis=-1)))
    unit = jax.lax.stop_gradient(_power_of_two_below(size))[..., None]
    return ab * unit, ac * unit, bc * unit, pre, unit


def _to_units(x, y, pre, unit):
    """``x - y`` in triangle units: prescale, subtract, then scale (one combined factor could underflow)."""
    return (x * pre - y * pre) * unit


def _safe_divide(numerator, denominator, valid):
    """``numerator / denominator`` where ``valid``, else zero, with no NaN in either gradient."""
    one = jnp.ones((), denominator.dtype)
    return jnp.where(valid, numerator / jnp.where(valid, denominator, one), 0)


def closest_point_on_triangle(
    p: Float[Array, "*batch 3"], a: Float[Array, "*batch 3"], b: Float[Array, "*batch 3"], c: Float[Array, "*batch 3"]
) -> tuple[Float[Array, "*batch 3"], Float[Array, "*batch 3"]]:
    """Closest point to ``p`` on the solid triangle ``(a, b, c)`` and its barycentric coordinates.

    If the orthogonal projection of ``p`` onto the triangle's plane lies inside the triangle
    (barycentric coordinates all non-negative, computed as triple products
    ``(e1 x e2) . (e1 x (p - x))`` around each vertex, so that the small coordinates of a skinny
    triangle keep their relative accuracy), that projection is the answer. Otherwise the answer is the best of the three clamped edge
    projections (edges ``AB``, ``AC``, ``BC``; vertex regions fall out of the clamping; an exact
    tie keeps the first). Degenerate triangles (collinear or coincident vertices) therefore
    reduce to the closest point on their longest extent, with finite gradients.

    Args:
        p: query points ``(..., 3)``.
        a, b, c: triangle vertices ``(..., 3)``, broadcastable against ``p``, same float dtype.

    Returns:
        ``(point, barycentric)``: the closest point ``(..., 3)`` and weights ``(..., 3)`` of
        ``(a, b, c)`` (non-negative, summing to one); ``point = sum_i w_i x_i``.

    Differentiable (reverse and forward mode) in all inputs. The result is piecewise smooth:
    inside a Voronoi region of a feature (face interior, edge, vertex) it is a smooth function of
    ``p`` and the vertices; on a region boundary the derivative of the region that was selected
    is returned. Non-finite inputs give NaN outputs.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax._geometry import closest_point_on_triangle
        >>> a, b, c = jnp.array([0.0, 0, 0]), jnp.array([1.0, 0, 0]), jnp.array([0.0, 1, 0])
        >>> point, weights = closest_point_on_triangle(jnp.array([[0.2, 0.3, 2.0], [2.0, 2.0, 0.0]]), a, b, c)
        >>> print(np.round(np.asarray(point), 3))
        [[0.2 0.3 0. ]
         [0.5 0.5 0. ]]
        >>> print(np.round(np.asarray(weights), 3))
        [[0.5 0.2 0.3]
         [0.  0.5 0.5]]
    """
    p, a, b, c = jnp.broadcast_arrays(p, a, b, c)
    ab, ac, bc, pre, unit = scaled_triangle(a, b, c, p)
    ap, bp = _to_units(p, a, pre, unit), _to_units(p, b, pre, unit)

    # Projected barycentric numerators, each around its own vertex, as triple products with the
    # normal n = ab x ac: n . (ab x ap) for c, n . (ap x ac) for b, n . (bc x bp) for a. Their
    # expanded (Lagrange identity) forms, differences of products of dot products, cancel
    # catastrophically on skinny triangles: a coordinate of size 1/aspect would drown in the
    # rounding of terms of size 1.
    normal = jnp.cross(ab, ac)
    weight_c = _dot(normal, jnp.cross(ab, ap))
    weight_b = _dot(normal, jnp.cross(ap, ac))
    weight_a = _dot(normal, jnp.cross(bc, bp))
    ab2, ac2, bc2 = _dot(ab, ab), _dot(ac, ac), _dot(bc, bc)
    total = weight_a + weight_b + weight_c
    inside = (weight_a >= 0) & (weight_b >= 0) & (weight_c >= 0) & (total > 0)
    interior = jnp.stack([weight_a, weight_b, weight_c], axis=-1)
    interior = _safe_divide(interior, total[..., None], inside[..., None])

    def edge(start_to_p, direction, length2):
        t = jnp.clip(_safe_divide(_dot(start_to_p, direction), length2, length2 > 0), 0, 1)
        offset = start_to_p - t[..., None] * direction
        return t, _dot(offset, offset)

    t_ab, d_ab = edge(ap, ab, ab2)
    t_ac, d_ac = edge(ap, ac, ac2)
    t_bc, d_bc = edge(bp, bc, bc2)
    w_ab = jnp.stack([1 - t_ab, t_ab, jnp.zeros_like(t_ab)], axis=-1)
    w_ac = jnp.stack([1 - t_ac, jnp.zeros_like(t_ac), t_ac], axis=-1)
    w_bc = jnp.stack([jnp.zeros_like(t_bc), 1 - t_bc, t_bc], axis=-1)
    use_ab = (d_ab <= d_ac) & (d_ab <= d_bc)
    use_ac = ~use_ab & (d_ac <= d_bc)
    boundary = jnp.where(use_ab[..., None], w_ab, jnp.where(use_ac[..., None], w_ac, w_bc))
    weights = jnp.where(inside[..., None], interior, boundary)
    on_boundary = boundary[..., 0:1] * a + boundary[..., 1:2] * b + boundary[..., 2:3] * c
    # Inside, the point is p moved along the normal, not the weighted corners: its derivative is
    # then the in-plane identity to rounding, where the corners' weights (derivatives of size
    # 1 / height) would cancel to rounding times the aspect ratio on a skinny triangle.
    height = _safe_divide(_dot(normal, ap), _dot(normal, normal), inside)
    projected = p - height[..., None] * normal / unit / pre
    point = jnp.where(inside[..., None], projected, on_boundary)
    return point, weights


def ray_triangle_intersection(origin: Vector, direction: Vector, a: Vector, b: Vector, c: Vector) -> RayHit:
    """Intersection of the ray ``origin + t * direction`` (``t >= 0``) with triangle ``(a, b, c)``.

    Möller-Trumbore on scaled coordinates (edges and ``origin - a`` in triangle units, the
    direction divided by a power of two of its own size), so the result does not depend on the
    scale of either. Both faces count (no back-face culling); a ray in the triangle's plane, a
    degenerate triangle or a zero direction never hits.

    Args:
        origin, direction: ``(..., 3)``; ``t`` is in units of ``|direction|`` (normalize the
            direction first for Euclidean distances).
        a, b, c: triangle vertices ``(..., 3)``, broadcastable, same float dtype.

    Returns:
        ``(t, barycentric, hit)``: the ray parameter (``+inf`` where there is no hit), the
        weights ``(..., 3)`` of ``(a, b, c)`` at the hit (zeros where there is no hit) and the
        hit mask. Edges and vertices count as hits (closed triangle).

    Differentiable in all inputs where ``hit`` (the hit point moves with the ray and the
    triangle); misses have zero gradients.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax._geometry import ray_triangle_intersection
        >>> a, b, c = jnp.array([0.0, 0, 1]), jnp.array([1.0, 0, 1]), jnp.array([0.0, 1, 1])
        >>> t, weights, hit = ray_triangle_intersection(jnp.array([0.25, 0.25, 0.0]), jnp.array([0.0, 0, 2]), a, b, c)
        >>> print(float(t), np.round(np.asarray(weights), 3), bool(hit))
        0.5 [0.5  0.25 0.25] True
    """
    t, weights, valid = ray_plane_intersection(origin, direction, a, b, c)
    hit = valid & jnp.all(weights >= 0, axis=-1) & (t >= 0)
    return jnp.where(hit, t, jnp.inf), jnp.where(hit[..., None], weights, 0), hit


def ray_plane_intersection(origin: Vector, direction: Vector, a: Vector, b: Vector, c: Vector) -> RayHit:
    """Where the line ``origin + t * direction`` meets the plane of ``(a, b, c)``, ungated.

    The computation of :func:`ray_triangle_intersection` without its inside and ``t >= 0``
    tests: ``t`` may be negative and the barycentric weights (summing to one) may be negative.
    Used to replay a hit chosen by a BVH search, where rounding may put the hit a hair outside
    the chosen triangle. ``valid`` is false (``t = inf``, weights zero, zero gradients) for a
    line parallel to the plane, a degenerate triangle or a zero direction.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax._geometry import ray_plane_intersection
        >>> a, b, c = jnp.array([0.0, 0, 1]), jnp.array([1.0, 0, 1]), jnp.array([0.0, 1, 1])
        >>> t, weights, valid = ray_plane_intersection(jnp.array([2.0, 0.5, 3]), jnp.array([0.0, 0, 1]), a, b, c)
        >>> print(float(t), np.asarray(weights), bool(valid))
        -2.0 [-1.5  2.   0.5] True
    """
    origin, direction, a, b, c = jnp.broadcast_arrays(origin, direction, a, b, c)
    ab, ac, _, pre, unit = scaled_triangle(a, b, c, origin)
    ao = _to_units(origin, a, pre, unit)
    length = jnp.max(jnp.abs(direction), axis=-1)
    direction_scale = jax.lax.stop_gradient(_power_of_two_below(length))
    d = direction * direction_scale[..., None]

    pvec = jnp.cross(d, ac)
    det = _dot(ab, pvec)
    qvec = jnp.cross(ao, ab)
    valid = (det != 0) & jnp.isfinite(det) & (length > 0)
    u = _safe_divide(_dot(ao, pvec), det, valid)
    v = _safe_divide(_dot(d, qvec), det, valid)
    # Scaled coordinates turn the ray parameter into t_scaled = t * pre * unit / direction_scale.
    t_scaled = _safe_divide(_dot(ac, qvec), det, valid)
    t = jnp.where(valid, t_scaled * (direction_scale / unit[..., 0]) / pre[..., 0], jnp.inf)
    weights = jnp.where(valid[..., None], jnp.stack([1 - u - v, u, v], axis=-1), 0)
    return t, weights, valid


def triangle_normal(a: Float[Array, "*batch 3"], b: Float[Array, "*batch 3"], c: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """Unit normal ``(b - a) x (c - a) / |...|`` following the winding (counter-clockwise = up).

    Computed on scaled edges, so tiny and huge triangles keep full precision; a degenerate
    triangle gives the zero vector (with zero gradient).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax._geometry import triangle_normal
        >>> n = triangle_normal(jnp.array([0.0, 0, 0]), jnp.array([0.0, 1e-30, 0]), jnp.array([1e-30, 0, 0]))
        >>> print(np.asarray(n))
        [ 0.  0. -1.]
    """
    a, b, c = jnp.broadcast_arrays(a, b, c)
    ab, ac, _, _, _ = scaled_triangle(a, b, c)
    normal = jnp.cross(ab, ac)
    # Normalise by the largest component first so the squared norm cannot underflow.
    largest = jnp.max(jnp.abs(normal), axis=-1, keepdims=True)
    valid = largest > 0
    unit_ish = _safe_divide(normal, largest, valid)
    norm2 = _dot(unit_ish, unit_ish)[..., None]
    one = jnp.ones((), normal.dtype)
    norm = jnp.sqrt(jnp.where(valid, norm2, one))
    return jnp.where(valid, unit_ish / norm, 0)


def winding_numbers(points: Float[Array, "num_points 3"], triangles: Float[Array, "num_faces 3 3"]) -> Float[Array, " num_points"]:
    """Exact generalized winding numbers ``sum_f omega_f / (4 pi)`` of points w.r.t. triangles.

    Each triangle's signed solid angle is the Van Oosterom-Strackee formula. Memory is
    ``O(points x faces)``: callers block over the points (``map_query_blocks``).
    """
    relative = triangles[None] - points[:, None, None, :]
    a, b, c = relative[:, :, 0], relative[:, :, 1], relative[:, :, 2]
    la, lb, lc = (jnp.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = jnp.sum(a * jnp.cross(b, c), -1)
    denominator = la * lb * lc + jnp.sum(a * b, -1) * lc + jnp.sum(b * c, -1) * la + jnp.sum(c * a, -1) * lb
    return jnp.sum(2 * jnp.arctan2(det, denominator), axis=1) / (4 * jnp.pi)


def overflow_safe_norm(x: Float[Array, "*batch dims"]) -> Float[Array, "*batch"]:
    """``|x|`` over the last axis without overflow or underflow; zero gradient at ``x = 0``.

    The components are divided by the largest magnitude (not differentiated) before squaring,
    so the squares neither overflow for huge coordinates nor flush to zero for tiny ones.
    """
    largest = jax.lax.stop_gradient(jnp.max(jnp.abs(x), axis=-1))
    usable = (largest > 0) & jnp.isfinite(largest)
    one = jnp.ones((), x.dtype)
    scale = jnp.where(usable, largest, one)
    sumsq = jnp.sum(jnp.square(x / scale[..., None]), axis=-1)
    return jnp.where(usable, scale * jnp.sqrt(jnp.where(usable, sumsq, one)), jnp.where(largest > 0, largest, 0))
