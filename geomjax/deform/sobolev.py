"""Sobolev (H^1 / Helmholtz) smoothing of a displacement on a simplicial mesh."""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._dispatch import platform_of, select_implementation
from .._errors import raises_documented_errors, runtime_check
from .._points import add_batch_axis, remove_batch_axis
from .._sharding import map_local_shards
from .._validate import (
    as_index_array,
    check_coordinates,
    check_host_index_range,
    check_index_range,
    check_integer,
    check_one_per_point,
    check_real_scalar,
    check_same_device,
    check_same_shape,
    is_array,
)
from ..linalg import (
    CellStiffness,
    HelmholtzOperator,
    JacobiPCG,
    MultilevelPreconditioner,
    RowPattern,
    RowStiffness,
    aggregation_hierarchy,
    jacobi_pcg,
    off_diagonal_entries,
    off_diagonal_pairs,
    referenced_vertices,
    row_pattern,
    simplex_stiffness,
    solution_or_error,
    uniform_lumped_mass,
)
from ..linalg._helmholtz import StiffnessOperator
from ..linalg._multilevel import Coarsening
from ..linalg._pcg import solver_name

__all__ = ["sobolev_deform_points"]

DEFAULT_TOLERANCE = {jnp.dtype(jnp.float32): 1e-6, jnp.dtype(jnp.float64): 1e-10}
WARP_MAX_CELL_POINTS = 4  # segments, triangles, tetrahedra
# The JAX path preconditions with Jacobi where a bound on Jacobi-CG's iterations is at most this
# (or three quarters of max_iterations, if smaller), else with the multilevel V-cycle: a cycle
# costs about four Jacobi iterations on a CPU and saves 3-7x the iterations, so it pays only where
# Jacobi needs many (benchmarks/bench_real_meshes.py). The Warp path always cycles: its stiffness
# products cost more than the JAX V-cycle, which then pays at any count.
JACOBI_ITERATIONS = 96

_NAME = "sobolev_deform_points"
_DEGENERATE = "cells must be finite, nondegenerate simplices (every Gram determinant finite and > 0 when length_scale > 0)"


