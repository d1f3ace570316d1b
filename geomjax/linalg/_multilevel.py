"""A multilevel (aggregation) preconditioner for the Helmholtz systems ``m̄ I + l^2 K``.

Why: Jacobi-PCG needs about ``l / h`` iterations, and on scanned meshes, whose cells are much
smaller than ``l`` in places, that is 130-310 iterations (``benchmarks/bench_real_meshes.py``),
above the default budget of 128. The slow modes are the smooth ones, which Jacobi barely touches
and a coarse grid represents well; once a coarse cell is as large as ``l`` the mass term
dominates and the coarse system is easy. So a few levels suffice.

Two parts, split by what they depend on:

* :func:`aggregation_hierarchy` (host, NumPy, cached per topology like
  :func:`~geomjax.linalg.row_pattern`): greedy aggregation of each level's neighbour graph into
  vertex + neighbours groups (coarsening by about 5-7 on triangle meshes), down to at most
  :data:`COARSEST_SIZE` vertices. Piecewise-constant prolongation ``P``, so the Galerkin product
  ``P^T A P`` of an operator in difference form is again in difference form: coarse masses are
  sums of fine masses, coarse couplings sums of fine couplings between aggregates, and
  intra-aggregate couplings drop out. Each level stores where every fine coupling lands.
* :class:`MultilevelPreconditioner` (JAX, built per solve from the current coefficients, not
  differentiated): the coarse operators by segment sums, a dense Cholesky factor of the coarsest
  one, and the symmetric V-cycle ``x -> M^-1 x`` with one Jacobi pre- and post-smoothing step
  per level, its diagonal bounded below by a fraction of the l1 row norms
  (:data:`SMOOTHER_L1_FRACTION`) so that it converges for any symmetric positive definite ``A``.
  The post-smoother is the pre-smoother's adjoint, so ``M^-1`` is symmetric positive definite:
  a valid CG preconditioner whatever the mesh (obtuse cells, negative couplings, fixed rows).

The operator is given as padded rows, ``(A x)_i = mass_i x_i + sum_k c_ik (x[n_ik] - x_i)`` (the
form of :class:`~geomjax.linalg.RowStiffness`). Fixed (Dirichlet) rows are identity rows whose
couplings are zero, so one hierarchy per topology serves every mask: the preconditioner stays
valid, only a little less sharp where a mask cuts an aggregate.
"""

from __future__ import annotations

import collections
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._validate import as_jax_array
from ._stiffness import RowPattern, RowStiffness, TopologyCache

__all__ = ["COARSEST_SIZE", "Coarsening", "aggregation_hierarchy", "MultilevelPreconditioner", "jacobi_iteration_bound"]

# The coarsest level is solved by a dense Cholesky factorisation (cubic in its size, per solve).
COARSEST_SIZE = 150
# Aggregation that shrinks a level by less than this factor stops coarsening (a level of isolated
# vertices or a complete graph); the coarsest level is then larger and smoothed instead of solved.
_MIN_COARSENING = 1.5
# The coarsest level is factorised only up to this size; above it, it gets smoothing steps.
_MAX_DENSE_SIZE = 1024
# The smoother is Jacobi with ``D_ii = max(A_ii, SMOOTHER_L1_FRACTION * sum_j |A_ij|)``. Any
# fraction above 1/2 makes ``2 D - A`` positive definite (``sum_j |A_ij| - A`` is diagonally
# dominant), so the smoother converges and the V-cycle is positive definite on every mesh; on rows
# with nonnegative cotangent weights it is Jacobi damped by about 0.9. Measured on the shared
# meshes (``benchmarks/bench_real_meshes.py``): 0.55 needs the fewest iterations; plain l1-Jacobi
# (fraction 1) needs 15-30% more, undamped Jacobi breaks down.
SMOOTHER_L1_FRACTION = 0.55


class Coarsening(NamedTuple):
    """One step from a level with ``n`` vertices and ``W`` couplings per row to the next.

    Attributes:
        aggregate: ``(n,)`` int32, the coarse vertex of each vertex.
        neighbours: ``(n_c, W_c)`` int32 padded rows of the coarse level (padded with the row).
        slots: ``(n W,)`` int32, where each fine coupling (row-major) is summed in the flattened
            ``(n_c W_c)`` coarse couplings; ``n_c W_c`` (dropped) for intra-aggregate couplings.
        neighbour_aggregates: ``(n, W)`` int32, the coarse vertex of each fine neighbour
            (``aggregate[fine neighbours]``, for products with a prolonged coarse vector).
    """

    aggregate: Int[Array, " n"]
    neighbours: Int[Array, "n_c W_c"]
    slots: Int[Array, " nW"]
    neighbour_aggregates: Int[Array, "n W"]


