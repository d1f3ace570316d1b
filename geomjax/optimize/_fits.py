"""Least-squares fits of deformation parameters to measured target positions, on optimistix.

The deformations of :mod:`geomjax.deform` are linear in their parameters (lattice or control
displacements) but not in their points or controls, and users fit them over and over: a lattice
that carries a set of landmarks onto measured positions, control displacements that reproduce a
scan. Each fit here is one ``optimistix.least_squares`` call (Gauss-Newton by default, exact for
these linear problems in one step, with forward-mode Jacobians) on the residuals ``deform(points; params) - targets`` plus an optional
Tikhonov term ``sqrt(regularization) * params``, so it runs under ``jit`` and ``vmap`` (a batch
of fits) and, through ``optimistix.ImplicitAdjoint``, the fitted parameters are differentiable
with respect to the points and targets.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from .._errors import raises_documented_errors
from ..deform.ffd import free_form_deform_points
from ..deform.morph import morph_points
from ._outcome import fitted

__all__ = ["fit_free_form_deformation", "fit_morph"]

# Tolerances of the default solver, per dtype: the fits are linear least squares in their
# parameters, so Gauss-Newton lands on the optimum in one step and these only confirm it.
_DEFAULT_TOLERANCE = {jnp.dtype(jnp.float32): 1e-6, jnp.dtype(jnp.float64): 1e-10}


def _least_squares(op_name: str, residuals, params0, args, solver, max_steps: int, throw: bool, return_solution: bool):
    if solver is None:
        tolerance = _DEFAULT_TOLERANCE.get(jnp.dtype(params0.dtype), 1e-6)
        solver = optx.GaussNewton(rtol=tolerance, atol=tolerance)
    solution: optx.Solution = optx.least_squares(residuals, solver, params0, args=args, max_steps=max_steps, throw=False, adjoint=optx.ImplicitAdjoint())
    return fitted(solution, op_name=op_name, max_steps=max_steps, throw=throw, return_solution=return_solution)


def _with_penalty(misfit: jax.Array, params: jax.Array, regularization: float) -> jax.Array:
    if regularization == 0:
        return misfit
    return jnp.concatenate([misfit.reshape(-1), jnp.sqrt(jnp.asarray(regularization, params.dtype)) * params.reshape(-1)])


def check_weight(name: str, value, *, op_name: str | None = None) -> float:
    """A fit's weight as a float: a finite real ``>= 0`` (NumPy scalars too), else ``ValueError``
    (its message prefixed with ``op_name``, when given)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) or not 0 <= value < float("inf"):
        prefix = f"{op_name}: " if op_name else ""
        raise ValueError(f"{prefix}{name} must be a finite real >= 0, got {value!r}")
    return float(value)


def _check_targets(points: jax.Array, target_points) -> jax.Array:
    target_points = jnp.asarray(target_points)
    if target_points.shape != points.shape or target_points.dtype != points.dtype:
        raise ValueError(
            f"target_points must have the shape and dtype of points {points.shape} {points.dtype}, got {target_points.shape} {target_points.dtype}"
        )
    # Concrete targets are checked now; traced ones make the solve's residuals non-finite, which
    # the solve's result reports (RuntimeError, see _outcome).
    if not isinstance(target_points, jax.core.Tracer) and target_points.is_fully_addressable and not bool(jnp.all(jnp.isfinite(target_points))):
        raise ValueError("target_points must be finite")
    return target_points


