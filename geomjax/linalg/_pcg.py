"""Preconditioned conjugate gradients on ``(N, D)`` blocks (Jacobi unless a preconditioner is given), and a lineax solver around it.

Why not ``lineax.CG`` as shipped: with ``atol=0`` and a sparse right-hand side its per-element
scale ``rtol * |b|`` is zero almost everywhere, so it stops after one step with a wrong answer;
its max-norm, per-element stopping rule stalls where a 2-norm rule is met; and its breakdown test
``|p^T A p| > 100 * eps * N * |gamma|`` fires spuriously in float32 for large ``N``. This solver:

* treats the ``D`` columns of the block as ``D`` independent CG recurrences (one ``alpha`` and one
  ``beta`` per column) that share every operator application, so a solve of a 3-component field
  costs the matvecs of one solve and each column converges at its own rate;
* stops on the relative 2-norm of the residual of the whole block,
  ``||r||_F <= rtol * ||b||_F``, after rescaling the system by a power of two near ``max |b|`` (so squared norms
  neither overflow nor underflow, in float32 too; a zero right-hand side returns zero);
* only accepts convergence on the *true* residual ``b - A x``: when the recurrence residual meets
  the tolerance the true residual is recomputed and, if rounding has made them drift apart, the
  recurrence restarts from it (one extra matvec per restart, usually one in total);
* accepts the true residual at the *rounding floor* where that lies above ``rtol ||b||``: storing
  the solution in the working precision moves each entry by up to ``u |x_i|`` (``u = eps / 2``),
  which alone leaves a residual of about ``0.27 eps ||D x||_F`` (``D = diag(A)``; measured
  0.25-0.30 on the Helmholtz systems of all eleven shared real meshes, ``benchmarks/
  bench_real_meshes.py``). No iterate does better, so in float32 a tolerance below it (1e-6 on
  stiff meshes, whose floor is 1e-6 to 3e-5) would otherwise fail after any number of
  iterations. The floor accepted is ``FLOOR_FACTOR eps ||D x||_F``, twice the measured one;
  in float64 it lies near 1e-14 of ``||b||`` and practically never binds;
* uses the initial guess only if its residual is no larger than ``||b||`` (otherwise zero), so a
  forward-solve guess never slows down a tangent or adjoint solve that shares the options;
* reports breakdown (non-finite values, ``p^T A p <= tiny`` in a column that is not yet solved, or
  ``r^T M^-1 r < 0``) and non-convergence; :class:`JacobiPCG` turns both into runtime errors, so an inexact solution
  (or an inexact implicit gradient) is never returned silently.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

from .._errors import runtime_branched_check

__all__ = ["PCGResult", "jacobi_pcg", "solution_or_error", "JacobiPCG", "FLOOR_FACTOR"]

# The rounding floor accepted, in units of ``eps ||diag(A) x||_F`` (see the module docstring).
FLOOR_FACTOR = 0.5


class PCGResult(NamedTuple):
    """Outcome of :func:`jacobi_pcg`: the solution, the iterations used and three status flags
    (``at_rounding_floor``: converged at the rounding floor, above ``rtol ||b||``)."""

    solution: Array
    num_steps: Array
    converged: Array
    breakdown: Array
    at_rounding_floor: Array


def _column_dot(a: Array, b: Array) -> Array:
    """Per-column inner products of two ``(N, D)`` blocks.

    Written on transposed operands: XLA's CPU reduction of an ``(N, D)`` product over its major
    axis is several times slower than over the minor axis of ``(D, N)`` operands, and these
    reductions dominate a CG iteration after the operator product (``benchmarks/bench_sobolev.py``
    measures the whole solve).
    """
    return jnp.sum(a.T * b.T, axis=1)


def jacobi_pcg(
    matvec: Callable[[Array], Array],
    rhs: Float[Array, "num_rows num_columns"],
    inverse_diagonal: Float[Array, " num_rows"],
    initial_guess: Float[Array, "num_rows num_columns"],
    *,
    rtol: float | Array,
    max_steps: int,
    preconditioner: Callable[[Array], Array] | None = None,
) -> PCGResult:
    """Solve ``A X = B`` column by column with preconditioned CG (see the module docstring).

    Args:
        matvec: ``X -> A X`` for a symmetric positive definite ``A`` that acts on every column
            alike (``A`` ⊗ ``I_D``); called on ``(N, D)`` arrays.
        rhs: ``B``, shape ``(N, D)``, ``N >= 1``.
        inverse_diagonal: positive ``(N,)`` ``1 / diag(A)``: the preconditioner (Jacobi) unless
            ``preconditioner`` is given, and the scale of the rounding floor in any case.
        initial_guess: ``(N, D)`` starting point, used only if it beats zero.
        rtol: relative tolerance on ``||B - A X||_F / ||B||_F`` (a scalar, may be traced).
        max_steps: the most CG iterations, counted over restarts.
        preconditioner: optional ``R -> M^-1 R`` on ``(N, D)`` blocks, symmetric positive
            definite and acting on every column alike (e.g.
            :class:`~geomjax.linalg.MultilevelPreconditioner`); ``None`` is Jacobi.

    Returns:
        :class:`PCGResult`. ``converged`` is true only when the true residual meets the tolerance
        (or the rounding floor ``FLOOR_FACTOR eps ||diag(A) X||_F``, where that is larger) and no
        breakdown occurred. Works under ``jit`` and ``vmap`` (a batched solve iterates until
        its last item converges; finished items are frozen). Not meant to be differentiated:
        :class:`JacobiPCG` and the Warp path's ``custom_vjp`` differentiate the solve implicitly.
    """
    dtype = rhs.dtype
    tiny = jnp.asarray(jnp.finfo(dtype).tiny, dtype)
    one = jnp.ones((), dtype)
    inverse_diagonal = inverse_diagonal[:, None]

    def precondition(r):
        return r * inverse_diagonal if preconditioner is None else preconditioner(r)

    largest = jnp.max(jnp.abs(rhs))
    finite_rhs = jnp.isfinite(largest)
    # A power of two, so that scaling is exact and the scaled residual is the residual, scaled.
    _, exponent = jnp.frexp(jnp.where(finite_rhs & (largest > 0), largest, one))
    scale = jnp.ldexp(one, exponent)
    b = rhs / scale
    bb = jnp.sum(b * b)
    threshold = jnp.square(jnp.asarray(rtol, dtype)) * bb

    def squared_norm(r):
        return jnp.sum(r * r)

    floor_factor = jnp.asarray(FLOOR_FACTOR * jnp.finfo(dtype).eps, dtype)

    def accepted(x):
        """The squared residual accepted at ``x``: the tolerance's, or the rounding floor's."""
        return jnp.maximum(threshold, squared_norm(floor_factor * x / inverse_diagonal))

    def meets_tolerance(rr, x):
        return rr <= accepted(x)  # False for NaN

    x = initial_guess / scale
    r = b - matvec(x)
    use_guess = squared_norm(r) <= bb
    x = jnp.where(use_guess, x, 0)
    r = jnp.where(use_guess, r, b)

    def cg_step(state):
        x, r, p, gamma, _, steps, broken = state
        ap = matvec(p)
        curvature = _column_dot(p, ap)
        unsolved = gamma > 0
        regular = curvature > tiny
        broken = broken | jnp.any(unsolved & ~regular)
        alpha = jnp.where(unsolved & regular, gamma / jnp.where(regular, curvature, one), 0)
        x = x + alpha * p
        r = r - alpha * ap
        z = precondition(r)
        gamma_next = _column_dot(r, z)
        beta = jnp.where(unsolved, gamma_next / jnp.where(unsolved, gamma, one), 0)
        p = z + beta * p
        rr = squared_norm(r)
        # r^T M^-1 r < 0 means the preconditioner is not positive: no CG recurrence applies.
        broken = broken | ~jnp.all(jnp.isfinite(gamma_next) & (gamma_next >= 0)) | ~jnp.isfinite(rr)
        return x, r, p, gamma_next, rr, steps + 1, broken

    def restart(state):
        # ``r`` is a true residual here; iterate on the recurrence, then recompute it exactly.
        x, r, rr, steps, broken = state
        z = precondition(r)
        gamma = _column_dot(r, z)
        # The recurrence runs to the level accepted at the restart's start (the floor moves with
        # ``x``, little once near the solution; the true residual below decides).
        level = accepted(x)

        def keep_iterating(state):
            *_, rr, steps, broken = state
            return ~(rr <= level) & ~broken & (steps < max_steps)

        inner = (x, r, z, gamma, rr, steps, broken)
        x, _, _, _, _, steps, broken = jax.lax.while_loop(keep_iterating, cg_step, inner)
        r = b - matvec(x)
        rr = squared_norm(r)
        return x, r, rr, steps, broken | ~jnp.isfinite(rr)

    def not_done(state):
        x, _, rr, steps, broken = state
        return ~meets_tolerance(rr, x) & ~broken & (steps < max_steps)

    rr = squared_norm(r)
    start = (x, r, rr, jnp.zeros((), jnp.int32), ~finite_rhs | ~jnp.isfinite(rr))
    x, _, rr, steps, broken = jax.lax.while_loop(not_done, restart, start)
    converged = meets_tolerance(rr, x) & ~broken
    return PCGResult(x * scale, steps, converged, broken, converged & ~(rr <= threshold))


def solution_or_error(result: PCGResult, *, max_steps: int, context: str, method: str = "Jacobi-PCG") -> Array:
    """``result.solution``, guarded by a runtime check (``RuntimeError``) if the solve failed
    (see :class:`JacobiPCG`); ``method`` names the solver in the messages."""
    failure = jnp.where(result.breakdown, 2, jnp.where(result.converged, 0, 1))
    return runtime_branched_check(
        result.solution,
        failure > 0,
        failure,
        (
            "",
            f"{context}: the {method} solve did not converge within {max_steps} iterations. Increase max_iterations "
            f"or relax tolerance ({method} needs more iterations where cells are badly shaped or much smaller than "
            "length_scale)",
            f"{context}: the {method} solve did not converge (breakdown: non-finite values or a "
            "non-positive curvature p^T A p). Check that the inputs are finite; increase "
            "max_iterations or relax tolerance",
        ),
        RuntimeError,
    )


def solver_name(preconditioner) -> str:
    """How failure messages name a solve: Jacobi-PCG, or the preconditioner's ``method``."""
    return "Jacobi-PCG" if preconditioner is None else getattr(preconditioner, "method", "PCG")