_HIERARCHIES = TopologyCache()


def aggregation_hierarchy(pattern: RowPattern) -> tuple[Coarsening, ...]:
    """The coarsening steps of the pattern's neighbour graph, cached on its contents.

    Empty when the graph is already small (at most :data:`COARSEST_SIZE` vertices). Device arrays,
    concrete even when first built while tracing.
    """
    neighbours = np.asarray(pattern.neighbours)

    def build() -> tuple[Coarsening, ...]:
        steps = []
        rows = neighbours
        while rows.shape[0] > COARSEST_SIZE:
            aggregate, count = _aggregate(rows)
            if count * _MIN_COARSENING > rows.shape[0]:
                break
            coarse_rows, slots = _coarse_pattern(rows, aggregate, count)
            steps.append((aggregate, coarse_rows, slots, aggregate[rows]))
            rows = coarse_rows
        with jax.ensure_compile_time_eval():
            return tuple(Coarsening(*(as_jax_array(a.astype(np.int32)) for a in step)) for step in steps)

    return _HIERARCHIES.get(neighbours, build)


def _aggregate(neighbours: np.ndarray) -> tuple[np.ndarray, int]:
    """Greedy aggregation: ``(aggregate (n,), number of aggregates)``.

    A vertex whose neighbours are all free seeds an aggregate of itself and its neighbours (in
    vertex order); every vertex left over joins the aggregate most of its neighbours are in;
    isolated vertices share one aggregate (their rows are decoupled, any grouping is valid).
    """
    n = neighbours.shape[0]
    rows = np.arange(n)
    # CSR of the distinct neighbours other than the row itself (the padding).
    real = neighbours != rows[:, None]
    lists = [row[mask].tolist() for row, mask in zip(neighbours, real)]
    aggregate = [-1] * n
    count = 0
    for i in range(n):
        if aggregate[i] >= 0 or not lists[i]:
            continue
        if all(aggregate[j] < 0 for j in lists[i]):
            aggregate[i] = count
            for j in lists[i]:
                aggregate[j] = count
            count += 1
    isolated = None
    for i in range(n):
        if aggregate[i] >= 0:
            continue
        votes = collections.Counter(aggregate[j] for j in lists[i] if aggregate[j] >= 0)
        if votes:
            aggregate[i] = votes.most_common(1)[0][0]
            continue
        if lists[i]:  # all neighbours still free: a new aggregate of the leftovers around it
            aggregate[i] = count
            for j in lists[i]:
                if aggregate[j] < 0:
                    aggregate[j] = count
            count += 1
            continue
        if isolated is None:
            isolated, count = count, count + 1
        aggregate[i] = isolated
    return np.asarray(aggregate, np.int64), count


