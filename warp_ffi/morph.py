"""Compact Wendland-C2 Shepard morphing on Warp: hash-grid kernels, adjoint kernel, custom_vjp.

Inputs arrive validated and normalised (no checks here): points ``(B, N, D)``, controls and
displacements ``(B, C, D)``, radius ``(B, C)``, one float dtype, ``N, C > 0``.

Compact support pays: a spatial hash grid, built in plain JAX (so it traces under ``jit`` and
``vmap`` on CPU and CUDA), lets each point visit only the controls of its neighbour cells.

* Cell size ``h`` = the largest ``|radius|`` of the design (a traced value), widened by 1/64 so
  float rounding of ``floor(x / h)`` can never move an in-range control out of the neighbour
  cells, and clamped from below so cell coordinates fit int32. The grid uses the first three
  coordinates (lower ``D`` is zero-padded to three; higher ``D`` keeps the extra coordinates in
  the distance but not in the grid, which is still exact).
* Controls are sorted by ``hash(cell) mod T`` (static power-of-two table ``T >= 2C``), which
  also gives the bucket ranges. Points are sorted by the same key, so consecutive points walk
  the same buckets (a 2x speed-up from cache locality alone). Both sorts are
  ``_grid.counting_sort`` (a serial counting sort in Warp on CPU, ``argsort`` elsewhere).
* A kernel visits the 27 neighbour cells of its point, skipping those farther than one cell
  width, walks each bucket with a squared-distance pre-test on packed ``(x, y, z, 1 / r^2)`` boxes,
  and skips controls whose stored cell differs from the visited one, so hash collisions never
  count a control twice.
* An infinite radius gives an infinite cell: every finite point and control share cell zero and
  the search degenerates to brute force, which is exact.

The forward kernel makes one pass over the candidates, keeping the Shepard sums relative to the
nearest active control seen so far (rescaled when a nearer one appears), and saves the reference
index, its normalised distance, the denominator, the coincidence count and the correction
``u - d_ref`` for the adjoint kernel, which recomputes each candidate's weight and scatters
control gradients. On CPU a launch is split into chunks of points run by a thread pool (Warp's
CPU launches are single-threaded and its CPU atomics are plain adds, so each worker accumulates
control gradients in a private buffer, summed afterwards). Under ``vmap`` the calls run
sequentially over the batch. Arrays are flattened over the batch (1-D arrays index faster than
2-D ones in Warp's CPU code).
"""

import math
from typing import Any, no_type_check

import jax
import jax.numpy as jnp

from ._grid import counting_sort
from ._wrap import KernelFamily, scalars, vectors, with_adjoint
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["morph_field", "hash_grid"]

GRID_DIMS = 3
CELL_SLACK = 2.0**-6  # relative widening of the cell over the largest radius
REJECT_SLACK = wp.constant(2.0**-8)  # relative widening of the squared-distance pre-test
CELL_LIMIT = 2**29  # |cell coordinate| bound (neighbours stay inside int32)
FAST_MIN_DIST2 = wp.constant(2.0**-100)  # squared distances above this are normal in float32


# ---------------------------------------------------------------------------------------------
# Warp functions and kernels.


@wp.func
@no_type_check
def _wendland(q: Any):
    one = type(q)(1.0)
    a = one - q
    a2 = a * a
    return a2 * a2 * (type(q)(4.0) * q + one)


@wp.func
@no_type_check
def _wendland_derivative(q: Any):
    a = type(q)(1.0) - q
    return type(q)(-20.0) * q * a * a * a


@wp.func
@no_type_check
def _block_hash(sx: wp.int32, sy: wp.int32, sz: wp.int32) -> wp.uint32:
    # Additive combination then an xorshift-multiply mix: XOR-of-products hashes collide
    # heavily on small integer grids, this one fills the table like a random function.
    h = wp.uint32(sx) * wp.uint32(0x2545F491) + wp.uint32(sy) * wp.uint32(0x4F6CDD1D) + wp.uint32(sz) * wp.uint32(0x62A9D9ED)
    h = h ^ (h >> wp.uint32(15))
    h = h * wp.uint32(0x2C1B3C6D)
    return h ^ (h >> wp.uint32(12))


