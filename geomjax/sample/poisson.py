"""Poisson-disk samples on a triangle surface: parallel dart throwing, exact sample elimination."""

from __future__ import annotations

import functools
import math
import numbers
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._blocking import map_query_blocks, query_block_size
from .._dispatch import platform_of, select_implementation
from .._errors import raises_documented_errors
from .._hash_grid import cell_order, check_cell_range, grid_resolution, table_dims
from .._hashing import lowbias32
from .._projection import SurfaceProjector
from .._sharding import outside_context_mesh
from .._validate import check_allocatable, check_choice, check_host_surface, check_host_vertex_field, check_integer, check_real_scalar

__all__ = ["mesh_poisson_disk_sample"]

_NAME = "mesh_poisson_disk_sample"
MODES = ("dart_throwing", "weighted_sample_elimination")


# Conflicts are tested against squared radii widened by this factor: it exceeds the float32
# rounding of the squared distances and radii, so no accepted pair is ever closer than its radius.
CONFLICT_WIDENING = 1.0 + 2.0**-18
ITERATION_SEED_STRIDE = 104729  # seed of iteration k: random_seed + 104729 k (as the reference)
_GOLDEN = 0x9E3779B9  # stream separation of the counter-based random numbers
# Grid cells are twice the largest query radius: a query visits 1 to 8 cells instead of 27 (each
# visit costs Warp three integer divisions), about twice as fast overall.
GRID_CELL_FACTOR = 2.0

# Weighted sample elimination (Yuksel 2015, with Open3D's constants).
POOL_FACTOR = 5.0
WEIGHT_EXPONENT = 8  # alpha
WEIGHT_LIMIT_BETA = 0.65
WEIGHT_LIMIT_GAMMA = 1.5
# Pair weights are integers: multiples of w_max / 2**20 (fewer bits when a sample has so many
# neighbours that its sum could overflow int32).
WEIGHT_BITS = 20
# Relaxation of the eliminated set: steps of neighbour repulsion, each projected onto the surface.
RELAXATION_STEPS = 1
RELAXATION_RATE = 0.3  # push per unit summed force, in r_max
RELAXATION_LIMIT = 0.25  # largest move per step, in r_max


