"""Exact power-of-two scaling on bit patterns (``geomjax._tiny_scale``), against NumPy's ``ldexp``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from geomjax._tiny_scale import max_scale_exponent, scale_exactly, tiny_problem_exponent


@pytest.mark.parametrize("dtype, unsigned", [(np.float64, np.uint64), (np.float32, np.uint32)])
def test_scale_exactly_matches_ldexp_on_every_kind_of_value(dtype, unsigned):
    """Random bit patterns (normal, subnormal, inf, NaN), both signs, scaled up and down: NumPy's
    ``ldexp`` (IEEE arithmetic, no flushing) rounds once to nearest-even, so the bits must agree."""
    info = np.finfo(dtype)
    patterns = np.random.default_rng(0).integers(0, np.iinfo(unsigned).max, 20_000, dtype=unsigned).view(dtype)
    specials = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, info.tiny, -info.tiny, info.smallest_subnormal, info.max], dtype)
    values = np.concatenate([patterns, specials])
    largest = max_scale_exponent(dtype)
    scale = jax.jit(scale_exactly)
    for exponent in (0, 1, -1, info.nmant, -info.nmant, largest // 2, -largest // 2, largest, -largest):
        got = np.asarray(scale(jnp.asarray(values), jnp.int32(exponent)))
        with np.errstate(over="ignore", under="ignore", invalid="ignore"):  # NaN patterns
            expected = np.ldexp(values, exponent).astype(dtype)
        same = (got.view(unsigned) == expected.view(unsigned)) | (np.isnan(got) & np.isnan(expected))
        assert same.all(), (exponent, values[~same][:3], got[~same][:3], expected[~same][:3])


def test_tiny_problem_exponent_scales_only_tiny_designs():
    designs = jnp.array([[3e-310, -1e-311, 0.0], [1.0, 1e-310, 0.0], [0.0, 0.0, 0.0], [1e-200, 2e-200, jnp.inf]])
    exponent = np.asarray(tiny_problem_exponent([designs]))
    # 3e-310 lies in [2^-1028, 2^-1027): brought to [1, 2) but for the cap; 2e-200 (the largest
    # finite) in [2^-664, 2^-663); a design of zeros stays.
    np.testing.assert_array_equal(exponent, [min(1028, max_scale_exponent(np.float64)), 0, 0, 664])
    assert jax.grad(lambda v: scale_exactly(v, jnp.int32(1000)))(1e-310) == 2.0**1000
