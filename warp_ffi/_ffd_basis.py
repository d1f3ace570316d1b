"""The pieces the fixed and the general Warp FFD kernels share: basis codes, argument types and
the per-axis basis (:mod:`warp_ffi.ffd`, :mod:`warp_ffi._ffd_general`)."""

from __future__ import annotations

from typing import Any, no_type_check

from ._wrap import warp as wp

__all__ = ["BASIS_CODES", "Batched", "PerDesign", "axis_basis", "kernel_types"]

BASIS_CODES = {"bernstein": 0, "bspline": 1, "linear": 2, "cubic_hermite": 3, "quintic_hermite": 4}

# The kernels' argument types (float types resolved per overload).
Batched: Any = wp.array3d(dtype=Any)  # (B, N, D) points and fields, (B, nodes, D) lattices
PerDesign: Any = wp.array2d(dtype=Any)  # (B, D) box corners and edge lengths


@wp.func
@no_type_check
def axis_basis(kind: int, n: int, u: Any, table: Any):
    """Supporting nodes on one axis at local coordinate ``u`` in ``[0, 1]``.

    Returns ``(weights, d weights / du, first node, node count)``.
    """
    one = type(u)(1.0)
    weight = table
    slope = table
    start = int(0)
    count = int(0)
    if kind == 0:
        # Bernstein of degree n - 1 by the de Casteljau recurrence; the derivative comes from the
        # degree n - 2 basis: dB^p_i = p (B^{p-1}_{i-1} - B^{p-1}_i).
        lower = one - u
        weight[0] = one
        for k in range(1, n):
            if k == n - 1:
                degree = type(u)(float(k))
                slope[0] = -degree * weight[0]
                for i in range(1, k):
                    slope[i] = degree * (weight[i - 1] - weight[i])
                slope[k] = degree * weight[k - 1]
            weight[k] = u * weight[k - 1]
            for r in range(k - 1):
                i = k - 1 - r
                weight[i] = lower * weight[i] + u * weight[i - 1]
            weight[0] = lower * weight[0]
        count = n
    else:
        spans = n - 1
        if kind == 1:
            spans = n - 3
        scale = type(u)(float(spans))
        s = u * scale
        cell = wp.clamp(int(wp.floor(s)), 0, spans - 1)
        start = cell
        t = s - type(u)(float(cell))
        if kind == 1:
            # uniform cubic B-spline
            sixth = one / type(u)(6.0)
            v = one - t
            weight[0] = v * v * v * sixth
            weight[1] = (type(u)(3.0) * t * t * t - type(u)(6.0) * t * t + type(u)(4.0)) * sixth
            weight[2] = (type(u)(-3.0) * t * t * t + type(u)(3.0) * t * t + type(u)(3.0) * t + one) * sixth
            weight[3] = t * t * t * sixth
            half = type(u)(0.5)
            slope[0] = -half * v * v * scale
            slope[1] = (type(u)(1.5) * t * t - type(u)(2.0) * t) * scale
            slope[2] = (type(u)(-1.5) * t * t + t + half) * scale
            slope[3] = half * t * t * scale
            count = 4
        else:
            upper = t
            upper_slope = one
            if kind == 3:
                upper = t * t * (type(u)(3.0) - type(u)(2.0) * t)
                upper_slope = type(u)(6.0) * t * (one - t)
            elif kind == 4:
                upper = t * t * t * (t * (t * type(u)(6.0) - type(u)(15.0)) + type(u)(10.0))
                upper_slope = type(u)(30.0) * t * t * (t - one) * (t - one)
            weight[0] = one - upper
            weight[1] = upper
            slope[0] = -upper_slope * scale
            slope[1] = upper_slope * scale
            count = 2
    return weight, slope, start, count


def kernel_types(s):
    names = ("points", "values", "out", "lattice", "field_adj", "points_adj", "weights", "slopes")  # (scratch tables: _ffd_general.py)
    return {name: wp.array3d(dtype=s) for name in names} | {"origin": wp.array2d(dtype=s), "extent": wp.array2d(dtype=s)}