@raises_documented_errors
def fit_free_form_deformation(
    points: Float[Array, "num_points num_dims"],
    target_points: Float[Array, "num_points num_dims"],
    resolution: Sequence[int],
    *,
    origin: Sequence[float] | Float[Array, " num_dims"],
    extent: Sequence[float] | Float[Array, " num_dims"],
    basis: str = "bernstein",
    regularization: float = 0.0,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 64,
    throw: bool = True,
    return_solution: bool = False,
    implementation: str | None = None,
) -> Float[Array, "*resolution num_dims"]:
    """The FFD lattice that moves ``points`` onto ``target_points`` in least squares.

    Minimises ``sum_i |FFD(points_i; L) - target_i|^2 + regularization |L|^2`` over the lattice
    displacements ``L`` of :func:`geomjax.free_form_deform_points` with the given box and basis.
    Points outside the box do not move, so they do not inform the fit.

    Args:
        points: ``(N, D)`` float32 or float64 positions.
        target_points: ``(N, D)``, their measured positions (same dtype).
        resolution: the lattice's nodes per axis ``(n_1, ..., n_D)``.
        origin, extent, basis: the lattice's box and basis, as for
            :func:`geomjax.free_form_deform_points`.
        regularization: ``>= 0``, the weight of ``|L|^2``. Needed when the points do not
            determine every node (fewer points than nodes, nodes far from every point, as the
            corners of a box around a curved mesh): without it the solver's steps there are
            rounding amplified by the near-singular system, the fit does not settle, and
            ``throw=True`` raises. ``1e-9`` keeps such nodes at zero and moves the others by
            about ``1e-9`` relative.
        solver: an optimistix least-squares solver (default ``optimistix.GaussNewton`` with
            tolerances ``1e-6`` in float32, ``1e-10`` in float64; its QR solve needs the points
            to determine every node, or a ``regularization``).
        max_steps: the solver's step budget.
        throw: ``True``: a solve that does not succeed (not converged within ``max_steps``, or a
            non-finite residual) raises ``RuntimeError``; ``False``: the last iterate is returned
            without a check.
        return_solution: return the whole ``optimistix.Solution`` (``.value`` the lattice,
            ``.result`` whether the solve succeeded, ``.stats`` its steps) instead of the lattice,
            with no check: for callers that handle a failed fit themselves.
        implementation: the deformation's backend, as for :func:`geomjax.free_form_deform_points`.

    Returns:
        ``(n_1, ..., n_D, D)`` lattice displacements, differentiable with respect to ``points``
        and ``target_points`` (implicit adjoint). ``jax.vmap`` over ``points`` and
        ``target_points`` fits a batch.

    Raises:
        ValueError: ``target_points`` of another shape or dtype, or not finite (checked when
            concrete), a negative or non-finite ``regularization``, and the errors of
            :func:`geomjax.free_form_deform_points`.
        RuntimeError: with ``throw=True``, a solve that does not succeed (at run time under
            ``jit``), the fit's message first.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import free_form_deform_points
        >>> from geomjax.optimize import fit_free_form_deformation
        >>> points = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (60, 2)))
        >>> true = jnp.asarray(np.random.default_rng(1).normal(0, 0.1, (3, 3, 2)))
        >>> moved = free_form_deform_points(points, true, origin=[0.0, 0.0], extent=[1.0, 1.0])
        >>> lattice = fit_free_form_deformation(points, moved, (3, 3), origin=[0.0, 0.0], extent=[1.0, 1.0])
        >>> print(bool(jnp.allclose(lattice, true, atol=1e-8)))
        True
    """
    points = jnp.asarray(points)
    target_points = _check_targets(points, target_points)
    regularization = check_weight("regularization", regularization)
    resolution = tuple(int(n) for n in resolution)
    if points.ndim != 2 or len(resolution) != points.shape[-1]:
        raise ValueError(f"resolution must give one node count per coordinate of points {points.shape}, got {resolution}")

    def residuals(lattice, args):
        points, targets = args
        moved = free_form_deform_points(points, lattice, origin=origin, extent=extent, basis=basis, implementation=implementation)
        return _with_penalty(moved - targets, lattice, regularization)

    lattice0 = jnp.zeros((*resolution, points.shape[-1]), points.dtype)
    return _least_squares("fit_free_form_deformation", residuals, lattice0, (points, target_points), solver, max_steps, throw, return_solution)


@raises_documented_errors
def fit_morph(
    points: Float[Array, "num_points num_dims"],
    target_points: Float[Array, "num_points num_dims"],
    control_points: Float[Array, "num_controls num_dims"],
    *,
    radius: float | Float[Array, ""] | Float[Array, " num_controls"],
    kernel: str = "wendland_c2",
    regularization: float = 0.0,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 64,
    throw: bool = True,
    return_solution: bool = False,
    implementation: str | None = None,
) -> Float[Array, "num_controls num_dims"]:
    """The control displacements of :func:`geomjax.morph_points` that move ``points`` onto
    ``target_points`` in least squares.

    Minimises ``sum_i |morph(points_i; U) - target_i|^2 + regularization |U|^2`` over the
    displacements ``U`` of ``control_points`` (Shepard-normalised compact kernels of the given
    ``radius``). Points that no control reaches do not move and do not inform the fit.

    Args:
        points, target_points: ``(N, D)`` positions and their measured positions (same dtype).
        control_points: ``(C, D)`` handles.
        radius, kernel, implementation: as for :func:`geomjax.morph_points`.
        regularization, solver, max_steps, throw, return_solution: as for
            :func:`fit_free_form_deformation`.

    Returns:
        ``(C, D)`` control displacements, differentiable with respect to ``points``,
        ``target_points``, ``control_points`` and an array ``radius`` (implicit adjoint).

    Raises:
        ValueError: ``target_points`` of another shape or dtype, or not finite (checked when
            concrete), a negative or non-finite ``regularization``, and the errors of
            :func:`geomjax.morph_points`.
        RuntimeError: with ``throw=True``, a solve that does not succeed (at run time under
            ``jit``), the fit's message first.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import morph_points
        >>> from geomjax.optimize import fit_morph
        >>> rng = np.random.default_rng(0)
        >>> points, controls = jnp.asarray(rng.uniform(0, 1, (80, 3))), jnp.asarray(rng.uniform(0, 1, (6, 3)))
        >>> true = jnp.asarray(rng.normal(0, 0.05, (6, 3)))
        >>> moved = morph_points(points, controls, true, radius=0.8)
        >>> print(bool(jnp.allclose(fit_morph(points, moved, controls, radius=0.8), true, atol=1e-8)))
        True
    """
    points = jnp.asarray(points)
    target_points = _check_targets(points, target_points)
    regularization = check_weight("regularization", regularization)
    control_points = jnp.asarray(control_points)

    def residuals(displacements, args):
        points, targets, controls, radius = args
        moved = morph_points(points, controls, displacements, radius=radius, kernel=kernel, implementation=implementation)
        return _with_penalty(moved - targets, displacements, regularization)

    displacements0 = jnp.zeros(control_points.shape, points.dtype)
    return _least_squares("fit_morph", residuals, displacements0, (points, target_points, control_points, radius), solver, max_steps, throw, return_solution)