@raises_documented_errors
@outside_context_mesh
def mesh_poisson_disk_sample(
    mesh_vertices: Float[Array, "num_vertices 3"],
    mesh_indices: Int[Array, "num_faces 3"] | Int[Array, " num_indices"],
    min_distance: float = 0.02,
    per_vertex_radius: Float[Array, " num_vertices"] | None = None,
    batch_size: int = 131072,
    max_points: int = 2_000_000,
    max_iterations: int = 64,
    random_seed: int = 42,
    hash_grid_resolution: int | tuple[int, int, int] | Int[Array, "3"] = 128,
    mode: str = "dart_throwing",
    target_num_points: int | None = None,
    *,
    implementation: str | None = None,
) -> Float[Array, "num_samples 3"]:
    """Blue-noise samples on a triangle surface.

    Candidates (both modes) are uniform on the surface: a triangle drawn from the normalised
    cumulative-area distribution, then barycentric weights ``(1 - sqrt(u1), sqrt(u1) u2,
    sqrt(u1) (1 - u2))``, computed in float32 from a counter-based hash of the seed and the
    candidate index (the same numbers on every backend and platform). Each candidate also gets
    a radius (``min_distance``, or ``per_vertex_radius`` interpolated with the same weights) and
    a random 32-bit priority.

    ``mode="dart_throwing"``: parallel dart throwing. Iteration ``k`` (seed ``random_seed +
    104729 k``) draws ``batch_size`` candidates, kills every candidate closer than its own
    radius to an accepted sample, then resolves conflicts among the survivors in one round: a
    candidate dies if a live candidate closer than ``min(r_i, r_j)`` has a higher priority (ties:
    the higher index). The survivors are accepted in index order, up to ``max_points``. The loop
    stops after an iteration that accepts nothing, at ``max_points`` or after
    ``max_iterations``. The minimum distance holds exactly: any two returned samples are at
    least ``min(r_i, r_j)`` apart (``min_distance`` for a constant radius), measured on the
    returned float32 coordinates (conflicts are tested with squared radii widened by
    ``2**-18``, more than float32 rounding). The reference's final clean-up pass is therefore
    unnecessary and omitted.

    ``mode="weighted_sample_elimination"``: Yuksel's weighted sample elimination, exact, then one
    relaxation step. A pool of ``max(T + 1, round(5 T))`` uniform candidates (``T =
    target_num_points``, default ``max_points``), listed cell by cell, is reduced to exactly
    ``T`` samples by repeatedly removing the sample of largest weight, one at a time, with an
    indexed max-heap. With ``r_max = 2 sqrt(A / (2 sqrt(3) T))`` (``A`` the surface area) and
    ``r_min = 0.65 r_max (1 - (T / pool)^1.5)``, a pair closer than ``r_max`` weighs ``(1 -
    max(d, r_min) / r_max)^8`` and a sample's weight is the sum over its surviving neighbours.
    Pair weights are held as integers (multiples of ``2**-20`` of the largest pair weight) so
    every update is exact and ties go to the lowest index, on every backend. Unlike the
    reference, which deletes samples in batches (an approximation), this is the exact algorithm
    (the one of Open3D's ``sample_points_poisson_disk``). The survivors then take one
    relaxation step: each moves away from its neighbours closer than ``r_max`` (pair force
    ``(1 - d / r_max)^2`` along the separation, summed, times ``0.3 r_max``, at most ``0.25
    r_max``) and is projected back onto the surface. This raises the mean and minimum
    nearest-neighbour distances by about 2 to 3% over the exact elimination (measured by
    ``benchmarks/bench_sampling_remesh.py``); the samples are then no longer pool points.
    ``per_vertex_radius`` is ignored (with a warning); ``min_distance``, ``batch_size`` and
    ``max_iterations`` are validated but unused.

    Args:
        mesh_vertices: ``(V, 3)`` float32 or float64, finite (cast to float32, as the reference).
        mesh_indices: triangle indices of any integer dtype (not bool), ``(F, 3)`` or flat
            ``(3 F,)``, ``F >= 1``, each in ``[0, V)``. The total area must be positive.
        min_distance: constant Poisson radius, a positive finite real.
        per_vertex_radius: optional ``(V,)`` float32/float64 positive finite radii (adaptive
            dart throwing), on the device of ``mesh_vertices``.
        batch_size: candidates per dart-throwing iteration, integer ``>= 1``.
        max_points: cap on the number of samples, integer ``>= 1``.
        max_iterations: dart-throwing iterations, integer ``>= 1``.
        random_seed: integer seed (used modulo ``2**32``); equal seeds give equal samples.
        hash_grid_resolution: dimensions of the spatial hash table: one positive integer or
            three (a sequence or a concrete integer array). A performance knob: the table is
            clamped to the cells the surface spans, and to at least 3 per axis.
        mode: ``"dart_throwing"`` or ``"weighted_sample_elimination"``.
        target_num_points: number of samples of the elimination mode, integer ``>= 1`` or
            ``None`` (then ``max_points``).
        implementation: ``"warp"``, ``"jax"`` (also ``"torch"``) or ``None``. Both share the
            candidates and pair weights. Warp finds neighbours with a spatial hash grid (both
            CPU cores) and runs the elimination heap in one compiled CPU thread. The JAX path is
            a brute-force reference for small inputs: each iteration compares every candidate
            with every accepted sample and every other candidate, and the elimination takes an
            ``argmax`` over the pool per removal. ``None`` picks Warp on every platform when
            warp-lang is installed (``benchmarks/bench_sampling_remesh.py`` measures it on CPU),
            JAX otherwise.

    Returns:
        ``(n_samples, 3)`` float32 sample positions on the surface, on the vertices' device.
        Output order carries no meaning beyond determinism.

    Raises:
        TypeError: non-float vertices or radii, non-integer or bool indices, a non-real
            ``min_distance``, a non-integer count, seed or resolution, traced inputs (the
            output size depends on the data, so this runs eagerly: call it outside ``jit``).
        ValueError: bad shapes, indices out of range, non-finite vertices, non-positive or
            non-finite radii, counts below 1, an unknown ``mode``, a zero-area surface, a
            radius too small for the coordinate range (more than ``2**30`` grid cells), or a
            ``batch_size`` (dart throwing) or ``target_num_points`` (elimination, whose pool
            holds 5x as many candidates) beyond ``2**31 - 1`` candidates or the memory the
            device has left (checked before anything is allocated), an input split across
            processes (a multi-host array: this runs on one host; replicated arrays and arrays
            on several local devices are read from one device, also under ``jax.set_mesh``).
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Not differentiable (samples are random draws; no gradient is defined).

    Example:
        >>> import numpy as np
        >>> from geomjax import icosphere, mesh_poisson_disk_sample
        >>> sphere = icosphere(2)
        >>> samples = mesh_poisson_disk_sample(sphere.points, sphere.cells, min_distance=0.3,
        ...                                    batch_size=512, implementation="jax")
        >>> gaps = np.linalg.norm(np.asarray(samples)[:, None] - np.asarray(samples)[None], axis=-1)
        >>> print(samples.dtype, bool(gaps[~np.eye(len(gaps), dtype=bool)].min() >= 0.3))
        float32 True
        >>> fixed = mesh_poisson_disk_sample(sphere.points, sphere.cells, mode="weighted_sample_elimination",
        ...                                  target_num_points=40, implementation="jax")
        >>> fixed.shape
        (40, 3)
    """
    vertices, faces = check_host_surface(_NAME, mesh_vertices, mesh_indices, flat_indices=True)
    min_distance = check_real_scalar("min_distance", min_distance, jnp.float32, positive=True)
    vertex_radius = _checked_vertex_radius(per_vertex_radius, vertices)
    batch_size = check_integer("batch_size", batch_size, minimum=1)
    max_points = check_integer("max_points", max_points, minimum=1)
    max_iterations = check_integer("max_iterations", max_iterations, minimum=1)
    seed = _checked_seed(random_seed)
    resolution = grid_resolution("hash_grid_resolution", hash_grid_resolution)
    check_choice("mode", mode, MODES)
    if target_num_points is not None:
        target_num_points = check_integer("target_num_points", target_num_points, minimum=1)
    # Not differentiated: only the backend's name matters here.
    backend = select_implementation(_NAME, implementation, platform=platform_of(vertices)).name
    device = next(iter(vertices.devices()))
    # The candidates of one batch (dart throwing) or the whole pool (elimination) are generated
    # at once: a count the device cannot hold must fail here, not abort the process in XLA.
    target = max_points if target_num_points is None else target_num_points  # of the elimination
    if mode == "dart_throwing":
        check_allocatable(f"{_NAME}: batch_size={batch_size}", batch_size, CANDIDATE_BYTES, device)
    else:
        what = f"target_num_points={target}" if target_num_points is not None else f"max_points={target} (the default target_num_points)"
        check_allocatable(f"{_NAME}: {what} (a candidate pool of {POOL_FACTOR:g}x)", _pool_size(target), CANDIDATE_BYTES, device)
    surface = _surface(vertices, faces, vertex_radius, min_distance)
    search = _WarpSearch(device) if backend == "warp" else _JaxSearch(device)
    if mode == "dart_throwing":
        samples = _dart_throwing(surface, search, batch_size, max_points, max_iterations, seed, resolution)
    else:
        if vertex_radius is not None:
            warnings.warn("per_vertex_radius is ignored by weighted_sample_elimination", UserWarning, stacklevel=2)
        samples = _weighted_sample_elimination(surface, search, target, seed, resolution)
    return jax.device_put(jnp.asarray(samples, jnp.float32), device)