@raises_documented_errors
def sobolev_deform_points(
    points: Float[Array, "*batch num_points num_dims"],
    cells: Int[Array, "num_cells num_cell_points"],
    displacement: Float[Array, "*batch num_points num_dims"],
    *,
    length_scale: float,
    fixed_points: Bool[Array, "*batch num_points"] | None = None,
    max_iterations: int = 128,
    tolerance: float | None = None,
    implementation: str | None = None,
) -> Float[Array, "*batch num_points num_dims"]:
    r"""Smooth a displacement with the Sobolev (H^1, Helmholtz) filter of a mesh and apply it.

    Solves, per batch item and per coordinate, ``(M + l^2 K) u = M d`` and returns ``x + u``,
    where ``K`` is the P1 (linear Lagrange) stiffness matrix of the simplicial mesh ``cells``
    (segments, triangles, tetrahedra and, on the JAX path, any simplex with ``V - 1 <= D``;
    embedded manifolds such as curves in 2D/3D and surfaces in 3D work too) and ``M = m̄ I`` is a
    uniform mass: the mean lumped P1 vertex mass over the vertices with positive mass (``1`` if
    there is none). A cell with edge matrix ``E`` (rows ``x_i - x_0``) and Gram matrix
    ``G = E E^T`` has measure ``sqrt(det G) / m!`` and local stiffness ``|c| Ĝ G^-1 Ĝ^T``,
    ``Ĝ = [-1 ... -1; I_m]``. ``l`` is the smoothing length: detail shorter than ``l`` is damped.

    Boundary conditions are natural (Neumann) except at ``fixed_points``, where ``u = 0``
    (identity rows, zero right-hand side, columns removed). Vertices that no cell references
    keep their raw displacement. Constant displacements are reproduced exactly when nothing is
    fixed. ``length_scale = 0`` returns ``x + d`` (masked) before any assembly or value
    validation, so degenerate cells are then accepted.

    The system is solved by preconditioned CG on the whole ``(N, D)`` block (see
    :func:`geomjax.linalg.jacobi_pcg`). With concrete ``cells`` the preconditioner is a multilevel
    V-cycle (:class:`geomjax.linalg.MultilevelPreconditioner`: aggregation built once per
    topology on the host and cached, coarse operators from the current geometry, the coarsest
    solved directly), which needs 3-7x fewer iterations than Jacobi on fine or badly shaped meshes
    and is exact on meshes of at most 150 vertices. On larger meshes the JAX path keeps Jacobi
    where an a-priori bound says Jacobi-CG finishes within 96 iterations (a V-cycle costs about
    four Jacobi iterations on a CPU); the Warp path always cycles. With traced ``cells`` (an
    argument of ``jit``) it is Jacobi: close over the cells instead (a constant of the program)
    to keep the V-cycle. (torch_bridge builds the topology from its concrete tensors, so its
    calls, eager or compiled, get the V-cycle.) The solve starts from the masked ``d`` and runs until the true residual
    satisfies ``||b - A u|| <= tolerance * ||b||`` over the whole field, or reaches the rounding
    floor ``0.5 eps ||diag(A) u||`` where that is larger: the residual that storing ``u`` in the
    dtype alone leaves (no iterate does better). Only float32 on stiff systems meets it (fine or
    badly shaped meshes, large ``length_scale``: a floor of 1e-6 to 3e-5 of ``||b||`` on scanned
    meshes); there the result is as exact as float32 holds it.

    Args:
        points: vertex positions ``(N, D)`` or batched ``(B, N, D)``, float32 or float64.
        cells: ``(C, V)`` int32/int64 vertex indices shared by the batch; ``V >= 2``,
            ``V - 1 <= D``, indices in ``[0, N)``. ``C = 0`` leaves every point isolated.
        displacement: exactly the shape, dtype and device of ``points``.
        length_scale: finite real ``l >= 0`` with ``l^2`` representable in the dtype.
        fixed_points: optional bool mask ``(N,)`` / ``(B, N)`` of points held in place.
        max_iterations: the most CG iterations per solve (a Python ``int >= 1``).
        tolerance: relative residual tolerance ``> 0``; ``None`` means ``1e-6`` (float32) or
            ``1e-10`` (float64).
        implementation: ``"jax"`` (also ``"torch"``), ``"warp"`` or ``None``. ``None`` picks
            ``"jax"`` on CPU, where it beats the Warp path (whose CPU kernels are slow) and, using both
            cores, scipy's Jacobi-CG on a preassembled matrix (``benchmarks/bench_sobolev.py``). With
            concrete ``cells`` the JAX path assembles the operator into padded rows from a host-side
            pattern (cached per topology), so each CG product is a few gathers; with traced ``cells``
            (an argument of ``jit``) it falls back to per-cell scatters, which make a CPU solve several
            times slower. GPUs keep ``"jax"`` until measured there. The Warp path (segments, triangles
            and tetrahedra) runs the same solver with Warp stiffness products (deterministic per-vertex
            gathers, both CPU cores).

    Returns:
        Deformed points, same shape and dtype as ``points``.

    Raises:
        TypeError: non-float ``points``/``displacement`` or mixed dtypes; non-integer ``cells``;
            non-bool ``fixed_points``; ``bool`` or non-real ``length_scale``/``tolerance``;
            non-int ``max_iterations``.
        ValueError: bad shapes or batching; ``V < 2`` or ``V - 1 > D``; ``V > 4`` with
            ``implementation="warp"``; a negative, non-finite or too large ``length_scale``;
            ``max_iterations < 1``; a non-positive ``tolerance``. At ``length_scale > 0``:
            indices outside ``[0, N)`` and degenerate or non-finite cells ("cells must be
            finite, nondegenerate simplices"). These value checks run eagerly (host sync) when
            the arrays are concrete; on traced arrays (inside ``jit``, ``vmap`` over points) they
            become ``equinox.error_if`` checks that raise this ``ValueError`` with the same
            message when the computation runs (under a user's own ``jit``: JAX's runtime error
            carrying the message).
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.
        RuntimeError: the solve did not converge within ``max_iterations`` or broke down
            (e.g. non-finite displacements), in the forward solve and in the adjoint/tangent
            solves of a gradient: an inexact implicit gradient is never returned.

    Differentiable in ``points`` (through the operator and the mass) and ``displacement``, by the
    implicit function theorem (an adjoint solve, never unrolled CG iterations): ``grad`` and
    ``jvp`` through ``lineax.linear_solve`` on the JAX path, a solve-level ``custom_vjp`` on the
    Warp path (README, "Backends and transforms"). No gradient flows to ``cells``,
    ``fixed_points``, ``length_scale`` or ``tolerance``.

    Sharding: see the README's "Sharding"; under ``Explicit`` axes the Warp path solves shard by
    shard, and the JAX path runs with those axes turned ``Auto`` (XLA places the solve); both
    return the input's split.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import sobolev_deform_points
        >>> points = jnp.stack([jnp.linspace(0.0, 1.0, 6), jnp.zeros(6)], axis=-1)
        >>> cells = jnp.array([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]])
        >>> displacement = jnp.zeros((6, 2)).at[2, 1].set(0.3)
        >>> moved = sobolev_deform_points(points, cells, displacement, length_scale=0.2, implementation="jax")
        >>> print(np.round(np.asarray(moved[:, 1]), 4))
        [0.0301 0.0552 0.1263 0.0527 0.023  0.0126]
    """
    return deform_with_topology(
        points, cells, displacement, length_scale=length_scale, fixed_points=fixed_points, max_iterations=max_iterations,
        tolerance=tolerance, implementation=implementation,
    )  # fmt: skip