@wp.func
@no_type_check
def _split(c: wp.int32):
    """Floor division of a cell coordinate by 3 and its residue in {0, 1, 2}."""
    r = c % 3
    if r < 0:
        r += 3
    return (c - r) / 3, r


@wp.func
@no_type_check
def _shift(block: wp.int32, residue: wp.int32, offset: wp.int32):
    """Block and residue of the cell ``offset`` (-1, 0, 1) away."""
    r = residue + offset
    if r < 0:
        return block - 1, r + 3
    if r > 2:
        return block + 1, r - 3
    return block, r


@wp.func
@no_type_check
def _classify(diff: Any, r: Any, inv_r2: Any):
    """``(status, q, fast)``: status 0 outside, 1 active (``0 < q < 1``), 2 exact coincidence.

    Same rules as the JAX path: ``s = diff / r`` per component, non-finite -> outside, all-zero
    -> coincidence, hypot-like norm for tiny components. ``fast`` marks the common case (a
    normal radius, ``inv_r2 = 1 / r^2 > 0``, and normal squared distances) where
    ``q^2 = |diff|^2 / r^2`` is used directly.
    """
    two = type(r)(2.0)
    if inv_r2 > type(r)(0.0):
        dist2 = wp.dot(diff, diff)
        q2 = dist2 * inv_r2
        if dist2 >= type(r)(FAST_MIN_DIST2) and q2 >= type(r)(FAST_MIN_DIST2):
            if q2 < type(r)(1.0):
                return int(1), wp.sqrt(q2), True
            return int(0), two, True
    s = diff / r
    if not wp.isfinite(s):
        return int(0), two, False
    m = wp.max(wp.abs(s))
    if m == type(r)(0.0):
        return int(2), type(r)(0.0), False
    if m >= type(r)(1.0):
        return int(0), two, False
    t = s / m
    q = m * wp.sqrt(wp.dot(t, t))
    if q < type(r)(1.0):
        return int(1), q, False
    return int(0), two, False


@wp.func
@no_type_check
def _classify_candidate(x: Any, controls: wp.array(dtype=Any), radius: wp.array(dtype=Any), boxes: wp.array(dtype=Any), j: int):
    """``_classify`` for control ``j`` once it passes the box pre-test (else status 0), and its ``1 / r^2``.

    The pre-test's squared distance is reused when ``D = 3``.
    """
    box = boxes[j]
    e0 = x[0] - box[0]
    e1 = x[1] - box[1]
    e2 = x[2] - box[2]
    dist2 = e0 * e0 + e1 * e1 + e2 * e2
    inv_r2 = box[3]
    two = type(dist2)(2.0)
    if not (dist2 * inv_r2 <= type(dist2)(1.0) + type(dist2)(REJECT_SLACK)):
        return int(0), two, False, inv_r2
    if len(x) == 3:
        q2 = dist2 * inv_r2
        if inv_r2 > type(dist2)(0.0) and dist2 >= type(dist2)(FAST_MIN_DIST2) and q2 >= type(dist2)(FAST_MIN_DIST2):
            if q2 < type(dist2)(1.0):
                return int(1), wp.sqrt(q2), True, inv_r2
            return int(0), two, True, inv_r2
    status, q, fast = _classify(x - controls[j], radius[j], inv_r2)
    return status, q, fast, inv_r2


@wp.func
@no_type_check
def _distance_gradient(diff: Any, r: Any, q: Any):
    """``dq / d(diff)`` for ``q = |diff / r|`` in the slow (tiny or unusual) cases."""
    s = diff / r
    t = s / wp.max(wp.abs(s))
    return (t / wp.sqrt(wp.dot(t, t))) / r