# ---------------------------------------------------------------------------------------------
# Validation.


def _checked_vertex_radius(per_vertex_radius, vertices: jax.Array) -> np.ndarray | None:
    host = check_host_vertex_field(_NAME, "per_vertex_radius", per_vertex_radius, vertices)
    if host is not None and host.max() > np.finfo(np.float32).max:
        raise ValueError("per_vertex_radius must be finite and positive (within the float32 range)")
    return host


def _checked_seed(random_seed) -> int:
    if isinstance(random_seed, (bool, np.bool_)) or not isinstance(random_seed, numbers.Integral):
        raise TypeError(f"random_seed must be an integer, got {type(random_seed).__name__}")
    return int(random_seed) % 2**32


# ---------------------------------------------------------------------------------------------
# Candidates (shared by both backends).


class _Surface(NamedTuple):
    vertices: jax.Array  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int64
    corners: jax.Array  # (F, 3, 3) float32 triangle corners
    corner_radius: jax.Array  # (F, 3) float32 radius at each corner
    cdf: jax.Array  # (F,) float32 normalised cumulative area, last entry exactly 1
    area: float
    max_radius: float
    low: np.ndarray  # bounding box of the float32 vertices
    high: np.ndarray


def _surface(vertices: jax.Array, faces: np.ndarray, vertex_radius: np.ndarray | None, min_distance: float) -> _Surface:
    vertices32 = np.asarray(vertices).astype(np.float32)
    corners = vertices32[faces]
    # Areas in float64 so that the distribution is accurate for many small triangles.
    corners64 = corners.astype(np.float64)
    areas = 0.5 * np.linalg.norm(np.cross(corners64[:, 1] - corners64[:, 0], corners64[:, 2] - corners64[:, 0]), axis=1)
    area = float(areas.sum())
    if not area > 0.0:
        raise ValueError(f"{_NAME}: the surface has zero area")
    cdf = (np.cumsum(areas) / area).astype(np.float32)
    cdf[-1] = 1.0
    if vertex_radius is None:
        radius32 = np.float32(min_distance)
        if float(radius32) < min_distance:
            radius32 = np.nextafter(radius32, np.float32(np.inf))
        corner_radius = np.full(faces.shape, radius32, np.float32)
        max_radius = float(radius32)
    else:
        vertex_radius32 = vertex_radius.astype(np.float32)
        corner_radius = vertex_radius32[faces]
        max_radius = float(corner_radius.max())
    put = functools.partial(jax.device_put, device=next(iter(vertices.devices())))
    return _Surface(
        put(vertices32), faces, put(corners), put(corner_radius), put(cdf), area, max_radius, vertices32.min(axis=0),
        vertices32.max(axis=0),
    )  # fmt: skip


