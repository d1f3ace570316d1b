"""Exact power-of-two rescaling for problems below the normal floating-point range.

XLA on CPU flushes subnormal numbers to zero, on input and on output of every arithmetic
operation (JAX sets the processor's flush-to-zero and denormals-are-zero modes). A problem whose
lengths are all subnormal (a radius of ``1e-310`` with points and displacements of that size)
therefore computes with zeros, where the reference (PyTorch, IEEE arithmetic) gives an answer
and a finite gradient. An op that is homogeneous in its lengths (``f(2^k x) = 2^k f(x)``) can
run such a problem at a normal scale instead: :func:`tiny_problem_exponent` picks ``k`` per
design from the largest magnitude, and :func:`scale_exactly` multiplies by ``2^k`` on the bit
patterns (integer arithmetic, which no flushing touches), so subnormal inputs arrive intact and
subnormal results leave intact, rounded once to nearest-even. For a problem of normal size
``k = 0`` and nothing changes, bit for bit.

Derivatives: :func:`homogeneous_at_normal_scale` returns ``2^-k f(2^k x)`` with the derivative
``J_f(2^k x)``, which equals ``J(x)`` for an ``f`` homogeneous of degree one: the factors cancel
instead of meeting the incoming cotangent, where ``2^-k`` would flush it to zero.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["homogeneous_at_normal_scale", "scale_exactly", "tiny_problem_exponent"]


def _layout(dtype) -> tuple[type, int, int]:
    """``(unsigned integer type, mantissa bits, exponent bias)`` of a float dtype."""
    info = jnp.finfo(dtype)
    unsigned = {2: jnp.uint16, 4: jnp.uint32, 8: jnp.uint64}[jnp.dtype(dtype).itemsize]
    return unsigned, int(info.nmant), int(info.maxexp) - 1


def max_scale_exponent(dtype) -> int:
    """The largest ``|k|`` used: ``2^k`` and ``2^-k`` stay normal numbers of ``dtype``."""
    return int(jnp.finfo(dtype).maxexp) - 24


def _exponent_of(magnitude_bits: jax.Array, dtype) -> jax.Array:
    """``floor(log2 |v|)`` (int32) from ``|v|``'s bit pattern; subnormals included, -inf-like for 0."""
    unsigned, mantissa_bits, bias = _layout(dtype)
    width = 8 * jnp.dtype(unsigned).itemsize
    biased = (magnitude_bits >> mantissa_bits).astype(jnp.int32)
    fraction = magnitude_bits & unsigned((1 << mantissa_bits) - 1)
    # A subnormal's leading bit is its fraction's: 2^(1 - bias - mantissa_bits + floor(log2 fraction)).
    top = (width - 1) - jax.lax.clz(fraction).astype(jnp.int32)
    subnormal = 1 - bias - mantissa_bits + top
    return jnp.where(biased > 0, biased - bias, jnp.where(fraction > 0, subnormal, jnp.iinfo(jnp.int32).min // 2))


def tiny_problem_exponent(arrays, *, batch_axes: int = 1) -> jax.Array:
    """Per design (the leading ``batch_axes`` axes), the ``k`` that brings a tiny problem up.

    ``k = 0`` unless the largest finite magnitude over all ``arrays`` (same dtype, same leading
    axes) is nonzero and below ``2^-(maxexp / 2)`` (``2^-512`` in float64, ``2^-64`` in
    float32); then ``k = -floor(log2(largest))`` (the largest becomes ``[1, 2)``), at most
    :func:`max_scale_exponent`. Not differentiated (an integer).
    """
    dtype = arrays[0].dtype
    unsigned, _, _ = _layout(dtype)
    sign_off = unsigned((1 << (8 * jnp.dtype(unsigned).itemsize - 1)) - 1)
    infinity = jax.lax.bitcast_convert_type(jnp.asarray(jnp.inf, dtype), unsigned)

    def largest_bits(array):
        bits = jax.lax.bitcast_convert_type(jax.lax.stop_gradient(array), unsigned) & sign_off
        # Non-negative floats order like their bit patterns, subnormals included.
        bits = jnp.where(bits < infinity, bits, unsigned(0))
        return jnp.max(bits.reshape(*bits.shape[:batch_axes], -1), axis=-1, initial=unsigned(0))

    largest = functools.reduce(jnp.maximum, [largest_bits(array) for array in arrays])
    exponent = _exponent_of(largest, dtype)
    threshold = -(int(jnp.finfo(dtype).maxexp) // 2)
    tiny = (exponent < threshold) & (largest > 0)  # all zeros (or non-finite) need no scaling
    return jnp.where(tiny, jnp.minimum(-exponent, max_scale_exponent(dtype)), 0).astype(jnp.int32)


@jax.custom_jvp
def scale_exactly(values: jax.Array, exponent: jax.Array) -> jax.Array:
    """``values * 2^exponent`` rounded once to nearest-even, subnormals included.

    ``exponent`` is an int32 array broadcastable to ``values`` with ``|exponent| <=``
    :func:`max_scale_exponent`. Zeros, infinities and NaNs pass unchanged; overflow gives an
    infinity of the value's sign.
    """
    values = jnp.asarray(values)
    dtype = values.dtype
    unsigned, mantissa_bits, bias = _layout(dtype)
    width = 8 * jnp.dtype(unsigned).itemsize
    signed = {16: jnp.int16, 32: jnp.int32, 64: jnp.int64}[width]
    exponent = jnp.broadcast_to(exponent, values.shape).astype(signed)
    bits = jax.lax.bitcast_convert_type(values, unsigned)
    sign = bits & unsigned(1 << (width - 1))
    magnitude = bits ^ sign
    biased = (magnitude >> mantissa_bits).astype(signed)
    fraction = magnitude & unsigned((1 << mantissa_bits) - 1)
    implicit = unsigned(1 << mantissa_bits)
    # values = significand * 2^(power - bias - mantissa_bits), significand normalised below.
    significand = jnp.where(biased > 0, fraction | implicit, fraction)
    power = jnp.maximum(biased, 1)
    lead = (width - 1) - jax.lax.clz(jnp.maximum(significand, unsigned(1))).astype(signed)
    shift_up = mantissa_bits - lead  # > 0 for subnormals only
    significand = significand << jnp.maximum(shift_up, 0).astype(unsigned)
    power = power - shift_up + exponent
    finite = (magnitude >> mantissa_bits) != unsigned((1 << (width - 1 - mantissa_bits)) - 1)
    # Normal result: the biased exponent and the fraction. Overflow: infinity.
    top = (1 << (width - 1 - mantissa_bits)) - 1
    as_normal = (jnp.clip(power, 1, top).astype(unsigned) << mantissa_bits) | (significand & unsigned((1 << mantissa_bits) - 1))
    infinity = unsigned(top << mantissa_bits)
    # Subnormal result: shift right by 1 - power with round-half-even; a carry into the
    # exponent field gives the smallest normal number, as it should.
    shift = jnp.clip(1 - power, 1, mantissa_bits + 2).astype(unsigned)
    kept = significand >> shift
    remainder = significand - (kept << shift)
    half = unsigned(1) << (shift - unsigned(1))
    round_up = (remainder > half) | ((remainder == half) & ((kept & unsigned(1)) == unsigned(1)))
    as_subnormal = kept + round_up.astype(unsigned)
    scaled = jnp.where(power >= top, infinity, jnp.where(power >= 1, as_normal, as_subnormal))
    scaled = jnp.where(finite & (magnitude != unsigned(0)), scaled, magnitude)
    return jax.lax.bitcast_convert_type(scaled | sign, dtype)


@scale_exactly.defjvp
def _scale_exactly_jvp(primals, tangents):
    values, exponent = primals
    tangent, _ = tangents
    factor = jnp.ldexp(jnp.ones((), values.dtype), exponent.astype(jnp.int32))  # a normal power of two
    return scale_exactly(values, exponent), tangent * factor


def homogeneous_at_normal_scale(fn, lengths: tuple, others: tuple, exponent: jax.Array) -> jax.Array:
    """``fn(*lengths, *others)`` computed as ``2^-k fn(2^k lengths, others)``, ``k = exponent``.

    ``fn`` must be homogeneous of degree one in ``lengths`` (coordinates, displacements, radii:
    scaling them all by ``s`` scales the result by ``s``) and of degree zero in ``others``
    (weights; arrays or ``None``). ``exponent`` is int32 ``(B,)`` (from
    :func:`tiny_problem_exponent`) for arrays with the design axis first; it broadcasts over
    their other axes. Derivatives with respect to ``lengths`` are those of ``fn`` at the scaled
    point, where nothing underflows; those with respect to ``others`` are scaled by ``2^-k`` (as
    small as the result).
    """
    return _scaled_call(fn, tuple(lengths), tuple(others), exponent)


def _per_design(exponent: jax.Array, array: jax.Array) -> jax.Array:
    return exponent.reshape(exponent.shape + (1,) * (array.ndim - exponent.ndim))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _scaled_call(fn, lengths, others, exponent):
    scaled = tuple(scale_exactly(a, _per_design(exponent, a)) for a in lengths)
    out = fn(*scaled, *others)
    return scale_exactly(out, -_per_design(exponent, out))


@_scaled_call.defjvp
def _scaled_call_jvp(fn, primals, tangents):
    lengths, others, exponent = primals
    length_tangents, other_tangents, _ = tangents
    scaled = tuple(scale_exactly(a, _per_design(exponent, a)) for a in lengths)

    def shrink(tangent, array):
        if array is None or not jnp.issubdtype(array.dtype, jnp.inexact):
            return tangent  # None or a float0 tangent
        return tangent * jnp.ldexp(jnp.ones((), array.dtype), -_per_design(exponent, array))

    other_tangents = tuple(shrink(t, a) for t, a in zip(other_tangents, others))
    out, out_tangent = jax.jvp(lambda ls, os: fn(*ls, *os), (scaled, others), (length_tangents, other_tangents))
    return scale_exactly(out, -_per_design(exponent, out)), out_tangent