def _without_guess(options: dict[str, Any]) -> dict[str, Any]:
    return {key: value for key, value in options.items() if key != "y0"}


class JacobiPCG(lx.AbstractLinearSolver):
    """:func:`jacobi_pcg` as a ``lineax`` solver, for operators tagged positive semidefinite.

    ``lineax.linear_solve(operator, b, JacobiPCG(...), options=...)`` then differentiates the
    solve implicitly (an adjoint solve for reverse mode, a tangent solve for ``jvp``, both with
    this solver) and batches it under ``vmap``. The solve is on a single ``(N, D)`` array whose
    columns the operator treats alike (see :func:`jacobi_pcg`).

    Options (``options=`` of ``lineax.linear_solve``; both must be free of gradients, e.g.
    wrapped in ``jax.lax.stop_gradient``):

    * ``"inverse_diagonal"`` (required): ``(N,)`` ``1 / diag(A)``, the Jacobi preconditioner.
    * ``"preconditioner"``: a symmetric positive definite ``R -> M^-1 R`` used instead of Jacobi
      (a pytree such as :class:`~geomjax.linalg.MultilevelPreconditioner`), for every solve.
    * ``"y0"``: initial guess, ``(N, D)``; dropped for the transposed (adjoint) solve.

    Failure (non-convergence within ``max_steps`` or breakdown) raises a ``RuntimeError``
    through ``equinox.error_if`` in every solve, primal, tangent and adjoint alike (see
    ``geomjax._errors``): public ops raise it as a plain ``RuntimeError`` with the message;
    under a user's ``jit`` it is JAX's runtime error carrying the same message.

    Attributes:
        rtol: relative 2-norm residual tolerance (a Python float or a scalar array).
        max_steps: the most CG iterations per solve.
        context: prefix of the error messages, e.g. the public op's name.
    """

    rtol: float | Array
    max_steps: int = eqx.field(static=True)
    context: str = eqx.field(static=True, default="JacobiPCG")

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if operator.in_structure() != operator.out_structure():
            raise ValueError(f"{self.context}: JacobiPCG needs a square operator")
        if not lx.is_positive_semidefinite(operator):
            raise ValueError(f"{self.context}: JacobiPCG needs an operator tagged positive (semi)definite")
        return operator

    def compute(self, state, vector, options: dict[str, Any]):
        operator = state
        guess = options.get("y0")
        if guess is None:
            guess = jnp.zeros_like(vector)
        preconditioner = options.get("preconditioner")
        result = jacobi_pcg(operator.mv, vector, options["inverse_diagonal"], guess, rtol=self.rtol, max_steps=self.max_steps, preconditioner=preconditioner)
        solution = solution_or_error(result, max_steps=self.max_steps, context=self.context, method=solver_name(preconditioner))
        return solution, lx.RESULTS.successful, {"num_steps": result.num_steps}

    def transpose(self, state, options: dict[str, Any]):
        # Symmetric operator: the adjoint solve reuses it (and the preconditioner), without the
        # forward initial guess.
        return state.transpose(), _without_guess(options)

    def conj(self, state, options: dict[str, Any]):
        return state, _without_guess(options)

    def assume_full_rank(self) -> bool:
        return True