@wp.func
@no_type_check
def _cell_gap(offset: int, f: Any):
    """Squared distance, in cell units, from a point at fraction ``f`` of its cell to a neighbour."""
    if offset < 0:
        return f * f
    if offset > 0:
        return (type(f)(1.0) - f) * (type(f)(1.0) - f)
    return type(f)(0.0)


@wp.func
@no_type_check
def _cell_fraction(x: Any, h: Any, cell: int, limit: Any):
    """Position of ``x`` inside its cell in ``[0, 1]``; ``-1`` where rounding makes it unreliable."""
    y = x / h
    if wp.abs(y) > limit:
        return type(x)(-1.0)
    return wp.clamp(y - type(x)(cell), type(x)(0.0), type(x)(1.0))


@wp.func
@no_type_check
def _skip_cell(neighbour: int, f0: Any, f1: Any, f2: Any):
    """Whether neighbour cell ``neighbour`` (0..26) is out of reach of every support.

    Cells are wider than the largest radius by ``CELL_SLACK``, so a gap of one cell (squared
    distance >= 1 in cell units) is out of reach with room for rounding.
    """
    if f0 < type(f0)(0.0) or f1 < type(f0)(0.0) or f2 < type(f0)(0.0):
        return False
    gap = _cell_gap(neighbour % 3 - 1, f0) + _cell_gap((neighbour // 3) % 3 - 1, f1) + _cell_gap(neighbour // 9 - 1, f2)
    return gap >= type(f0)(1.0)


@wp.func
@no_type_check
def _neighbour_bucket(blocks: wp.vec3i, residues: wp.vec3i, neighbour: int, mask: wp.uint32):
    """Bucket (in one design's table) of neighbour ``neighbour`` (0..26) of a cell.

    The key is ``hash(3x3x3 block) * 32 + residue index``: the 27 neighbours of any cell have 27
    distinct residue triples, hence 27 distinct buckets, so no control is ever visited twice.
    """
    bx, rx = _shift(blocks[0], residues[0], neighbour % 3 - 1)
    by, ry = _shift(blocks[1], residues[1], (neighbour // 3) % 3 - 1)
    bz, rz = _shift(blocks[2], residues[2], neighbour // 9 - 1)
    return wp.int32((_block_hash(bx, by, bz) << wp.uint32(5)) & mask) + rx + 3 * ry + 9 * rz


@wp.func
@no_type_check
def _grid_position(x: Any, cell: wp.vec3i, scale: Any):
    """Where point ``x`` sits in its cell ``cell``: per-axis fractions (see ``_cell_fraction``),
    and the cell's 3x3x3 block and residue (see ``_neighbour_bucket``)."""
    f0 = _cell_fraction(x[0], scale[0], cell[0], scale[1])
    f1 = _cell_fraction(x[1], scale[0], cell[1], scale[1])
    f2 = _cell_fraction(x[2], scale[0], cell[2], scale[1])
    bx, rx = _split(cell[0])
    by, ry = _split(cell[1])
    bz, rz = _split(cell[2])
    return f0, f1, f2, wp.vec3i(bx, by, bz), wp.vec3i(rx, ry, rz)


@wp.func
@no_type_check
def _neighbour_controls(
    bucket_offsets: wp.array(dtype=wp.int32), blocks: wp.vec3i, residues: wp.vec3i, neighbour: int, table_size: int, b: int,
    f0: Any, f1: Any, f2: Any,
):  # fmt: skip
    """The range of sorted controls in neighbour cell ``neighbour`` (empty when out of reach)."""
    if _skip_cell(neighbour, f0, f1, f2):
        return int(0), int(0)
    key = b * (table_size + 1) + _neighbour_bucket(blocks, residues, neighbour, wp.uint32(table_size - 1))
    return bucket_offsets[key], bucket_offsets[key + 1]


@wp.kernel
@no_type_check
def _forward_kernel(
    points: wp.array(dtype=Any), point_cells: wp.array(dtype=wp.vec3i), controls: wp.array(dtype=Any),
    displacements: wp.array(dtype=Any), radius: wp.array(dtype=Any), boxes: wp.array(dtype=Any),
    bucket_offsets: wp.array(dtype=wp.int32), grid_scale: wp.array(dtype=Any), num_points: wp.int32, table_size: wp.int32,
    offset: wp.int32, field: wp.array(dtype=Any), ref_index: wp.array(dtype=wp.int32), ref_q: wp.array(dtype=Any),
    denominator: wp.array(dtype=Any), coincident_count: wp.array(dtype=wp.int32), correction: wp.array(dtype=Any),
):  # fmt: skip
    b, t = wp.tid()
    pi = b * num_points + t + offset
    x = points[pi]
    zero = field.dtype()
    one = radius.dtype(1.0)

    count = int(0)
    coincident_sum = zero
    ref = int(-1)
    q_ref = one
    phi_ref = one
    inv_phi_ref = one
    d_ref = zero
    # Shepard sums scaled so that the current reference has weight one:
    # weight_sum = sum_{j != ref} w_j, weighted = sum_{j != ref} w_j (d_j - d_ref).
    weight_sum = radius.dtype(0.0)
    weighted = zero

    f0, f1, f2, blocks, residues = _grid_position(x, point_cells[pi], grid_scale[b])
    for neighbour in range(27):  # one loop: nested 3-loops would be unrolled 27 times
        start, end = _neighbour_controls(bucket_offsets, blocks, residues, neighbour, table_size, b, f0, f1, f2)
        for j in range(start, end):
            status, q, fast, inv_r2 = _classify_candidate(x, controls, radius, boxes, j)
            if status == 2:
                count += 1
                coincident_sum = coincident_sum + displacements[j]
            elif status == 1 and count == 0:
                d = displacements[j]
                p = _wendland(q)
                if ref < 0:
                    ref = j
                    q_ref = q
                    phi_ref = p
                    inv_phi_ref = one / p
                    d_ref = d
                elif q < q_ref:
                    # New reference: the old sums (and the old reference) get weight sigma.
                    ratio = q / q_ref
                    sigma = ratio * ratio * phi_ref / p
                    weighted = sigma * (weighted + (one + weight_sum) * (d_ref - d))
                    weight_sum = sigma * (one + weight_sum)
                    ref = j
                    q_ref = q
                    phi_ref = p
                    inv_phi_ref = one / p
                    d_ref = d
                else:
                    ratio = q_ref / q
                    w = ratio * ratio * p * inv_phi_ref
                    weight_sum = weight_sum + w
                    weighted = weighted + w * (d - d_ref)

    u = zero
    delta = zero
    den = one
    if count > 0:
        u = coincident_sum / radius.dtype(count)
        ref = -1
    elif ref >= 0:
        # Same two regimes as the JAX path: d_ref + correction near the controls, the plain
        # quotient where the background dominates (there d_ref + correction would cancel).
        background = q_ref * q_ref / phi_ref
        total = one + weight_sum
        den = background + total
        if background <= total:
            delta = (weighted - background * d_ref) / den
            u = d_ref + delta
        else:
            u = (total * d_ref + weighted) / den
            delta = u - d_ref
    field[pi] = u
    ref_index[pi] = ref
    ref_q[pi] = q_ref
    denominator[pi] = den
    coincident_count[pi] = count
    correction[pi] = delta


@wp.kernel
@no_type_check
def _backward_kernel(
    points: wp.array(dtype=Any), point_cells: wp.array(dtype=wp.vec3i), controls: wp.array(dtype=Any),
    displacements: wp.array(dtype=Any), radius: wp.array(dtype=Any), boxes: wp.array(dtype=Any),
    bucket_offsets: wp.array(dtype=wp.int32), grid_scale: wp.array(dtype=Any), ref_index: wp.array(dtype=wp.int32),
    ref_q: wp.array(dtype=Any), denominator: wp.array(dtype=Any), coincident_count: wp.array(dtype=wp.int32),
    correction: wp.array(dtype=Any), field_bar: wp.array(dtype=Any), num_points: wp.int32, table_size: wp.int32, offset: wp.int32,
    points_bar: wp.array(dtype=Any), controls_bar: wp.array(dtype=Any), displacements_bar: wp.array(dtype=Any),
    radius_bar: wp.array(dtype=Any),
):  # fmt: skip
    b, t = wp.tid()
    pi = b * num_points + t + offset
    zero = points_bar.dtype()
    one = radius.dtype(1.0)
    count = coincident_count[pi]
    ref = ref_index[pi]
    x_bar = zero
    if count > 0 or ref >= 0:
        x = points[pi]
        g = field_bar[pi]
        coincident_scale = one
        if count > 0:
            coincident_scale = one / radius.dtype(count)
        q_ref = ref_q[pi]
        inv_phi_ref = one / _wendland(q_ref)
        inv_den = one / denominator[pi]
        delta = correction[pi]
        d_ref = zero
        if ref >= 0:
            d_ref = displacements[ref]

        f0, f1, f2, blocks, residues = _grid_position(x, point_cells[pi], grid_scale[b])
        for neighbour in range(27):
            start, end = _neighbour_controls(bucket_offsets, blocks, residues, neighbour, table_size, b, f0, f1, f2)
            for j in range(start, end):
                status, q, fast, inv_r2 = _classify_candidate(x, controls, radius, boxes, j)
                if count > 0:
                    if status == 2:
                        displacements_bar[j] = displacements_bar[j] + coincident_scale * g
                elif status == 1:
                    diff = x - controls[j]
                    r = radius[j]
                    # u = sum a_j d_j / (1 + sum a_j) with a_j = phi_j / q_j^2; scaled by
                    # b = q_ref^2 / phi_ref: du/dd_j = w_j / den, du/dq_j = (d_j - u) b a'(q_j) / den,
                    # b a'(q_j) = (q_ref / q_j)^2 (phi'_j - 2 phi_j / q_j) / phi_ref.
                    d = displacements[j]
                    # The fast path has q >= 2**-50, so 1 / q is safe there.
                    inv_q = one
                    ratio = one
                    if fast:
                        inv_q = one / q
                        ratio = q_ref * inv_q
                    else:
                        ratio = q_ref / q
                    scaled = ratio * ratio * inv_phi_ref
                    p = _wendland(q)
                    displacements_bar[j] = displacements_bar[j] + (scaled * p * inv_den) * g
                    coef = wp.dot(g, (d - d_ref) - delta) * inv_den * scaled
                    diff_bar = zero
                    if fast:
                        q_bar = coef * (_wendland_derivative(q) - radius.dtype(2.0) * p * inv_q)
                        diff_bar = (q_bar * inv_q * inv_r2) * diff
                        radius_bar[j] = radius_bar[j] - q_bar * q * r * inv_r2
                    else:
                        q_bar = coef * _wendland_derivative(q) - radius.dtype(2.0) * (coef * p) / q
                        diff_bar = q_bar * _distance_gradient(diff, r, q)
                        radius_bar[j] = radius_bar[j] - q_bar * q / r
                    x_bar = x_bar + diff_bar
                    controls_bar[j] = controls_bar[j] - diff_bar
    points_bar[pi] = x_bar


# ---------------------------------------------------------------------------------------------
# Kernel families: CPU launches split over threads (chunked), arrays flattened over the batch.


def _types(s, dim: int) -> dict:
    """The Warp types of the kernels' generic arguments for scalar ``s`` and ``D = dim >= 3``."""
    return {
        **{name: vectors(s, dim) for name in ("points", "controls", "displacements", "field", "correction", "field_bar")},
        **{name: vectors(s, dim) for name in ("points_bar", "controls_bar", "displacements_bar")},
        **{name: scalars(s) for name in ("radius", "ref_q", "denominator", "radius_bar")},
        "boxes": vectors(s, 4),
        "grid_scale": vectors(s, 2),
    }


_AUX_NAMES = ("ref_index", "ref_q", "denominator", "coincident_count", "correction")
_GRAD_NAMES = ("points_bar", "controls_bar", "displacements_bar", "radius_bar")
# The common overloads are registered up front: each new overload set recompiles the module (~3 s).
_forward = KernelFamily(_forward_kernel, _types, outputs=("field", *_AUX_NAMES), chunked=True, variants=((GRID_DIMS,),))
_backward = KernelFamily(_backward_kernel, _types, outputs=_GRAD_NAMES, accumulate=_GRAD_NAMES[1:], chunked=True, variants=((GRID_DIMS,),))


# ---------------------------------------------------------------------------------------------
# The hash grid (plain JAX) and the custom_vjp wrapper.


def _bucket_keys(cells: jax.Array, table_size: int) -> jax.Array:
    """Bucket of each cell: the same uint32 arithmetic as ``_neighbour_bucket``."""
    blocks = jnp.floor_divide(cells, 3).astype(jnp.uint32)
    residues = jnp.mod(cells, 3)
    h = blocks[..., 0] * jnp.uint32(0x2545F491) + blocks[..., 1] * jnp.uint32(0x4F6CDD1D) + blocks[..., 2] * jnp.uint32(0x62A9D9ED)
    h = h ^ (h >> 15)
    h = h * jnp.uint32(0x2C1B3C6D)
    h = h ^ (h >> 12)
    key = ((h << 5) & jnp.uint32(table_size - 1)).astype(jnp.int32)
    return key + residues[..., 0] + 3 * residues[..., 1] + 9 * residues[..., 2]


def table_size_for(num_controls: int) -> int:
    """Static hash-table size: 32 buckets (27 used) per 3x3x3 block, at least C / 2 block slots."""
    return 16 * (1 << max(2, math.ceil(math.log2(num_controls))))


def hash_grid(points: jax.Array, controls: jax.Array, radius: jax.Array):
    """Spatial hash of ``(B, C, D>=3)`` controls for ``(B, N, D)`` points (nothing differentiated).

    Returns ``(point_order, control_order, grid)``: the permutations sorting each design's points
    and controls by bucket, and the kernels' grid arrays, flattened over the batch and in sorted
    order: ``point_cells`` ``(B*N, 3)``, pre-test ``boxes`` ``(B*C, 4)`` = ``(x, y, z, 1 / r^2)``
    (the last entry zero, i.e. no pre-test, where it could be inexact), ``bucket_offsets``
    ``(B*(T+1),)`` (each design's bucket ranges as global indices into the sorted controls) and
    ``grid_scale`` ``(B, 2)`` = (cell size, coordinate bound under which cell culling is exact).
    """
    points, controls, radius = (jax.lax.stop_gradient(a) for a in (points, controls, radius))
    dtype = points.dtype
    info = jnp.finfo(dtype)
    eps = float(info.eps)
    num_batch, num_controls = controls.shape[:2]
    table_size = table_size_for(num_controls)
    p3, c3 = points[..., :GRID_DIMS], controls[..., :GRID_DIMS]

    size = jnp.abs(radius)
    size = jnp.max(jnp.where(jnp.isnan(size), 0, size), axis=1)

    def finite_max(a):
        a = jnp.abs(a)
        return jnp.max(jnp.where(jnp.isfinite(a), a, 0), axis=(1, 2))

    extent = jnp.maximum(finite_max(p3), finite_max(c3))
    # floor(x / h) then moves an in-range control by at most one cell (see module docstring).
    floor = extent * max(eps * 2.0**8, 2.0**-28)
    cell = jnp.maximum(size * (1 + CELL_SLACK), jnp.maximum(floor, info.tiny))

    def cells_of(a):
        c = jnp.floor(a / cell[:, None, None])
        c = jnp.clip(jnp.where(jnp.isnan(c), 0, c), -CELL_LIMIT, CELL_LIMIT)
        return c.astype(jnp.int32)

    point_cells, control_cells = cells_of(p3), cells_of(c3)
    _, point_order = counting_sort(_bucket_keys(point_cells, table_size), table_size)
    control_offsets, control_order = counting_sort(_bucket_keys(control_cells, table_size), table_size)
    offsets = control_offsets + jnp.arange(num_batch, dtype=jnp.int32)[:, None] * num_controls

    r2 = jnp.square(radius)
    usable = jnp.isfinite(r2) & (r2 >= info.tiny * 2.0**24) & (r2 <= info.max / 2)
    one = jnp.ones((), dtype)
    inv_r2 = jnp.where(usable, one / jnp.where(usable, r2, one), 0)
    boxes = jnp.concatenate([c3, inv_r2[..., None]], axis=-1)
    # Cell fractions y - floor(y) of coordinates y = x / h up to this bound are exact to 2**-9.
    grid_scale = jnp.stack([cell, jnp.full_like(cell, 2.0**-9 / eps)], axis=-1)

    def flat_sorted(a, order):
        return jnp.take_along_axis(a, order[..., None], axis=1).reshape(-1, a.shape[-1])

    grid = (flat_sorted(point_cells, point_order), flat_sorted(boxes, control_order), offsets.reshape(-1), grid_scale)
    return point_order, control_order, grid


@jax.jit
def morph_field(points: jax.Array, controls: jax.Array, displacements: jax.Array, radius: jax.Array) -> jax.Array:
    """The Shepard field ``u`` ``(B, N, D)`` computed by the Warp kernels (first-order VJP)."""
    num_batch, num_points, dim = points.shape
    if dim < GRID_DIMS:
        pad = [(0, 0), (0, 0), (0, GRID_DIMS - dim)]
        points, controls, displacements = (jnp.pad(a, pad) for a in (points, controls, displacements))
    point_order, control_order, grid = hash_grid(points, controls, radius)

    def flat_sorted(a, order):
        return jnp.take_along_axis(a, order[..., None], axis=1).reshape(-1, a.shape[-1])

    field = _field(
        flat_sorted(points, point_order),
        flat_sorted(controls, control_order),
        flat_sorted(displacements, control_order),
        jnp.take_along_axis(radius, control_order, axis=1).reshape(-1),
        grid,
    )
    # Undo the point sort with the inverse permutation (a gather, whose transpose is a scatter).
    inverse = jax.vmap(lambda o: jnp.zeros_like(o).at[o].set(jnp.arange(num_points, dtype=o.dtype)))(point_order)
    field = jnp.take_along_axis(field.reshape(num_batch, num_points, -1), inverse[..., None], axis=1)
    return field[..., :dim]


def _grid_inputs(points, controls, displacements, radius, grid):
    """The kernels' leading inputs, their sizes ``(N, T)`` and the launch ``(B, N)``."""
    point_cells, boxes, bucket_offsets, grid_scale = grid
    num_batch = grid_scale.shape[0]
    num_points, table_size = points.shape[0] // num_batch, bucket_offsets.shape[0] // num_batch - 1
    inputs = (points, point_cells, controls, displacements, radius, boxes, bucket_offsets, grid_scale)
    return inputs, (num_points, table_size), (num_batch, num_points)


def _field_forward(points, controls, displacements, radius, grid):
    inputs, sizes, launch = _grid_inputs(points, controls, displacements, radius, grid)
    shapes = dict.fromkeys(_forward.outputs, points.shape[:1])
    field, *aux = _forward(points.dtype, points.shape[-1])(*inputs, *sizes, launch=launch, shapes=shapes)
    return field, aux


def _field_adjoint(args, aux, field_bar):
    points, controls = args[:2]
    inputs, sizes, launch = _grid_inputs(*args)
    shapes = dict(zip(_GRAD_NAMES, (points.shape[:1], controls.shape[:1], controls.shape[:1], controls.shape[:1]), strict=True))
    return _backward(points.dtype, points.shape[-1])(*inputs, *aux, field_bar, *sizes, launch=launch, shapes=shapes)


# The grid is topology (positions stopped upstream): not differentiated.
_field = with_adjoint(_field_forward, _field_adjoint, constant_argnums=(4,))