HelmholtzTopology = tuple[RowPattern, tuple[Coarsening, ...]]


def helmholtz_topology(cells: np.ndarray, num_points: int) -> HelmholtzTopology | None:
    """The host-side structures of concrete ``cells`` (``(C, V)`` integers in ``[0, num_points)``):
    the padded rows of the JAX path's products and the multilevel preconditioner's coarsening,
    built once per topology (cached on its contents). ``None`` for cells that are not such an
    array (the call then rejects them), for no cells, and where the rows would be too wide to pad
    (the per-cell product and Jacobi serve those)."""
    cells = np.asarray(cells)
    if cells.ndim != 2 or cells.shape[0] == 0 or not np.issubdtype(cells.dtype, np.integer):
        return None
    if cells.min() < 0 or cells.max() >= num_points:
        return None
    pattern = row_pattern(cells, num_points)
    return None if pattern is None else (pattern, aggregation_hierarchy(pattern))


def deform_with_topology(points, cells, displacement, *, length_scale, fixed_points, max_iterations, tolerance, implementation,
                         topology: HelmholtzTopology | None = None, field_only: bool = False):  # fmt: skip
    """:func:`sobolev_deform_points` with, for traced ``cells``, their :func:`helmholtz_topology`
    built by the caller from the same cells on the host (torch_bridge does, as its programs
    take every tensor traced); ignored when ``cells`` are concrete (built here, cached).
    ``field_only=True`` returns the smoothed field ``u`` instead of ``x + u`` (the Sobolev
    descent's direction, without the rounding of ``(x + u) - x``)."""
    points, batched = check_coordinates("points", points)
    displacement = check_same_shape("points", points, "displacement", displacement)
    cells = _check_cells(cells, points)
    free = _free_mask(fixed_points, points)
    dtype = points.dtype
    length_scale = check_real_scalar("length_scale", length_scale, dtype, nonnegative=True)
    if length_scale * length_scale > float(jnp.finfo(dtype).max):
        raise ValueError(f"length_scale={length_scale}: length_scale**2 is not representable in {jnp.dtype(dtype)}")
    max_iterations = _check_max_iterations(max_iterations)
    if tolerance is None:
        tolerance = DEFAULT_TOLERANCE[jnp.dtype(dtype)]
    else:
        tolerance = check_real_scalar("tolerance", tolerance, dtype, positive=True)
    backend = select_implementation(
        _NAME,
        implementation,
        platform=platform_of(points),
        warp_unsupported=None
        if cells.shape[1] <= WARP_MAX_CELL_POINTS
        else f"supports segments, triangles and tetrahedra (V <= {WARP_MAX_CELL_POINTS}); got cells with V={cells.shape[1]}",
    )

    x = add_batch_axis(points, batched)
    d = add_batch_axis(displacement, batched)
    free = add_batch_axis(free, batched)
    if length_scale == 0:
        return remove_batch_axis(_masked(d, free) if field_only else x + _masked(d, free), batched)

    num_points = x.shape[1]
    concrete_cells = not isinstance(cells, jax.core.Tracer)
    if concrete_cells:
        host_cells = np.asarray(cells)
        check_host_index_range(host_cells, num_points, _index_range_message(num_points))
        # The early check names the degenerate cell; it reads the points on the host, which a
        # process cannot do for rows on other processes (the solve's own runtime check covers
        # those, with the same message less the cell).
        if x.size and cells.shape[0] and not isinstance(x, jax.core.Tracer) and x.is_fully_addressable:
            _check_nondegenerate(x, cells)
        topology = helmholtz_topology(host_cells, num_points)
    pattern, hierarchy = (None, None) if topology is None else topology
    deform = functools.partial(
        _deform,
        pattern=pattern,
        hierarchy=hierarchy,
        # NumPy scalars, constants of the program: a JAX array made here would take the sharding
        # of a surrounding jax.set_mesh, which shard_map refuses to close over.
        length_scale_squared=np.asarray(length_scale * length_scale, dtype),
        tolerance=np.asarray(tolerance, dtype),
        max_iterations=max_iterations,
        backend=backend,
        check_indices=not concrete_cells,
        field_only=field_only,
    )
    # Designs are solved independently: explicitly split ones shard by shard (see _sharding),
    # on both backends. The runtime checks need check_vma off (equinox's error_if, traced for
    # the non-CPU platforms, does not type its branches' varying axes), which is safe as only the
    # integer cells and non-differentiated constants are replicated.
    out = map_local_shards(deform, (x, cells, d, free), (1, 0, 1, 1), out_axes=1, check_vma=False)
    return remove_batch_axis(out, batched)


