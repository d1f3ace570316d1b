"""Sobolev gradient descent for shape optimisation, as optimistix pieces.

The gradient of a shape objective with respect to mesh vertices is rough: each vertex sees only
its own triangles, so steepest descent on a fine mesh crumples the surface long before the
objective is minimal. The Sobolev (H^1) gradient is the same derivative measured in a smoother
metric: the Riesz representative ``r`` of the gradient ``g`` solves ``(M + l^2 K) r = M g``, the
system of :func:`geomjax.sobolev_deform_points` with the gradient as the displacement. Detail
shorter than ``l`` is damped, so each step moves the shape as a whole.

* :class:`SobolevDescent`: the descent direction ``-r`` (an ``optimistix.AbstractDescent``), for
  any optimistix minimiser built from a descent and a search.
* :class:`SobolevGradientDescent`: the complete minimiser (an
  ``optimistix.AbstractGradientDescent``): that descent with a backtracking Armijo line search
  and optimistix's Cauchy stopping rule, for ``optimistix.minimise``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree

from ..deform.sobolev import HelmholtzTopology, deform_with_topology, helmholtz_topology

__all__ = ["SobolevDescent", "SobolevGradientDescent"]

# A search direction needs no exact solve: the line search and the stopping rule work with the
# objective itself. A relative residual of 1e-3 keeps the direction within 0.1% of the Sobolev
# gradient (a descent direction) at a third of the cost of 1e-10 (benchmarks/bench_optimize.py).
DIRECTION_TOLERANCE = 1e-3


class _SobolevDescentState(eqx.Module):
    direction: Float[Array, "num_points num_dims"]


class SobolevDescent(optx.AbstractDescent):
    """The Sobolev-filtered steepest descent direction on a mesh's vertices.

    At the iterate ``y`` (vertex positions ``(N, D)``) with objective gradient ``g``, the
    direction is ``-r`` with ``(M + l^2 K(y)) r = M g``: the field that
    :func:`geomjax.sobolev_deform_points` makes of the displacement ``g`` on the mesh at ``y``
    (P1 stiffness ``K`` of ``cells`` at the current geometry, uniform mass ``M``, the same
    solver and multilevel preconditioner). ``fixed_points`` do not move. The step is
    ``-step_size * r``; ``r . g > 0`` (the operator is positive definite), so ``-r`` is a
    descent direction for every line search.

    Args:
        cells: ``(C, V)`` integer simplices of the mesh (concrete: the multilevel
            preconditioner's structure is built from them once, on the host).
        num_points: ``N``, the number of vertices of the designs ``y`` (default: the largest
            index in ``cells`` plus one).
        length_scale: the smoothing length ``l > 0`` (coordinate units): detail shorter than
            ``l`` is damped in the step.
        fixed_points: optional ``(N,)`` bool mask of vertices that never move.
        tolerance: the solve's relative residual (default ``1e-3``: a direction needs no
            exact solve; ``None`` takes :func:`geomjax.sobolev_deform_points`'s default).
        max_iterations, implementation: the solve's options, as for
            :func:`geomjax.sobolev_deform_points`.

    Raises:
        ValueError: ``cells`` not a concrete ``(C, V)`` integer array with indices in
            ``[0, N)``, or a bad ``length_scale`` (when the step is computed: the checks of
            :func:`geomjax.sobolev_deform_points`).
        RuntimeError: a solve that does not converge, when the step is computed.

    Example:
        A gradient on one vertex becomes a smooth bump around it:

        >>> import jax.numpy as jnp
        >>> from geomjax import icosphere
        >>> from geomjax.optimize import SobolevDescent
        >>> sphere = icosphere(2)
        >>> descent = SobolevDescent(sphere.cells, length_scale=0.3)
        >>> spike = jnp.zeros_like(sphere.points).at[0, 0].set(1.0)
        >>> r = descent.direction(sphere.points, spike)[:, 0]
        >>> print(bool(0 < r[0] < 1), int(jnp.sum(r > 0.1 * r[0])) > 10)
        True True
    """

    cells: Int[Array, "num_cells num_cell_points"]
    topology: HelmholtzTopology | None
    fixed_points: Bool[Array, " num_points"] | None
    length_scale: float = eqx.field(static=True)
    tolerance: float | None = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    implementation: str | None = eqx.field(static=True)

    def __init__(
        self,
        cells,
        *,
        length_scale: float,
        num_points: int | None = None,
        fixed_points=None,
        tolerance: float | None = DIRECTION_TOLERANCE,
        max_iterations: int = 128,
        implementation: str | None = None,
    ):
        host = np.asarray(cells)
        if host.ndim != 2 or not np.issubdtype(host.dtype, np.integer) or host.dtype == np.bool_:
            raise ValueError(f"SobolevDescent: cells must be a concrete (C, V) integer array, got {host.dtype} of shape {host.shape}")
        num_points = int(host.max()) + 1 if num_points is None and host.size else int(num_points or 0)
        if host.size and (host.min() < 0 or host.max() >= num_points):
            raise ValueError(f"SobolevDescent: cells must hold indices in [0, {num_points})")
        self.cells = jnp.asarray(host, jnp.int32)
        # Built once, here, on the host: inside optimistix's jit the cells are traced.
        self.topology = helmholtz_topology(host, num_points)
        self.fixed_points = None if fixed_points is None else jnp.asarray(fixed_points, bool)
        self.length_scale = length_scale
        self.tolerance = tolerance
        self.max_iterations = max_iterations
        self.implementation = implementation

    def direction(self, y: Float[Array, "num_points num_dims"], gradient: Float[Array, "num_points num_dims"]) -> Float[Array, "num_points num_dims"]:
        """The Sobolev gradient ``r`` at ``y`` (the step is ``-step_size * r``)."""
        return deform_with_topology(
            jax.lax.stop_gradient(y),
            self.cells,
            gradient,
            length_scale=self.length_scale,
            fixed_points=self.fixed_points,
            max_iterations=self.max_iterations,
            tolerance=self.tolerance,
            implementation=self.implementation,
            topology=self.topology,
            field_only=True,
        )

    def init(self, y, f_info_struct) -> _SobolevDescentState:
        del f_info_struct
        return _SobolevDescentState(jnp.zeros_like(y))

    def query(self, y, f_info, state: _SobolevDescentState) -> _SobolevDescentState:
        if isinstance(f_info, optx.FunctionInfo.ResidualJac):
            gradient = f_info.compute_grad()
        elif hasattr(f_info, "grad"):
            gradient = f_info.grad
        else:
            raise ValueError("SobolevDescent needs the objective's gradient; this solver does not evaluate it")
        return _SobolevDescentState(self.direction(y, gradient))

    def step(self, step_size, state: _SobolevDescentState):
        return -step_size * state.direction, optx.RESULTS.successful


class SobolevGradientDescent(optx.AbstractGradientDescent):
    """Sobolev gradient descent with a backtracking Armijo line search, for ``optimistix.minimise``.

    Minimises ``fn(y, args)`` over vertex positions ``y`` ``(N, D)`` of a mesh: each step goes
    along :class:`SobolevDescent`'s direction, the largest step of ``step_size``,
    ``step_size / 2``, ... that decreases the objective by at least a tenth of its linear
    prediction (``optimistix.BacktrackingArmijo``); it stops by optimistix's Cauchy rule (the
    change in ``y`` and in the objective below ``atol + rtol * |.|``, measured by ``norm``).

    Under ``jit`` and ``vmap`` (a batch of designs: ``jax.vmap`` over ``optimistix.minimise``),
    and with ``adjoint=optimistix.ImplicitAdjoint()`` (the default) the optimum is
    differentiable with respect to ``args`` (the implicit function theorem at the optimum).

    Args:
        cells: ``(C, V)`` concrete integer simplices of the mesh whose vertices are optimised.
        length_scale: the smoothing length ``l > 0`` of the steps.
        rtol, atol: optimistix's relative and absolute tolerances.
        step_size: the first step tried at every iteration, a multiple of the Sobolev gradient
            (in the objective's units: ``step_size * |r|`` should be a sensible first move).
        search: another optimistix line search instead (e.g. ``optimistix.LearningRate(0.5)``
            for fixed steps); ``step_size`` is then unused.
        norm: optimistix's norm for the stopping rule (default ``optimistix.max_norm``).
        num_points, fixed_points, tolerance, max_iterations, implementation: as for
            :class:`SobolevDescent`.

    Example:
        >>> import jax.numpy as jnp, numpy as np, optimistix as optx
        >>> from geomjax import icosphere
        >>> from geomjax.optimize import SobolevGradientDescent
        >>> sphere = icosphere(2)
        >>> target = sphere.points * jnp.array([1.3, 1.0, 0.8])  # an ellipsoid, vertex by vertex
        >>> def misfit(y, target):
        ...     return 0.5 * jnp.sum((y - target) ** 2)
        >>> solver = SobolevGradientDescent(sphere.cells, length_scale=0.2, rtol=1e-7, atol=1e-7)
        >>> solution = optx.minimise(misfit, solver, sphere.points, args=target, max_steps=500)
        >>> print(np.round(float(jnp.max(jnp.abs(solution.value - target))), 5))
        0.0
    """

    rtol: float
    atol: float
    norm: Callable[[PyTree], Any]
    descent: SobolevDescent
    search: optx.AbstractSearch

    def __init__(
        self,
        cells,
        *,
        length_scale: float,
        rtol: float,
        atol: float,
        step_size: float = 1.0,
        search: optx.AbstractSearch | None = None,
        norm: Callable[[PyTree], Any] = optx.max_norm,
        num_points: int | None = None,
        fixed_points=None,
        tolerance: float | None = DIRECTION_TOLERANCE,
        max_iterations: int = 128,
        implementation: str | None = None,
    ):
        self.rtol = rtol
        self.atol = atol
        self.norm = norm
        self.descent = SobolevDescent(
            cells, length_scale=length_scale, num_points=num_points, fixed_points=fixed_points, tolerance=tolerance,
            max_iterations=max_iterations, implementation=implementation,
        )  # fmt: skip
        self.search = optx.BacktrackingArmijo(step_init=step_size) if search is None else search