def _unit(h: jax.Array) -> jax.Array:
    """Uniform float32 in ``[0, 1)`` from the top 24 bits (exact in float32)."""
    return (h >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)


@functools.partial(jax.jit, static_argnames=("count",))
def surface_candidates(corners, corner_radius, cdf, seed, *, count: int):
    """``count`` uniform surface candidates: positions ``(count, 3)``, radii, uint32 priorities."""
    index = jnp.arange(count, dtype=jnp.uint32)
    base = lowbias32(lowbias32(seed.astype(jnp.uint32)) + index)
    u0, u1, u2, rank = (lowbias32(base + jnp.uint32((k * _GOLDEN) % 2**32)) for k in range(1, 5))
    face = jnp.clip(jnp.searchsorted(cdf, _unit(u0), side="right"), 0, cdf.shape[0] - 1)
    s = jnp.sqrt(_unit(u1))
    t = _unit(u2)
    weights = jnp.stack([1 - s, s * t, s * (1 - t)], axis=-1)
    tri = corners[face]
    positions = weights[:, 0:1] * tri[:, 0] + weights[:, 1:2] * tri[:, 1] + weights[:, 2:3] * tri[:, 2]
    radius = jnp.sum(weights * corner_radius[face], axis=-1)
    return positions, radius, rank


# Device and host bytes per surface candidate: the program's temporaries (indices, hashes, face,
# barycentrics, corners, position, radius, rank) and the host copies, with room to spare.
CANDIDATE_BYTES = 128


def _candidates(surface: _Surface, seed: int, count: int):
    positions, radius, rank = surface_candidates(surface.corners, surface.corner_radius, surface.cdf, jnp.asarray(seed, jnp.uint32), count=count)
    return np.asarray(positions), np.asarray(radius), np.asarray(rank)


# ---------------------------------------------------------------------------------------------
# Dart throwing.


def _grid_setup(surface: _Surface, cell_width: float, resolution) -> tuple[int, int, int]:
    largest = float(max(np.abs(surface.low).max(), np.abs(surface.high).max()))
    check_cell_range("the sampling radius", largest + cell_width, cell_width)
    return table_dims(surface.low - cell_width, surface.high + cell_width, cell_width, resolution)