def _coarse_pattern(neighbours: np.ndarray, aggregate: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Padded coarse rows and the coarse slot of every fine coupling (see :class:`Coarsening`)."""
    n, width = neighbours.shape
    rows = aggregate[np.repeat(np.arange(n), width)]
    columns = aggregate[neighbours.reshape(-1)]
    between = rows != columns
    keys = rows * count + columns
    unique_keys, inverse = np.unique(keys[between], return_inverse=True)
    unique_rows = unique_keys // count
    per_row = np.bincount(unique_rows, minlength=count)
    coarse_width = max(int(per_row.max(initial=0)), 1)
    starts = np.concatenate([[0], np.cumsum(per_row)[:-1]])
    unique_slots = unique_rows * coarse_width + (np.arange(unique_keys.size) - starts[unique_rows])
    coarse_neighbours = np.repeat(np.arange(count), coarse_width)
    coarse_neighbours[unique_slots] = unique_keys % count
    slots = np.full(n * width, count * coarse_width, np.int64)
    slots[between] = unique_slots[inverse]
    return coarse_neighbours.reshape(count, coarse_width), slots


# ---------------------------------------------------------------------------------------------
# Numeric part: per solve, in JAX.


def _row_norms(mass, couplings):
    """``(A_ii, sum_j |A_ij|)`` of the rows ``mass_i x_i + sum_k c_ik (x[n_ik] - x_i)``."""
    diagonal = mass - jnp.sum(couplings, axis=1)
    return diagonal, jnp.abs(diagonal) + jnp.sum(jnp.abs(couplings), axis=1)


def jacobi_iteration_bound(mass, couplings, smallest_eigenvalue, tolerance) -> Float[Array, ""]:
    """CG's iteration bound ``sqrt(kappa) / 2 * ln(2 / tolerance)`` for the Jacobi-preconditioned
    operator in padded rows, with ``kappa`` bounded from the rows alone:
    ``lambda_max(D^-1 A) <= max_i sum_j |A_ij| / A_ii`` (Gershgorin) and
    ``lambda_min(D^-1 A) >= smallest_eigenvalue(A) / max_i A_ii``. Worst-row bounds: one sliver
    raises it, so it errs towards the V-cycle, never towards a Jacobi solve that cannot finish.
    On a uniform sphere it is close to the count (70 bounded, 66 needed, ``icosphere(6)``)."""
    diagonal, l1 = _row_norms(mass, couplings)
    tiny = jnp.finfo(diagonal.dtype).tiny
    condition = jnp.max(l1 / jnp.maximum(diagonal, tiny)) * jnp.max(diagonal) / jnp.maximum(smallest_eigenvalue, tiny)
    return 0.5 * jnp.sqrt(condition) * jnp.log(2 / tolerance)


def _product(mass, couplings, rows, columns, v, *, unrolled: bool):
    """``mass_i v[rows_i] + sum_k couplings[i, k] (v[columns[i, k]] - v[rows_i])``.

    With ``rows = None`` (the identity) and ``columns`` the neighbours this is ``A v``; with the
    aggregates of the rows and of their neighbours it is ``A P v`` for a coarse ``v``, without
    forming ``P v`` (whose gathers XLA would fuse into every gather here).

    ``unrolled``: ``W`` plain gathers (fastest, as in ``RowStiffness``), else one ``(n, W, D)``
    gather and a reduction: slower, but XLA materialises a reduction, where it fuses the unrolled
    form into its consumers: a coarse level's product would be recomputed inside every gather of
    the finer level (ten times the cost of a cycle, measured).
    """
    own = v if rows is None else v[rows]
    if unrolled:
        total = mass[:, None] * own
        for k in range(columns.shape[1]):
            total = total + couplings[:, k, None] * (v[columns[:, k]] - own)
        return total
    return mass[:, None] * own + jnp.sum(couplings[:, :, None] * (v[columns] - own[:, None]), axis=1)


class _Level(eqx.Module):
    """``(A x)_i = mass_i x_i + sum_k couplings[i, k] (x[neighbours[i, k]] - x_i)`` and its smoother."""

    mass: Float[Array, " n"]
    couplings: Float[Array, "n W"]
    neighbours: Int[Array, "n W"]
    diagonal: Float[Array, " n"]
    inverse_smoother: Float[Array, " n"]

    @classmethod
    def build(cls, mass, couplings, neighbours):
        diagonal, l1 = _row_norms(mass, couplings)
        smoother = jnp.maximum(diagonal, SMOOTHER_L1_FRACTION * l1)
        return cls(mass, couplings, neighbours, diagonal, 1 / jnp.maximum(smoother, jnp.finfo(l1.dtype).tiny))

    def coarsen(self, step: Coarsening) -> _Level:
        count, width = step.neighbours.shape
        mass = jax.ops.segment_sum(self.mass, step.aggregate, num_segments=count)
        couplings = jax.ops.segment_sum(self.couplings.reshape(-1), step.slots, num_segments=count * width + 1)[:-1]
        return _Level.build(mass, couplings.reshape(count, width), step.neighbours)

    def dense(self) -> Float[Array, "n n"]:
        n = self.mass.shape[0]
        rows = jnp.broadcast_to(jnp.arange(n)[:, None], self.neighbours.shape)
        matrix = jnp.zeros((n, n), self.mass.dtype).at[rows, self.neighbours].add(self.couplings)
        return matrix + jnp.diag(self.diagonal)


class MultilevelPreconditioner(eqx.Module):
    """``r -> M^-1 r`` on ``(N, D)`` blocks: one symmetric V-cycle (see the module docstring), or
    Jacobi where ``jacobi_instead`` says so.

    Built from the finest operator in padded rows; not differentiable (build it from
    ``stop_gradient`` inputs: it changes the iterations, not the solution).
    """

    levels: tuple[_Level, ...]
    steps: tuple[Coarsening, ...]
    coarsest_factor: Float[Array, "n n"] | None
    # A scalar bool decided per solve (see for_helmholtz), or None for the V-cycle always.
    jacobi_instead: Bool[Array, ""] | None = None
    # How solver messages name a solve preconditioned with this.
    method: str = eqx.field(static=True, default="multilevel-PCG")

    @classmethod
    def build(
        cls, mass: Float[Array, " N"], couplings: Float[Array, "N W"], neighbours: Int[Array, "N W"], hierarchy: tuple[Coarsening, ...]
    ) -> MultilevelPreconditioner:
        """From the finest operator (per-row masses, couplings of the padded rows) and the
        hierarchy of its topology (:func:`aggregation_hierarchy`)."""
        levels = [_Level.build(mass, couplings, neighbours)]
        for step in hierarchy:
            levels.append(levels[-1].coarsen(step))
        factor = None
        if levels[-1].mass.shape[0] <= _MAX_DENSE_SIZE:
            factor = jnp.linalg.cholesky(levels[-1].dense())
        return cls(tuple(levels), hierarchy, factor)

    @classmethod
    def for_helmholtz(
        cls,
        stiffness: RowStiffness,
        mass: Float[Array, ""],
        length_scale_squared: Float[Array, ""],
        free: Bool[Array, " N"] | None,
        hierarchy: tuple[Coarsening, ...],
        *,
        jacobi_within: tuple[Float[Array, ""], int] | None = None,
    ) -> MultilevelPreconditioner:
        """For :class:`~geomjax.linalg.HelmholtzOperator` ``m̄ I + l^2 K`` with ``K`` in padded
        rows: a fixed row is an identity row, and a free row's couplings to fixed rows move to
        its mass (``-l^2 K_ij x_i``, the column removed). Gradients are stopped.

        ``jacobi_within=(tolerance, iterations)``: use Jacobi instead of the V-cycle when the
        a-priori bound on Jacobi-CG's iterations to ``tolerance`` is at most ``iterations``
        (:func:`jacobi_iteration_bound`). A V-cycle costs about four Jacobi iterations on a CPU,
        and saves 3-7x the iterations: it pays where Jacobi would need many.
        """
        coefficients, mass, length_scale_squared = jax.lax.stop_gradient((stiffness.coefficients, mass, length_scale_squared))
        couplings = length_scale_squared * coefficients
        masses = jnp.full(couplings.shape[:1], mass)
        smallest_eigenvalue = mass
        if free is not None:
            to_free = free[stiffness.neighbours]
            masses = jnp.where(free, mass - jnp.sum(jnp.where(to_free, 0, couplings), axis=1), 1)
            couplings = jnp.where(free[:, None] & to_free, couplings, 0)
            smallest_eigenvalue = jnp.minimum(mass, 1)  # fixed rows are identity rows
        preconditioner = cls.build(masses, couplings, stiffness.neighbours, hierarchy)
        if jacobi_within is None:
            return preconditioner
        tolerance, iterations = jacobi_within
        bound = jacobi_iteration_bound(masses, couplings, smallest_eigenvalue, tolerance)
        p = preconditioner
        return cls(p.levels, p.steps, p.coarsest_factor, jacobi_instead=bound <= iterations, method="PCG")

    def __call__(self, r: Float[Array, "N D"]) -> Float[Array, "N D"]:
        if self.jacobi_instead is None:
            return self._cycle(0, r)
        diagonal = self.levels[0].diagonal[:, None]
        return jax.lax.cond(self.jacobi_instead, lambda r: r / diagonal, lambda r: self._cycle(0, r), r)

    def _cycle(self, depth: int, b):
        """One smoothing step from zero, the coarse correction, one more smoothing step."""
        level = self.levels[depth]
        # The finest level's products are unrolled gathers (fastest); the coarser ones end in a
        # reduction, so that their results are materialised (see _product).
        unrolled = depth == 0
        scale = level.inverse_smoother[:, None]
        x = scale * b
        residual = b - _product(level.mass, level.couplings, None, level.neighbours, x, unrolled=unrolled)
        if depth == len(self.levels) - 1:
            if self.coarsest_factor is not None:
                return jax.scipy.linalg.cho_solve((self.coarsest_factor, True), b)
            return x + scale * residual  # two smoothing steps from zero
        step = self.steps[depth]
        coarse = jax.ops.segment_sum(residual, step.aggregate, num_segments=step.neighbours.shape[0])
        correction = self._cycle(depth + 1, coarse)
        # x + P e, smoothed: its residual is the pre-smoothed one minus A P e.
        prolonged = _product(level.mass, level.couplings, step.aggregate, step.neighbour_aggregates, correction, unrolled=unrolled)
        return x + correction[step.aggregate] + scale * (residual - prolonged)