# ---------------------------------------------------------------------------------------------
# Validation.


def _check_cells(cells, points: jax.Array) -> jax.Array:
    cells = as_index_array("cells", cells)
    check_same_device("points", points, "cells", cells)
    if cells.ndim != 2:
        raise ValueError(f"cells must have shape (C, V) (shared by the batch), got {tuple(cells.shape)}")
    num_cell_points, num_dims = cells.shape[1], points.shape[-1]
    if num_cell_points < 2:
        raise ValueError(f"cells must have V >= 2 vertices per cell, got shape {tuple(cells.shape)}")
    if num_cell_points - 1 > num_dims:
        raise ValueError(
            f"cells with V={num_cell_points} vertices are {num_cell_points - 1}-simplices, which need "
            f"D >= {num_cell_points - 1} coordinates; points have D={num_dims}"
        )
    return cells


def _free_mask(fixed_points, points: jax.Array) -> jax.Array | None:
    """``~fixed_points`` after checking it is a bool array of shape ``points.shape[:-1]``."""
    if fixed_points is None:
        return None
    if not is_array(fixed_points) or jnp.dtype(fixed_points.dtype) != jnp.dtype(bool):
        kind = jnp.dtype(fixed_points.dtype) if is_array(fixed_points) else type(fixed_points).__name__
        raise TypeError(f"fixed_points must be None or a bool array, got {kind}")
    return ~check_one_per_point("fixed_points", fixed_points, points, "flag")


