"""Lattice free-form deformation (FFD) with five per-axis bases."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._blocking import map_query_blocks, query_block_size
from .._dispatch import Implementation, platform_of, select_implementation
from .._errors import raises_documented_errors
from .._points import add_batch_axis, apply_point_weights, remove_batch_axis
from .._sharding import map_local_shards
from .._validate import as_float_array, check_choice, check_coordinates, check_point_weights, check_real_sequence, check_same_device, check_same_dtype, is_array

__all__ = ["free_form_deform_points", "FFD_BASES"]

FFD_BASES = ("bernstein", "bspline", "linear", "cubic_hermite", "quintic_hermite")
_MIN_NODES = {"bernstein": 2, "bspline": 4, "linear": 2, "cubic_hermite": 2, "quintic_hermite": 2}


# Largest lattice dimension and Bernstein nodes per axis that the Warp kernels handle (their
# per-thread basis tables have a fixed size); ``implementation=None`` falls back to JAX beyond it.
WARP_MAX_DIMS = 3
WARP_MAX_BERNSTEIN_NODES = 32


@raises_documented_errors
def free_form_deform_points(
    points: Float[Array, "*batch num_points num_dims"],
    control_displacements: Float[Array, "*batch *lattice_resolution num_dims"],
    *,
    origin: Float[Array, "*box_batch num_dims"] | Sequence[float],
    extent: Float[Array, "*box_batch num_dims"] | Sequence[float],
    basis: str = "bernstein",
    point_weights: Bool[Array, "*batch num_points"] | Float[Array, "*batch num_points"] | None = None,
    implementation: str | None = None,
) -> Float[Array, "*batch num_points num_dims"]:
    """Deform points with a control lattice by free-form deformation.

    A lattice of ``n_1 x ... x n_D`` displacement vectors ``P`` spans the axis-aligned box with
    minimum corner ``origin`` and edge lengths ``extent``. A point ``x`` has local coordinates
    ``u_d = (x_d - origin_d) / extent_d`` and is *inside* when every ``u_d`` lies in ``[0, 1]``
    (both faces included). Inside points move by the tensor-product interpolation
    ``d(x) = sum_i prod_d b_{i_d}(u_d) P_i`` and become ``x + w d(x)``; outside points and points
    with NaN coordinates are returned unchanged, with exactly zero gradient through the field.

    Bases (per axis; all are partitions of unity, so a zero lattice is exactly the identity and a
    constant lattice translates the inside of the box):

    * ``"bernstein"``: Bernstein polynomials of degree ``n_d - 1`` (classic Sederberg-Parry FFD,
      global support); node ``i`` sits at ``u = i / (n_d - 1)``.
    * ``"bspline"``: uniform cubic B-spline with ``n_d - 3`` knot spans over the box; coefficient
      ``i`` sits at the Greville coordinate ``u = (i - 1) / (n_d - 3)``, so the first and last
      planes lie one knot spacing outside the box and node values are not interpolated.
    * ``"linear"``, ``"cubic_hermite"``, ``"quintic_hermite"``: ``n_d - 1`` cells, two nodes per
      axis with upper weight ``t``, ``3t^2 - 2t^3`` or ``6t^5 - 15t^4 + 10t^3`` (C0, C1, C2);
      node values are interpolated exactly.

    Args:
        points: ``(N, D)`` or aligned batched ``(B, N, D)``, float32 or float64, ``D >= 1``.
        control_displacements: ``(n_1, ..., n_D, D)`` for unbatched points or
            ``(B, n_1, ..., n_D, D)`` for batched points, same dtype as ``points``. The lattice
            is read in C order and lattice axis ``d`` spans coordinate ``d``. Each axis needs at
            least 2 nodes (4 for ``"bspline"``).
        origin: minimum box corner: an array ``(D,)`` shared by the batch or ``(B, D)`` aligned
            with batched points (same dtype as ``points``; values are not checked), or a Python
            sequence of ``D`` finite reals.
        extent: box edge lengths, accepted like ``origin``; sequence entries must be finite and
            positive (at least ``tiny * eps`` of the dtype).
        basis: one of ``"bernstein"`` (default), ``"bspline"``, ``"linear"``,
            ``"cubic_hermite"``, ``"quintic_hermite"``.
        point_weights: optional ``(N,)`` / ``(B, N)`` weights multiplying the displacement. Bool
            weights are a hard mask; float weights must match the points dtype.
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``. ``None`` picks the
            backend measured faster by ``benchmarks/bench_ffd.py``: on CPU JAX for
            ``"bernstein"`` and Warp for the four local bases; on GPU Warp (the reference's
            choice; not measured here), and JAX for lattices beyond Warp's fixed kernels
            (``D > 3``, or more than 32 Bernstein nodes on an axis), or without warp-lang.
            Explicit ``"warp"`` takes every lattice (those through its general kernels, which
            also allocate ``2 B N D max(n_d)`` scratch values), with values and first-order
            reverse mode only (see Differentiability).

    Returns:
        Deformed points with the shape and dtype of ``points``.

    Raises:
        TypeError: non-float arrays, mismatched dtypes, integer weights, a non-sequence box, a
            box sequence without exactly ``D`` entries (as the reference), a ``bool`` or non-real
            sequence entry.
        ValueError: bad ranks or shapes (lattice rank, last lattice dim, box shapes), mixed
            batched/unbatched inputs, too few lattice nodes, unknown ``basis``, non-finite or
            non-positive sequence values.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Differentiability: ``points`` (through the basis), ``control_displacements`` and float
    ``point_weights``, with the transforms of the README's "Backends and transforms" (the Warp
    path through ``jax.custom_vjp``). ``origin`` and ``extent`` are configuration: gradients are
    stopped there. The JAX path evaluates queries in blocks, so memory stays bounded for millions
    of points.

    Sharding: see the README's "Sharding"; designs and points are computed shard by shard on
    both backends and the result keeps the split of ``points``.

    Example:
        >>> import jax.numpy as jnp
        >>> import numpy as np
        >>> from geomjax import free_form_deform_points
        >>> lattice = jnp.zeros((2, 2, 2)).at[1, 1].set(jnp.array([0.0, 1.0]))
        >>> points = jnp.array([[0.5, 0.5], [1.0, 1.0], [2.0, 0.5]])
        >>> out = free_form_deform_points(points, lattice, origin=[0.0, 0.0], extent=[1.0, 1.0])
        >>> print(np.round(np.asarray(out), 4))
        [[0.5  0.75]
         [1.   2.  ]
         [2.   0.5 ]]
    """
    points, batched = check_coordinates("points", points)
    num_dims = points.shape[-1]
    lattice = _check_lattice(points, batched, control_displacements)
    basis = check_choice("basis", basis, FFD_BASES)
    resolution = tuple(int(n) for n in lattice.shape[int(batched) : -1])
    minimum = _MIN_NODES[basis]
    if min(resolution) < minimum:
        raise ValueError(f"control_displacements needs at least {minimum} nodes per lattice axis for basis={basis!r}, got lattice resolution {resolution}")
    origin = _check_box("origin", origin, points, batched, positive=False)
    extent = _check_box("extent", extent, points, batched, positive=True)
    point_weights = check_point_weights(point_weights, points)

    # Lattices beyond Warp's fixed kernels (more axes, or more Bernstein nodes than their
    # register tables hold) run its general kernels when asked for; by default JAX (measured
    # faster for Bernstein on CPU, and the general kernels are not measured).
    general = num_dims > WARP_MAX_DIMS or (basis == "bernstein" and max(resolution) > WARP_MAX_BERNSTEIN_NODES)
    variant = "general" if general else basis
    backend = select_implementation("free_form_deform_points", implementation, platform=platform_of(points), variant=variant)

    return _free_form_deform(points, lattice, origin, extent, point_weights, basis=basis, backend=backend, batched=batched)


@functools.partial(jax.jit, static_argnames=("basis", "backend", "batched"))
def _free_form_deform(points, lattice, origin, extent, point_weights, *, basis: str, backend: Implementation, batched: bool) -> jax.Array:
    """The validated op as one compiled program: an eager call compiles it once per shape, not a
    one-operation program for each step (batch axes, box, weights)."""
    points_b = add_batch_axis(points, batched)
    lattice_b = add_batch_axis(lattice, batched)
    weights_b = add_batch_axis(point_weights, batched)
    # The box is configuration, not a design variable (the reference rejects origin/extent that
    # require grad): stop gradients so no cotangent ever reaches it.
    origin_b = jax.lax.stop_gradient(origin if origin.ndim == 2 else origin[None])
    extent_b = jax.lax.stop_gradient(extent if extent.ndim == 2 else extent[None])

    box_axes = 1 if origin_b.shape[0] == points_b.shape[0] != 1 else 0
    out = map_local_shards(
        functools.partial(_deform, basis=basis, backend=backend),
        (points_b, lattice_b, origin_b, extent_b, weights_b),
        (2, 1, box_axes, box_axes, 2),
        out_axes=2,
    )
    return remove_batch_axis(out, batched)


def _deform(points, lattice, origin, extent, weights, *, basis: str, backend: Implementation) -> jax.Array:
    """Deformed ``(B, N, D)`` points from normalised inputs (independent per design and point)."""
    if backend.is_warp:
        from warp_ffi.ffd import free_form_deform_field

        num_batch, _, num_dims = points.shape
        box = (jnp.broadcast_to(origin, (num_batch, num_dims)), jnp.broadcast_to(extent, (num_batch, num_dims)))
        field = backend.run(functools.partial(free_form_deform_field, basis=basis), functools.partial(_jax_field, basis=basis), points, lattice, *box)
    else:
        field = ffd_field(points, lattice, origin, extent, basis)
    return apply_point_weights(points, field, weights)


def _jax_field(points, lattice, origin, extent, *, basis: str) -> jax.Array:
    return ffd_field(points, lattice, origin, extent, basis)


# --------------------------------------------------------------------------------------------
# Validation


def _check_lattice(points: jax.Array, batched: bool, lattice) -> jax.Array:
    lattice = as_float_array("control_displacements", lattice)
    check_same_dtype("points", points, "control_displacements", lattice)
    check_same_device("points", points, "control_displacements", lattice)
    num_dims = points.shape[-1]
    expected_rank = num_dims + 1 + batched
    if lattice.ndim != expected_rank:
        if lattice.ndim == num_dims + 2 - batched:
            raise ValueError(
                "points and control_displacements must both be unbatched or both be batched: points "
                f"{tuple(points.shape)} need a lattice of rank {expected_rank} "
                f"({'(B, n_1, ..., n_D, D)' if batched else '(n_1, ..., n_D, D)'}), got {tuple(lattice.shape)}"
            )
        raise ValueError(
            f"control_displacements must have rank {expected_rank} "
            f"({'(B, n_1, ..., n_D, D)' if batched else '(n_1, ..., n_D, D)'}) for {num_dims}-D points, "
            f"got shape {tuple(lattice.shape)}"
        )
    if lattice.shape[-1] != num_dims:
        raise ValueError(f"control_displacements must hold {num_dims}-vectors (last axis {num_dims}), got shape {tuple(lattice.shape)}")
    if batched and lattice.shape[0] != points.shape[0]:
        raise ValueError(
            f"control_displacements batch size {lattice.shape[0]} does not match points batch size {points.shape[0]} (batches are aligned, not broadcast)"
        )
    return lattice


def _check_box(name: str, value, points: jax.Array, batched: bool, *, positive: bool) -> jax.Array:
    """A box vector: array ``(D,)`` / aligned ``(B, D)`` (trusted values) or a checked sequence."""
    num_dims = points.shape[-1]
    if not is_array(value):
        values = check_real_sequence(name, value, num_dims, points.dtype, positive=positive)
        return jnp.asarray(values, dtype=points.dtype)
    value = as_float_array(name, value)
    check_same_dtype("points", points, name, value)
    check_same_device("points", points, name, value)
    if value.ndim == 1 and value.shape[0] == num_dims:
        return value
    if value.ndim == 2 and batched and value.shape == (points.shape[0], num_dims):
        return value
    if value.ndim == 2 and not batched:
        raise ValueError(f"{name} of shape {tuple(value.shape)} is batched but points {tuple(points.shape)} are not; use shape ({num_dims},)")
    expected = f"({num_dims},) or ({points.shape[0]}, {num_dims})" if batched else f"({num_dims},)"
    raise ValueError(f"{name} must have shape {expected}, got {tuple(value.shape)}")


# --------------------------------------------------------------------------------------------
# JAX implementation (the specification)


# Per-block budget for live temporaries: 5^3 Bernstein blocks of ~4k points were among the fastest
# measured on CPU (cache-sized intermediates), and memory stays far below the 4 GB target.
_BLOCK_BYTES = 16 * 2**20


@functools.partial(jax.jit, static_argnames=("basis",))
def ffd_field(points: jax.Array, lattice: jax.Array, origin: jax.Array, extent: jax.Array, basis: str) -> jax.Array:
    """Displacement field ``(B, N, D)`` of lattices ``(B, n_1..n_D, D)`` at points ``(B, N, D)``.

    ``origin``/``extent`` are ``(1, D)`` (shared) or ``(B, D)``. Zero outside the box. Jitted
    (``basis`` static) so eager calls compile once per shape instead of dispatching op by op.
    """
    num_batch, num_points, num_dims = points.shape
    resolution = lattice.shape[1:-1]
    itemsize = jnp.dtype(points.dtype).itemsize
    if basis == "bernstein":
        # Live per-query temporaries: the first GEMM's output (prod(n)/n_1 * D) and the per-axis
        # weights, a few times over for the backward pass.
        per_query = math.prod(resolution[1:]) * num_dims + sum(resolution) * 4
    else:
        support = (4 if basis == "bspline" else 2) ** num_dims
        per_query = support * (num_dims + 3)
    block_size = query_block_size(num_points, max(1, num_batch) * per_query * itemsize * 4, budget_bytes=_BLOCK_BYTES)

    def blocked(x, lat, o, e):
        return map_query_blocks(lambda xb: _block_field(xb, lat, o, e, basis), (x,), block_size=block_size)

    def unrolled(x, lat, o, e):
        return _block_field(x, lat, o, e, "unrolled_bernstein")

    if basis == "bernstein" and math.prod(resolution) <= _UNROLLED_MAX_NODES and max(resolution) <= _WRITTEN_OUT_BERNSTEIN_NODES:
        one_design = _fast_value(blocked, unrolled)
    else:
        one_design = blocked

    box_axis = 0 if origin.shape[0] == num_batch and num_batch != 1 else None
    if box_axis is None:
        origin, extent = origin[0], extent[0]
    return jax.vmap(one_design, in_axes=(0, 0, box_axis, box_axis))(points, lattice, origin, extent)


def _block_field(x: jax.Array, lattice: jax.Array, origin: jax.Array, extent: jax.Array, basis: str) -> jax.Array:
    """Field at one block of points ``x`` ``(Q, D)`` for one lattice ``(n_1..n_D, D)``."""
    u = (x - origin) / extent
    zero = jnp.zeros((), x.dtype)
    # NaN compares False, so NaN points count as outside.
    inside = jnp.all((u >= zero) & (u <= jnp.ones((), x.dtype)), axis=-1)
    # Replace outside coordinates before the basis so no inf/NaN reaches the backward pass.
    u = jnp.where(inside[:, None], u, zero)
    if basis == "bernstein":
        field = _bernstein_field(u, lattice)
    elif basis == "unrolled_bernstein":
        field = _bernstein_field_unrolled(u, lattice)
    else:
        field = _local_field(u, lattice, basis)
    return jnp.where(inside[:, None], field, zero)


def bernstein_columns(u: jax.Array, num_nodes: int) -> list[jax.Array]:
    """Bernstein basis of degree ``num_nodes - 1`` at ``u`` ``(Q,)``: a list of ``num_nodes`` ``(Q,)``.

    Built by the de Casteljau recurrence ``B^k_i = (1-u) B^{k-1}_i + u B^{k-1}_{i-1}``: products
    and sums only, so derivatives of every order are finite at ``u = 0`` and ``u = 1`` (the
    closed form's ``u**i`` has a NaN derivative at 0 for ``i = 0``).
    """
    lower = jnp.ones((), u.dtype) - u
    columns = [jnp.ones_like(u)]
    for degree in range(1, num_nodes):
        columns = [lower * columns[0]] + [lower * columns[i] + u * columns[i - 1] for i in range(1, degree)] + [u * columns[degree - 1]]
    return columns


# Up to this many nodes the recurrence is written out column by column (fastest to run); beyond,
# it is a loop over the degree on a (Q, nodes) array: the written-out form has nodes^2 / 2
# operations for XLA to compile (a degree-132 axis compiled for minutes).
_WRITTEN_OUT_BERNSTEIN_NODES = 16


def bernstein_weights(u: jax.Array, num_nodes: int) -> jax.Array:
    """Bernstein weights ``(Q, num_nodes)`` at ``u`` ``(Q,)`` (see :func:`bernstein_columns`)."""
    if num_nodes <= _WRITTEN_OUT_BERNSTEIN_NODES:
        return jnp.stack(bernstein_columns(u, num_nodes), axis=-1)
    lower, upper = (jnp.ones((), u.dtype) - u)[:, None], u[:, None]

    def raise_degree(_, weights):
        # B^k_i = (1-u) B^{k-1}_i + u B^{k-1}_{i-1}; entries above the degree stay zero.
        shifted = jnp.concatenate([jnp.zeros_like(weights[:, :1]), weights[:, :-1]], axis=1)
        return lower * weights + upper * shifted

    start = jnp.zeros(u.shape + (num_nodes,), u.dtype).at[:, 0].set(1)
    return jax.lax.fori_loop(1, num_nodes, raise_degree, start)


# Later axes with at most this many nodes are contracted by an unrolled multiply-add (fastest
# forward); longer axes use one einsum, whose transpose stays cheap for long axes.
_UNROLLED_AXIS_NODES = 6


def _bernstein_field(u: jax.Array, lattice: jax.Array) -> jax.Array:
    """Tensor-product Bernstein sum, contracted one lattice axis at a time.

    The first axis is a GEMM ``(Q, n_1) @ (n_1, n_2..n_D * D)``; each later axis is a per-query
    contraction that shrinks the intermediate by ``n_d``. This never forms the ``(Q, prod(n))``
    weight tensor, which was measured several times slower for 5^3 and 10^3 lattices. (An
    unrolled first axis was faster forward but made the backward pass twice as slow.)
    """
    resolution = lattice.shape[:-1]
    num_queries, num_dims = u.shape
    trailing = math.prod(resolution[1:]) * num_dims
    partial = bernstein_weights(u[:, 0], resolution[0]) @ lattice.reshape(resolution[0], trailing)
    for d in range(1, len(resolution)):
        trailing //= resolution[d]
        partial = partial.reshape(num_queries, resolution[d], trailing)
        if resolution[d] <= _UNROLLED_AXIS_NODES:
            columns = bernstein_columns(u[:, d], resolution[d])
            slabs = jnp.split(partial, resolution[d], axis=1)
            reduced = columns[0][:, None] * slabs[0][:, 0]
            for j in range(1, resolution[d]):
                reduced = reduced + columns[j][:, None] * slabs[j][:, 0]
            partial = reduced
        else:
            partial = jnp.einsum("qj,qjk->qk", bernstein_weights(u[:, d], resolution[d]), partial)
    return partial


# Lattices up to this many nodes evaluate their value with the unrolled sum below (the 5^3
# benchmark lattice has 125; compile time grows with the node count).
_UNROLLED_MAX_NODES = 216


def _fast_value(reference_fn, value_fn):
    """``reference_fn`` whose primal value is computed by the equal but faster ``value_fn``.

    Derivatives of every order (``jvp``, and ``grad`` by transposing the jvp) come from
    ``reference_fn``, whose blocked GEMM form transposes cheaply; ``value_fn`` is only ever
    evaluated for the value. Plain forward calls thus get the fast path with no change to the
    derivative contract.
    """

    @jax.custom_jvp
    def fn(*args):
        return value_fn(*args)

    @fn.defjvp
    def fn_jvp(primals, tangents):
        # The value always comes from ``value_fn``, so a call returns the same bits whether or
        # not it is differentiated (the two forms differ by rounding).
        _, tangent_out = jax.jvp(reference_fn, primals, tangents)
        return value_fn(*primals), tangent_out

    return fn


def _bernstein_field_unrolled(u: jax.Array, lattice: jax.Array) -> jax.Array:
    """The Bernstein sum written out node by node, nested per axis (Horner-like).

    Every term is an elementwise product of ``(Q,)`` columns with a lattice scalar, so XLA fuses
    the whole sum into one vectorised loop over the queries with no intermediate arrays: on CPU
    it is several times faster than the GEMM form at 1e6 points and needs no query blocking.
    Its reverse-mode transpose would be hundreds of separate reductions, hence
    :func:`_fast_value`.
    """
    resolution = lattice.shape[:-1]
    num_dims = lattice.shape[-1]
    columns = [bernstein_columns(u[:, d], n) for d, n in enumerate(resolution)]

    def contract(axis: int, node: tuple[int, ...]) -> list[jax.Array]:
        total: list[jax.Array] | None = None
        for i in range(resolution[axis]):
            if axis == len(resolution) - 1:
                inner = [lattice[node + (i, c)] for c in range(num_dims)]
            else:
                inner = contract(axis + 1, node + (i,))
            term = [columns[axis][i] * value for value in inner]
            total = term if total is None else [a + t for a, t in zip(total, term, strict=True)]
        assert total is not None, "every lattice axis has at least two nodes (checked on entry)"
        return total

    return jnp.stack(contract(0, ()), axis=-1)


def _local_weights(u: jax.Array, num_nodes: int, basis: str) -> tuple[jax.Array, jax.Array]:
    """Per-axis first supporting node ``(Q,)`` int32 and weights ``(Q, K)`` of a local basis."""
    dtype = u.dtype
    one = jnp.ones((), dtype)
    spans = num_nodes - 3 if basis == "bspline" else num_nodes - 1
    s = u * jnp.asarray(spans, dtype)
    # The cell index is a discrete choice: computed on the detached coordinate, clamped so u = 1
    # falls in the last cell. t keeps the gradient of s.
    cell = jnp.clip(jnp.floor(jax.lax.stop_gradient(s)), 0, spans - 1)
    t = s - cell
    cell = cell.astype(jnp.int32)
    if basis == "bspline":
        t2 = t * t
        t3 = t2 * t
        v = one - t
        c = lambda value: jnp.asarray(value, dtype)  # noqa: E731
        weights = jnp.stack([v * v * v, c(3) * t3 - c(6) * t2 + c(4), c(-3) * t3 + c(3) * t2 + c(3) * t + one, t3], axis=-1) / c(6)
        return cell, weights
    if basis == "linear":
        upper = t
    elif basis == "cubic_hermite":
        upper = t * t * (jnp.asarray(3, dtype) - jnp.asarray(2, dtype) * t)
    else:  # quintic_hermite
        upper = t * t * t * (t * (t * jnp.asarray(6, dtype) - jnp.asarray(15, dtype)) + jnp.asarray(10, dtype))
    return cell, jnp.stack([one - upper, upper], axis=-1)


def _local_field(u: jax.Array, lattice: jax.Array, basis: str) -> jax.Array:
    """Gather the ``K^D`` supporting nodes of each query and sum them with tensor-product weights."""
    resolution = lattice.shape[:-1]
    num_queries, num_dims = u.shape
    index = jnp.zeros((num_queries, 1), jnp.int32)
    weight = jnp.ones((num_queries, 1), u.dtype)
    for d in range(num_dims):
        cell, axis_weights = _local_weights(u[:, d], resolution[d], basis)
        support = index.shape[1] * axis_weights.shape[1]
        axis_index = cell[:, None] + jnp.arange(axis_weights.shape[1], dtype=jnp.int32)
        index = (index[:, :, None] * resolution[d] + axis_index[:, None, :]).reshape(num_queries, support)
        weight = (weight[:, :, None] * axis_weights[:, None, :]).reshape(num_queries, support)
    nodes = lattice.reshape(math.prod(resolution), num_dims)[index]  # (Q, K^D, D)
    return jnp.einsum("qk,qkc->qc", weight, nodes)
