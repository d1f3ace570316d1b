"""map_query_blocks: blocked evaluation equals the unblocked one, values and gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from geomjax._blocking import map_query_blocks, query_block_size


@pytest.mark.parametrize("block_size", [1, 4, 5, 23, 40])  # divides N, leaves a tail, N itself, larger
def test_blocks_match_one_evaluation(block_size):
    x = jnp.asarray(np.random.default_rng(0).normal(size=(20, 3)))
    w = jnp.asarray(np.random.default_rng(1).normal(size=(3, 2)))

    def field(xb):
        return jnp.sin(xb) @ w

    # Blocking changes nothing but how XLA may fuse and vectorise the 3-term sums (with or without
    # FMA): a few roundings of the largest entry, not of each (small entries are cancellations).
    expected = field(x)
    atol = 8 * float(jnp.finfo(jnp.float64).eps) * float(jnp.abs(expected).max())
    np.testing.assert_allclose(map_query_blocks(field, (x,), block_size=block_size), expected, rtol=0, atol=atol)
    blocked_grads = jax.grad(lambda x, w: jnp.sum(map_query_blocks(lambda xb: jnp.sin(xb) @ w, (x,), block_size=block_size) ** 2), argnums=(0, 1))(x, w)
    direct_grads = jax.grad(lambda x, w: jnp.sum((jnp.sin(x) @ w) ** 2), argnums=(0, 1))(x, w)
    for blocked, direct in zip(blocked_grads, direct_grads):
        np.testing.assert_allclose(blocked, direct, rtol=1e-13)


def test_several_query_arrays_share_the_blocking():
    x, y = jnp.arange(11.0), jnp.arange(11.0) * 10
    np.testing.assert_array_equal(map_query_blocks(lambda a, b: a + b, (x, y), block_size=3), x + y)


def test_block_size_respects_the_budget():
    assert query_block_size(10**6, 1000, budget_bytes=10**6) == 1000
    assert query_block_size(10, 1000, budget_bytes=10**9) == 10
    assert query_block_size(0, 1000) == 1