def _check_max_iterations(max_iterations) -> int:
    # The CG step counter is int32: a larger budget is no budget at all, so it is capped there.
    return min(check_integer("max_iterations", max_iterations, minimum=1), 2**31 - 1)


def _index_range_message(num_points: int) -> str:
    return f"{_NAME}: cells indices must be in [0, {num_points}) for {num_points} points"


@jax.jit
def _gram_determinants(points: jax.Array, cells: jax.Array) -> jax.Array:
    return jax.vmap(lambda p: simplex_stiffness(p, cells)[2])(points)


def _check_nondegenerate(points: jax.Array, cells: jax.Array) -> None:
    determinants = np.asarray(_gram_determinants(points, cells))
    bad = ~(np.isfinite(determinants) & (determinants > 0))
    if bad.any():
        item, cell = (int(i[0]) for i in np.nonzero(bad))
        where = f"cell {cell}" + (f" of batch item {item}" if points.shape[0] > 1 else "")
        raise ValueError(f"{_NAME}: {_DEGENERATE}; {where} has Gram determinant {determinants[item, cell]}")


def _masked(field: jax.Array, free: jax.Array | None) -> jax.Array:
    return field if free is None else jnp.where(free[..., None], field, 0)


# ---------------------------------------------------------------------------------------------
# Shared pipeline.


@functools.partial(jax.jit, static_argnames=("max_iterations", "backend", "check_indices", "field_only"))
def _deform(
    points, cells, displacement, free, pattern, hierarchy, length_scale_squared, tolerance, *, max_iterations, backend, check_indices, field_only=False
):
    """``x + u`` (``u`` with ``field_only``) for ``(B, N, D)`` inputs, ``l > 0``; index and
    degeneracy checks under ``error_if``."""
    num_points = points.shape[1]
    if check_indices:
        cells = check_index_range(cells, num_points, _index_range_message(num_points))
    if points.size == 0 or cells.shape[0] == 0:
        # Nothing to smooth: every point is isolated and keeps its (masked) displacement.
        return _masked(displacement, free) if field_only else points + _masked(displacement, free)
    cells = cells.astype(jnp.int32)
    if backend.is_warp:
        # The topology's arrays are operands, not closed over: the Warp path's transforms
        # (fast_with_reference, which takes arrays) cannot close over the tracers they are here.
        topology, structure = jax.tree.flatten((pattern, hierarchy))

        def with_topology(field_fn):
            def run(points, displacement, free, cells, length_scale_squared, tolerance, *topology):
                pattern, hierarchy = jax.tree.unflatten(structure, topology)
                return field_fn(points, displacement, free, cells, length_scale_squared, tolerance, pattern, hierarchy, max_iterations=max_iterations)

            return run

        referenced, field = backend.run(
            with_topology(_warp_field), with_topology(_jax_field), points, displacement, free, cells, length_scale_squared, tolerance, *topology
        )
    else:
        referenced, field = _jax_field(points, displacement, free, cells, length_scale_squared, tolerance, pattern, hierarchy, max_iterations=max_iterations)
    # Unreferenced rows decouple (m̄ u = m̄ d): make them exact whatever the solver's start.
    field = jnp.where(referenced[:, None], field, displacement)
    return _masked(field, free) if field_only else points + _masked(field, free)


def _jax_field(
    points, displacement, free, cells, length_scale_squared, tolerance, pattern: RowPattern | None, hierarchy: tuple[Coarsening, ...] | None, *,
    max_iterations,
):  # fmt: skip
    """``(referenced, u)`` on the JAX path: which vertices a cell references, and the field."""
    referenced = referenced_vertices(cells, points.shape[1]) if pattern is None else pattern.referenced
    num_referenced = jnp.sum(referenced, dtype=jnp.int32)
    solve = functools.partial(
        _jax_solve, cells=cells, pattern=pattern, hierarchy=hierarchy, num_referenced=num_referenced,
        length_scale_squared=length_scale_squared, tolerance=tolerance, max_iterations=max_iterations,
    )  # fmt: skip
    return referenced, _one_by_one(solve, points, displacement, free)


