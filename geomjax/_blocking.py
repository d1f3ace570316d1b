"""Evaluate a query-point field in blocks so memory stays bounded.

Pairwise ops (morph, RBF, FFD) would otherwise materialise ``N x C`` temporaries: 1,000,000
points by 1,000 controls in float64 is 8 GB per live array. ``map_query_blocks`` splits the query
axis into fixed-size blocks, runs them with ``lax.map`` and wraps each block in
``jax.checkpoint`` so the backward pass recomputes a block's temporaries instead of storing them
all. Block sizes are static, so everything stays ``jit``/``vmap``/``grad`` compatible.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

# Live temporaries per block stay near this many bytes (per live array, before the op's factor).
DEFAULT_BLOCK_BYTES = 64 * 2**20


def query_block_size(num_queries: int, bytes_per_query: int, *, budget_bytes: int = DEFAULT_BLOCK_BYTES) -> int:
    """Number of queries per block so that ``block * bytes_per_query`` fits the budget."""
    block = max(1, budget_bytes // max(1, bytes_per_query))
    return int(min(max(num_queries, 1), block))


def map_query_blocks(field_fn: Callable[..., jax.Array], queries: tuple[jax.Array, ...], *, block_size: int) -> jax.Array:
    """Apply ``field_fn`` to blocks of the query arrays and concatenate the results.

    Args:
        field_fn: maps query arrays with a leading block axis to an output with the same leading
            axis. Everything that is not blocked (controls, coefficients) is closed over.
        queries: arrays sharing a leading query axis of length ``N``.
        block_size: static block length.

    Whole blocks run through ``lax.map``; a final partial block is evaluated directly (also
    checkpointed) and appended. Padding ``N`` up to a multiple of the block instead would copy the
    points and the output, about 30% of a cheap field's time on CPU (measured on Bernstein FFD).
    """
    num = queries[0].shape[0]
    if num <= block_size:
        return field_fn(*queries)
    num_blocks, remainder = divmod(num, block_size)
    whole = num_blocks * block_size
    blocked = tuple(q[:whole].reshape((num_blocks, block_size) + q.shape[1:]) for q in queries)
    out = jax.lax.map(lambda args: jax.checkpoint(field_fn)(*args), blocked)
    out = out.reshape((whole,) + out.shape[2:])
    if remainder:
        tail = jax.checkpoint(field_fn)(*(q[whole:] for q in queries))
        out = jnp.concatenate([out, tail], axis=0)
    return out