def _dart_throwing(surface: _Surface, search, batch_size, max_points, max_iterations, seed, resolution) -> np.ndarray:
    cell = GRID_CELL_FACTOR * surface.max_radius
    dims = _grid_setup(surface, cell, resolution)
    accepted = [np.zeros((0, 3), np.float32)]
    count = 0
    for iteration in range(max_iterations):
        positions, radius, rank = _candidates(surface, (seed + ITERATION_SEED_STRIDE * iteration) % 2**32, batch_size)
        alive = np.flatnonzero(search.reject_near_accepted(np.concatenate(accepted), positions, radius, cell, dims))
        keep = search.resolve_conflicts(positions[alive], radius[alive], rank[alive], alive, cell, dims)
        new = alive[keep][: max_points - count]
        if new.size == 0:
            break
        accepted.append(positions[new])
        count += new.size
        if count >= max_points:
            break
    return np.concatenate(accepted)


# ---------------------------------------------------------------------------------------------
# Weighted sample elimination.


@jax.jit
def _pair_weight_ratios(points, rows, columns, r_min, r_max):
    """``w(d) / w_max`` per pair: ``((1 - max(d, r_min) / r_max) / (1 - r_min / r_max))^8`` in [0, 1]."""
    d = points[rows] - points[columns]
    d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
    distance = jnp.maximum(jnp.sqrt(d2), r_min)
    x = jnp.maximum(1 - distance / r_max, 0) / (1 - r_min / r_max)
    x2 = x * x
    x4 = x2 * x2
    return x4 * x4


def _pool_size(target: int) -> int:
    return max(target + 1, round(POOL_FACTOR * target))