def _one_by_one(solve, points, displacement, free):
    """Solve the batch items one after another (``lax.map``, not ``vmap``).

    Each item then stops at its own convergence, and the CPU products stay plain gathers: a
    batched while loop would iterate every item until the slowest converges, and XLA's batched
    gathers are markedly slower on CPU. Under a user's ``vmap`` the map is batched as usual.
    """
    if points.shape[0] == 1:
        item = jax.tree.map(lambda a: a[0], (points, displacement, free))
        return jax.tree.map(lambda a: a[None], solve(*item))
    return jax.lax.map(lambda item: solve(*item), (points, displacement, free))


def _checked_stiffness(points, cells):
    local, measures, determinants = simplex_stiffness(points, cells)
    valid = jnp.all(jnp.isfinite(determinants) & (determinants > 0))
    return runtime_check(local, ~valid, f"{_NAME}: {_DEGENERATE}"), measures


# ---------------------------------------------------------------------------------------------
# JAX implementation: lineax solve with our Jacobi-PCG (implicit differentiation, jvp, vmap).


def _jax_solve(points, displacement, free, *, cells, pattern: RowPattern | None, hierarchy, num_referenced,
               length_scale_squared, tolerance, max_iterations):  # fmt: skip
    """``u`` for one item ``(N, D)``."""
    local, measures = _checked_stiffness(points, cells)
    rows = None if pattern is None else RowStiffness.assemble(local, pattern)
    stiffness: StiffnessOperator = CellStiffness.assemble(local, cells, points.shape[0]) if rows is None else rows
    mass = uniform_lumped_mass(measures, num_referenced)
    operator = HelmholtzOperator(stiffness, mass, length_scale_squared, free)
    rhs = _masked(mass * displacement, free)
    options: dict[str, Any] = {"inverse_diagonal": jax.lax.stop_gradient(operator.inverse_diagonal()), "y0": jax.lax.stop_gradient(_masked(displacement, free))}
    if rows is not None and hierarchy is not None:  # a host pattern comes with its hierarchy
        # Jacobi where it is bound to finish soon (a V-cycle would cost more than it saves); a
        # mesh without coarsening steps is small enough to be solved directly, always.
        jacobi_within = (tolerance, min(JACOBI_ITERATIONS, 3 * max_iterations // 4)) if hierarchy else None
        options["preconditioner"] = MultilevelPreconditioner.for_helmholtz(rows, mass, length_scale_squared, free, hierarchy, jacobi_within=jacobi_within)
    solver = JacobiPCG(tolerance, max_iterations, _NAME)
    structure = jax.eval_shape(lambda: points)  # with its type's sharding (per-shard under shard_map)
    # throw=False: JacobiPCG reports its failures itself (runtime_branched_check, typed and
    # without a host callback on CPU); lineax's own check would be an equinox host callback,
    # and JAX does not keep programs with host callbacks in its persistent compilation cache.
    return lx.linear_solve(operator.as_linear_operator(structure), rhs, solver, options=options, throw=False).value


# ---------------------------------------------------------------------------------------------
# Warp implementation: Warp stiffness products inside the same PCG, implicit adjoint by hand.


class _WarpStiffness(eqx.Module):
    off_diagonal: jax.Array  # (C, V (V - 1))
    cells: jax.Array
    offsets: jax.Array
    order: jax.Array

    def __call__(self, x):
        from warp_ffi.sobolev import stiffness_product

        return stiffness_product(x, self.off_diagonal, self.cells, self.offsets, self.order)

    def diagonal(self):
        from warp_ffi.sobolev import stiffness_diagonal

        return stiffness_diagonal(self.off_diagonal, self.cells, self.offsets, self.order)


def _warp_field(points, displacement, free, cells, length_scale_squared, tolerance, pattern: RowPattern | None, hierarchy, *, max_iterations):
    from warp_ffi.sobolev import vertex_incidence

    incidence = vertex_incidence(cells, points.shape[1])
    referenced = jnp.diff(incidence[0]) > 0
    num_referenced = jnp.sum(referenced, dtype=jnp.int32)
    rows = None if pattern is None else (pattern, hierarchy)

    def solve(x, d, f):
        return _warp_solve(x, d, f, cells, incidence, num_referenced, length_scale_squared, tolerance, rows, max_iterations)

    return referenced, _one_by_one(solve, points, displacement, free)


def _warp_operator(points, free, cells, incidence, num_referenced, length_scale_squared, rows):
    """The operator with Warp products, and the multilevel preconditioner when ``rows`` holds the
    topology's ``(pattern, hierarchy)`` (else ``None``: Jacobi)."""
    local, measures = _checked_stiffness(points, cells)
    stiffness = _WarpStiffness(off_diagonal_entries(local), cells, *incidence)
    operator = HelmholtzOperator(stiffness, uniform_lumped_mass(measures, num_referenced), length_scale_squared, free)
    if rows is None:
        return operator, None
    pattern, hierarchy = rows
    padded = RowStiffness.assemble(local, pattern)
    return operator, MultilevelPreconditioner.for_helmholtz(padded, operator.mass, length_scale_squared, free, hierarchy)


def _warp_pcg(operator, preconditioner, rhs, guess, tolerance, max_iterations):
    result = jacobi_pcg(operator.mv, rhs, operator.inverse_diagonal(), guess, rtol=tolerance, max_steps=max_iterations, preconditioner=preconditioner)
    return solution_or_error(result, max_steps=max_iterations, context=_NAME, method=solver_name(preconditioner))


@functools.partial(jax.custom_vjp, nondiff_argnums=(9,))
def _warp_solve(points, displacement, free, cells, incidence, num_referenced, length_scale_squared, tolerance, rows, max_iterations):
    """``u`` for one item, the products in Warp; the VJP is the implicit adjoint (one more solve)."""
    return _warp_solve_fwd(points, displacement, free, cells, incidence, num_referenced, length_scale_squared, tolerance, rows, max_iterations)[0]


def _warp_solve_fwd(points, displacement, free, cells, incidence, num_referenced, length_scale_squared, tolerance, rows, max_iterations):
    operator, preconditioner = _warp_operator(points, free, cells, incidence, num_referenced, length_scale_squared, rows)
    guess = _masked(displacement, free)
    field = _warp_pcg(operator, preconditioner, operator.mass * guess, guess, tolerance, max_iterations)
    residuals = (points, displacement, free, cells, num_referenced, length_scale_squared, tolerance, field, operator, preconditioner)
    return field, residuals


def _warp_solve_bwd(max_iterations, residuals, field_bar):
    points, displacement, free, cells, num_referenced, length_scale_squared, tolerance, field, operator, preconditioner = residuals
    # A is symmetric: the adjoint solve uses the same operator and preconditioner, from a zero
    # initial guess.
    adjoint = _warp_pcg(operator, preconditioner, _masked(field_bar, free), jnp.zeros_like(field_bar), tolerance, max_iterations)
    adjoint = _masked(adjoint, free)
    displacement_bar = operator.mass * adjoint
    data = _masked(displacement, free) - field
    a, b = off_diagonal_pairs(cells.shape[1])
    # d/dx of adjoint^T (M(x) d - A(x) u) with u, d and the adjoint held fixed.
    coupling = jnp.sum(adjoint[cells[:, a]] * (field[cells[:, b]] - field[cells[:, a]]), axis=-1)  # (C, P)

    def residual(x):
        local, measures, _ = simplex_stiffness(x, cells)
        mass = uniform_lumped_mass(measures, num_referenced)
        return mass * jnp.sum(adjoint * data) - length_scale_squared * jnp.sum(off_diagonal_entries(local) * coupling)

    points_bar = jax.grad(residual)(points)
    return points_bar, displacement_bar, None, None, None, None, None, None, None


_warp_solve.defvjp(_warp_solve_fwd, _warp_solve_bwd)
