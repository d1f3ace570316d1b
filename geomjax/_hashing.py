"""Counter-based integer hashing: reproducible random numbers that need no key plumbing.

Stochastic ops (voxel jitter, Poisson-disk candidates) derive every random number from
``lowbias32(seed, index, ...)`` so that results depend only on the seed and the element index,
never on block sizes, thread counts or the backend (the Warp kernels use the same arithmetic).
"""

import jax
import jax.numpy as jnp


def lowbias32(h: jax.Array) -> jax.Array:
    """The "lowbias32" 32-bit integer hash (C. Wellons) of a ``uint32`` array, elementwise."""
    h = h ^ (h >> 16)
    h = h * jnp.uint32(0x7FEB352D)
    h = h ^ (h >> 15)
    h = h * jnp.uint32(0x846CA68B)
    return h ^ (h >> 16)