def _weighted_sample_elimination(surface: _Surface, search, target: int, seed: int, resolution) -> np.ndarray:
    pool_size = _pool_size(target)
    r_max = 2.0 * math.sqrt(surface.area / (2.0 * math.sqrt(3.0) * target))
    points, _, _ = _candidates(surface, seed, pool_size)
    # The pool is listed cell by cell (this is "pool order"): neighbour searches run in order.
    points = points[cell_order(points, r_max)]
    r_min = r_max * WEIGHT_LIMIT_BETA * (1.0 - (target / pool_size) ** WEIGHT_LIMIT_GAMMA)
    r_max32 = float(np.float32(r_max))
    # Neighbour candidates: a superset of the pairs closer than r_max (farther ones weigh zero).
    limit = float(np.float32(r_max32 * r_max32 * CONFLICT_WIDENING))
    cell = GRID_CELL_FACTOR * r_max32
    dims = _grid_setup(surface, cell, resolution)
    row_offsets, columns = search.neighbour_lists(points, r_max32, limit, cell, dims, _neighbour_capacity(pool_size, target))
    rows = np.repeat(np.arange(pool_size, dtype=np.int32), np.diff(row_offsets))
    ratios = np.asarray(_pair_weight_ratios(points, rows, columns, np.float32(r_min), np.float32(r_max32)))
    positive_degree = np.bincount(rows[ratios > 0], minlength=pool_size)
    scale = min(2**WEIGHT_BITS, (2**31 - 1) // max(1, int(positive_degree.max(initial=0))))
    pair_weight = np.rint(ratios.astype(np.float64) * scale).astype(np.int32)
    weight = np.bincount(rows, weights=pair_weight, minlength=pool_size).astype(np.int32)
    survivors = search.eliminate(row_offsets, columns, pair_weight, weight, target)
    return _relax(points[survivors], surface, search, r_max32, limit, cell, dims, target)


@jax.jit
def _repelled(points, rows, columns, r_max):
    """Each sample pushed away from its neighbours closer than ``r_max`` (one relaxation step).

    Pair force ``(1 - d / r_max)^2`` along the unit separation; the summed push is scaled by
    ``RELAXATION_RATE r_max`` and capped at ``RELAXATION_LIMIT r_max``.
    """
    d = points[rows] - points[columns]
    distance = jnp.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    apart = distance > 0
    strength = jnp.square(jnp.maximum(1 - distance / r_max, 0)) / jnp.where(apart, distance, 1)
    force = jnp.where(apart, strength, 0)[:, None] * d
    push = jax.ops.segment_sum(force, rows, num_segments=points.shape[0]) * (jnp.float32(RELAXATION_RATE) * r_max)
    length = jnp.sqrt(jnp.sum(push * push, axis=1, keepdims=True))
    cap = jnp.float32(RELAXATION_LIMIT) * r_max
    return points + push * jnp.minimum(1, cap / jnp.where(length > 0, length, cap))


def _neighbour_capacity(count: int, target: int) -> int:
    """Room per point for neighbours within r_max in the one-pass search.

    About ``3.6 count / target`` are expected on a flat surface (a disk of radius r_max holds
    ``2 pi / sqrt(3)`` target-spacing cells); the margin is wide, and the room is limited to
    2**26 slots (256 MiB) in all: beyond either, the search takes a second, exact pass.
    """
    return min(max(16, math.ceil(12 * count / target)), 2**26 // max(count, 1))


def _relax(samples: np.ndarray, surface: _Surface, search, r_max: float, limit: float, cell: float, dims, target: int) -> np.ndarray:
    """``RELAXATION_STEPS`` repulsion steps, each followed by projection onto the surface."""
    if RELAXATION_STEPS == 0:
        return samples
    project = SurfaceProjector(surface.vertices, surface.faces, search.backend, _NAME)
    for _ in range(RELAXATION_STEPS):
        row_offsets, columns = search.neighbour_lists(samples, r_max, limit, cell, dims, _neighbour_capacity(samples.shape[0], target))
        rows = np.repeat(np.arange(samples.shape[0], dtype=np.int32), np.diff(row_offsets))
        # One pair order for every backend, so the summed pushes are bitwise equal.
        order = np.lexsort((columns, rows))
        moved = _repelled(samples, rows[order], columns[order], np.float32(r_max))
        samples = project(np.asarray(moved))[0]
    return samples


# ---------------------------------------------------------------------------------------------
# Neighbour searches: Warp (hash grid) and JAX (brute force, the reference).


class _WarpSearch:
    backend = "warp"

    def __init__(self, device):
        import warp

        self.device = str(warp.device_from_jax(device))

    def reject_near_accepted(self, accepted, positions, radius, cell, dims):
        from warp_ffi.poisson import reject_near_accepted

        return reject_near_accepted(accepted, positions, radius, cell, dims, CONFLICT_WIDENING, self.device)

    def resolve_conflicts(self, positions, radius, rank, index, cell, dims):
        from warp_ffi.poisson import resolve_conflicts

        if positions.shape[0] == 0:
            return np.zeros(0, bool)
        return resolve_conflicts(positions, radius, rank, index, cell, dims, CONFLICT_WIDENING, self.device)

    def neighbour_lists(self, points, radius, limit, cell, dims, capacity):
        from warp_ffi.poisson import neighbour_lists

        return neighbour_lists(points, radius, limit, capacity, cell, dims, self.device)

    def eliminate(self, row_offsets, columns, pair_weight, weight, target):
        from warp_ffi.poisson import eliminate

        return eliminate(row_offsets, columns, pair_weight, weight, target)


class _JaxSearch:
    backend = "jax"

    def __init__(self, device):
        self.put = functools.partial(jax.device_put, device=device)

    def reject_near_accepted(self, accepted, positions, radius, cell, dims):
        if accepted.shape[0] == 0:
            return np.ones(positions.shape[0], bool)
        # Padding to a power of two bounds the number of compiled shapes; padded rows are at
        # infinity, where no distance is below a limit.
        capacity = 1 << (accepted.shape[0] - 1).bit_length()
        padded = np.full((capacity, 3), np.inf, np.float32)
        padded[: accepted.shape[0]] = accepted
        block = query_block_size(positions.shape[0], capacity * 16)
        return np.asarray(_reject_near_accepted_jax(self.put(padded), self.put(positions), self.put(radius), block_size=block))

    def resolve_conflicts(self, positions, radius, rank, index, cell, dims):
        if positions.shape[0] == 0:
            return np.zeros(0, bool)
        # Padding to a power of two bounds the number of compiled shapes; padded candidates are at
        # infinity and never conflict.
        num = positions.shape[0]
        capacity = 1 << (num - 1).bit_length()
        pad = capacity - num
        padded = (
            np.concatenate([positions, np.full((pad, 3), np.inf, np.float32)]),
            np.concatenate([radius, np.ones(pad, np.float32)]),
            np.concatenate([rank, np.zeros(pad, np.uint32)]),
            np.concatenate([index, np.full(pad, -1)]).astype(np.int32),
        )
        block = query_block_size(capacity, capacity * 32)
        out = _resolve_conflicts_jax(*(self.put(a) for a in padded), block_size=block)
        return np.asarray(out)[:num]

    def neighbour_lists(self, points, radius, limit, cell, dims, capacity):
        block = query_block_size(points.shape[0], points.shape[0] * 16)
        close = np.asarray(_close_pairs_jax(self.put(points), np.float32(limit), block_size=block))
        rows, columns = np.nonzero(close)
        row_offsets = np.zeros(points.shape[0] + 1, np.int64)
        np.cumsum(np.bincount(rows, minlength=points.shape[0]), out=row_offsets[1:])
        return row_offsets, columns.astype(np.int32)

    def eliminate(self, row_offsets, columns, pair_weight, weight, target):
        num = weight.shape[0]
        degree = np.diff(row_offsets)
        width = max(1, int(degree.max(initial=0)))
        slot = np.arange(columns.size) - np.repeat(row_offsets[:-1], degree)
        rows = np.repeat(np.arange(num), degree)
        neighbours = np.full((num, width), num, np.int32)  # index `num` is dropped by the scatter
        pairs = np.zeros((num, width), np.int32)
        neighbours[rows, slot] = columns
        pairs[rows, slot] = pair_weight
        alive = _eliminate_jax(self.put(neighbours), self.put(pairs), self.put(weight), removals=num - target)
        return np.asarray(alive)


def _squared_distances(a: jax.Array, b: jax.Array) -> jax.Array:
    d = a[:, None, :] - b[None, :, :]
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


@functools.partial(jax.jit, static_argnames=("block_size",))
def _reject_near_accepted_jax(accepted, positions, radius, *, block_size: int):
    limit = radius * radius * jnp.float32(CONFLICT_WIDENING)

    def block(p, lim):
        return ~jnp.any(_squared_distances(p, accepted) < lim[:, None], axis=1)

    return map_query_blocks(block, (positions, limit), block_size=block_size)


@functools.partial(jax.jit, static_argnames=("block_size",))
def _resolve_conflicts_jax(positions, radius, rank, index, *, block_size: int):
    slot = jnp.arange(positions.shape[0])

    def block(p, r, k, i, s):
        m = jnp.minimum(r[:, None], radius[None, :])
        close = _squared_distances(p, positions) < m * m * jnp.float32(CONFLICT_WIDENING)
        higher = (rank[None, :] > k[:, None]) | ((rank[None, :] == k[:, None]) & (index[None, :] > i[:, None]))
        return ~jnp.any((slot[None, :] != s[:, None]) & close & higher, axis=1)

    return map_query_blocks(block, (positions, radius, rank, index, slot), block_size=block_size)


@functools.partial(jax.jit, static_argnames=("block_size",))
def _close_pairs_jax(points, limit, *, block_size: int):
    index = jnp.arange(points.shape[0])

    def block(p, i):
        return (_squared_distances(p, points) < limit) & (index[None, :] != i[:, None])

    return map_query_blocks(block, (points, index), block_size=block_size)


@functools.partial(jax.jit, static_argnames=("removals",))
def _eliminate_jax(neighbours, pairs, weight, *, removals: int):
    """Remove ``removals`` samples one at a time, largest weight first (``argmax``: lowest index)."""

    def step(_, state):
        weight, alive = state
        top = jnp.argmax(jnp.where(alive, weight, -1))
        weight = weight.at[neighbours[top]].add(-pairs[top], mode="drop")
        return weight, alive.at[top].set(False)

    _, alive = jax.lax.fori_loop(0, removals, step, (weight, jnp.ones(weight.shape, bool)))
    return alive
