"""Registration of a template surface onto a target surface with a free-form lattice, on optimistix.

The template's vertices move by :func:`geomjax.free_form_deform_points`; the lattice is the
least-squares solution (``optimistix.least_squares``; by default a dogleg trust-region method on
the loss's exact Hessian, whose steps for the distance residuals alone are ICP point-to-plane
Gauss-Newton steps on the lattice) of two kinds of residuals, both dimensionless:

* distance: for each template vertex ``i`` with a third of its triangles' area ``a_i`` (template
  area ``A``), ``sqrt(a_i / A) n . (p_i - q) / sqrt(A)``, where ``p_i`` is the moved vertex and
  ``n``, ``q`` the unit normal and a corner of the target face nearest to it (point-to-plane, as
  in ICP: smooth, so Gauss-Newton steps stay well defined on the surface). Their squares sum to
  the area-weighted mean squared distance over ``A``;
* regularisers, the deformation energies of the template under the move: the membrane strain
  energy (:func:`geomjax.simplex_strain_energy` of the triangles, unit Lame parameters) and the
  bending energy (:func:`geomjax.surface_bending_energy` of the interior hinges), each as the
  sum of squares of residuals linear in the strains and angle changes
  (``geomjax.energy.strain.strain_residuals``, ``geomjax.energy.bending.bending_residuals``),
  times ``sqrt(w / A)``: their squares sum to ``w`` times the energy per unit area. (The square
  root of a cell's energy would do as a residual only away from the rest shape: it is not
  differentiable where the energy vanishes, which is where a registration starts.)
* a Tikhonov term ``sqrt(regularization / A) L`` on the lattice, which fixes the nodes that no
  template vertex reaches.

The nearest target faces are found again at every evaluation (a Warp search tree of the target,
built once when the target is concrete; brute force in JAX with ``implementation="jax"``) and are
not differentiated: the residuals are differentiable functions of the moved vertices and the
chosen faces' corners. The solution is differentiable with respect to the template and the
target (``optimistix.ImplicitAdjoint``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Float, Int, PyTree

from .._dispatch import warp_available
from .._errors import raises_documented_errors
from .._geometry import triangle_normal
from ..deform.ffd import free_form_deform_points
from ..energy.bending import bending_residuals
from ..energy.strain import strain_residuals
from ..mesh import Mesh
from ..query.bvh import bvh_vertices32, closest_face_tree, closest_faces_brute_force, search_closest_faces
from ._fits import check_weight
from ._outcome import fitted

__all__ = ["register_surface"]

_NAME = "register_surface"
# Trust-region tolerances per dtype (relative and absolute, on the lattice and the loss).
_DEFAULT_TOLERANCE = {jnp.dtype(jnp.float32): 1e-5, jnp.dtype(jnp.float64): 1e-8}
# The lattice's Tikhonov weight per dtype: enough to keep the normal equations regular in that
# precision, small enough that the fit's bias (about its square root times the lattice, in units
# of sqrt(A)) stays below a registration's accuracy.
_DEFAULT_REGULARIZATION = {jnp.dtype(jnp.float32): 1e-6, jnp.dtype(jnp.float64): 1e-10}


@raises_documented_errors
def register_surface(
    template_points: Float[Array, "num_template_vertices 3"],
    template_faces: Int[Array, "num_template_faces 3"],
    target_points: Float[Array, "num_target_vertices 3"],
    target_faces: Int[Array, "num_target_faces 3"],
    resolution: Sequence[int],
    *,
    origin: Sequence[float] | Float[Array, "3"],
    extent: Sequence[float] | Float[Array, "3"],
    basis: str = "bernstein",
    strain_weight: float = 0.0,
    bending_weight: float = 0.0,
    regularization: float | None = None,
    solver: optx.AbstractLeastSquaresSolver | optx.AbstractMinimiser | None = None,
    max_steps: int = 200,
    throw: bool = True,
    return_solution: bool = False,
    implementation: str | None = None,
) -> Float[Array, "*resolution 3"]:
    """The FFD lattice that moves a template triangle surface onto a target surface.

    Minimises, over the lattice displacements ``L`` of :func:`geomjax.free_form_deform_points`
    (box ``origin``, ``extent``, ``basis``), the area-weighted mean squared point-to-plane
    distance from the moved template vertices to their nearest target faces, over the template
    area ``A``, plus ``strain_weight`` times the template's membrane strain energy and
    ``bending_weight`` times its bending energy, both per unit area (see the module's docstring
    for the residuals). The nearest faces are searched again at every step, so the template
    need only start near the target (as an ICP registration): scale and centre it first.

    Args:
        template_points: ``(V, 3)`` float32 or float64 template vertices (the rest shape of
            the energies).
        template_faces: ``(F, 3)`` integer triangles of the template.
        target_points: ``(W, 3)`` target vertices (same dtype).
        target_faces: ``(G, 3)`` integer triangles of the target (orientation does not matter).
        resolution: lattice nodes per axis ``(n_1, n_2, n_3)``.
        origin, extent, basis: the lattice box and basis, as for
            :func:`geomjax.free_form_deform_points`; the box should contain the template.
        strain_weight: ``>= 0``, weight of the membrane strain energy per unit area
            (:func:`geomjax.simplex_strain_energy`, unit Lame parameters, the template as the
            rest shape), against the mean squared distance in units of ``sqrt(A)``. It keeps the
            surface from bunching where the distances alone leave it free, and resists any
            stretch: ``1e-4`` already holds a template 10% smaller than the target about 1%
            short of it; ``1e-6``-``1e-5`` regularise a template of about the right size.
        bending_weight: ``>= 0``, weight of the bending energy per unit area
            (:func:`geomjax.surface_bending_energy` of the template's interior hinges).
        regularization: ``>= 0``, weight of ``|L|^2 / A``, which keeps the lattice nodes that no
            vertex reaches at zero and the normal equations regular (default ``1e-10`` in
            float64, ``1e-6`` in float32; ``0`` fails where the template leaves nodes free).
            The three weights are traced in the compiled solve: registering again with other
            positive weights (a sweep) compiles nothing new; a zero weight drops its term.
        solver: an optimistix least-squares solver or minimiser (default: the dogleg
            trust-region method on the exact Hessian of the loss, an optimistix quasi-Newton
            minimiser whose Hessian is computed, with tolerances ``1e-5`` in float32, ``1e-8``
            in float64; ``optimistix.Dogleg`` (Gauss-Newton) needs hundreds of steps where the
            strain or bending residuals stay large at the optimum, and plain
            ``optimistix.GaussNewton`` can cycle between two assignments of nearest faces and
            never meet its tolerance).
        max_steps, throw, return_solution: as for
            :func:`geomjax.optimize.fit_free_form_deformation` (``throw=True``: a registration
            that does not succeed within ``max_steps`` raises; ``return_solution=True``: the
            ``optimistix.Solution``, whose ``result`` says whether it did).
        implementation: backend of the deformation, the energies and the face search
            (``None``: the defaults, with the Warp search tree when warp-lang is installed;
            ``"jax"``: brute-force search in JAX, for small targets).

    Returns:
        ``(n_1, n_2, n_3, 3)`` lattice displacements: the registered template is
        ``free_form_deform_points(template_points, lattice, origin=origin, extent=extent,
        basis=basis)``. Differentiable with respect to the template and target points
        (implicit adjoint); ``jax.vmap`` over template or target points registers a batch.

    Raises:
        TypeError: non-float points, non-integer faces, mismatched dtypes.
        ValueError: bad shapes (not ``(V, 3)`` / ``(F, 3)``, a ``resolution`` without three
            entries), negative or non-finite weights, face indices out of range, and the errors
            of :func:`geomjax.free_form_deform_points` and the energies.
        RuntimeError: with ``throw=True``, a registration that does not succeed within
            ``max_steps`` (at run time under ``jit``), its message first.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import free_form_deform_points, icosphere
        >>> from geomjax.optimize import register_surface
        >>> sphere = icosphere(2)
        >>> template = jnp.asarray(sphere.points) * 0.9  # a smaller sphere inside the target
        >>> faces = jnp.asarray(sphere.cells)
        >>> box = dict(origin=[-1.5, -1.5, -1.5], extent=[3.0, 3.0, 3.0])
        >>> lattice = register_surface(template, faces, jnp.asarray(sphere.points), faces, (3, 3, 3), **box)
        >>> moved = free_form_deform_points(template, lattice, **box)
        >>> print(np.round(float(jnp.linalg.norm(moved, axis=1).mean()), 2))
        1.0
    """
    template = Mesh(template_points, template_faces)
    target = Mesh(target_points, target_faces)
    if template.points.shape[-1] != 3 or template.cells.shape[-1] != 3 or target.points.shape[-1] != 3 or target.cells.shape[-1] != 3:
        raise ValueError(f"{_NAME}: template and target must be triangle surfaces in 3-D, got points {template.points.shape} and {target.points.shape}")
    if template.points.dtype != target.points.dtype:
        raise TypeError(f"{_NAME}: template_points and target_points must share a dtype, got {template.points.dtype} and {target.points.dtype}")
    resolution = tuple(int(n) for n in resolution)
    if len(resolution) != 3:
        raise ValueError(f"{_NAME}: resolution must have 3 entries, got {resolution}")
    dtype = template.points.dtype
    if regularization is None:
        regularization = _DEFAULT_REGULARIZATION.get(jnp.dtype(dtype), 1e-6)
    strain_weight, bending_weight, regularization = (
        check_weight(name, w, op_name=_NAME)
        for name, w in (("strain_weight", strain_weight), ("bending_weight", bending_weight), ("regularization", regularization))
    )
    hinges = template.hinges if bending_weight > 0 else None
    brute_force = implementation in ("jax", "torch") or not warp_available()
    tree = None
    if not brute_force and not isinstance(target.points, jax.core.Tracer):
        tree = closest_face_tree(_NAME, target.points, target.topology.cells_host)  # built once, eagerly
    if solver is None:
        tolerance = _DEFAULT_TOLERANCE.get(jnp.dtype(dtype), 1e-5)
        solver = _NewtonTrustRegion(rtol=tolerance, atol=tolerance)
    # Positive weights go in as arrays, traced in the compiled solve: a sweep over a weight
    # compiles once (a zero weight drops its term, a different program).
    traced_strain, traced_bending, traced_regularization = (jnp.asarray(w, dtype) if w > 0 else 0.0 for w in (strain_weight, bending_weight, regularization))
    options = dict(
        origin=origin, extent=extent, basis=basis, strain_weight=traced_strain, bending_weight=traced_bending,
        regularization=traced_regularization, implementation=implementation, brute_force=brute_force,
    )  # fmt: skip
    lattice0 = jnp.zeros((*resolution, 3), dtype)
    meshes = (template.points, template.cells, target.points, target.cells, tree, hinges)
    solution = _solve(lattice0, meshes, solver, max_steps, options)
    return fitted(solution, op_name=_NAME, max_steps=max_steps, throw=throw, return_solution=return_solution)


class _NewtonTrustRegion(optx.AbstractQuasiNewton):
    """The dogleg trust-region method on the exact Hessian of the loss: :func:`register_surface`'s
    default solver (an optimistix minimiser; ``optimistix.least_squares`` minimises half the
    sum of squared residuals with it).

    Gauss-Newton (``optimistix.Dogleg``) drops the residuals' second derivatives, which is exact
    for the distance residuals (linear in the lattice for given nearest faces) but not for the
    strain and bending ones: where those stay large at the optimum (a template 10% smaller than
    its target, ``strain_weight=1e-2``), it converges linearly and took 646 steps in float64;
    this method takes 16. Built on optimistix's quasi-Newton solver with the Hessian computed
    (``jax.hessian``, the lattice's size squared) at each accepted point instead of updated.
    A trust region: the nearest faces change from step to step, and a step that raises the loss
    is refused (plain Newton or Gauss-Newton steps can hop between two face assignments). The
    steps solve by SVD: near the optimum the Hessian can be singular to rounding where nodes
    are held only by the regularisation.
    """

    rtol: float
    atol: float
    norm: Callable[[PyTree], Array] = optx.max_norm
    use_inverse: bool = False
    descent: optx.DoglegDescent = eqx.field(default_factory=lambda: _DoglegDescent(linear_solver=lx.SVD()))
    search: optx.ClassicalTrustRegion = eqx.field(default_factory=optx.ClassicalTrustRegion)
    verbose: Callable[..., None] = lambda **_: None
    # The loss's Hessian, bound to the function and its arguments for one step (see step).
    hessian: Callable | None = None

    def init_hessian(self, y, f, grad):
        return optx.FunctionInfo.EvalGradHessian(f, grad, _hessian_operator(jnp.eye(y.size, dtype=y.dtype).reshape(y.shape * 2), y)), None

    def update_hessian(self, y, y_eval, f_info, f_eval_info, hessian_update_state):
        assert self.hessian is not None  # bound by step
        return optx.FunctionInfo.EvalGradHessian(f_eval_info.f, f_eval_info.grad, _hessian_operator(self.hessian(y_eval), y_eval)), None

    def terminate(self, fn, y, args, options, state, tags):
        done, result = super().terminate(fn, y, args, options, state, tags)
        # optimistix checks its tolerances on accepted steps only. At a minimum in float32 the
        # computed loss stops decreasing before the steps meet them (its rounding exceeds the
        # model's predicted decrease): every step is refused and the trust radius (relative to
        # the Newton step) shrinks without end. Below the dtype's epsilon no step can move the
        # lattice: that is a minimum to working precision.
        collapsed = state.search_state.step_size < jnp.finfo(jnp.result_type(*jax.tree.leaves(y))).eps
        return done | collapsed, result

    def step(self, fn, y, args, options, state, tags):
        def hessian(at):
            return jax.hessian(lambda z: fn(z, args)[0])(at)

        return super(_NewtonTrustRegion, eqx.tree_at(lambda s: s.hessian, self, hessian, is_leaf=lambda leaf: leaf is None)).step(
            fn, y, args, options, state, tags
        )


def _hessian_operator(matrix: jax.Array, y: jax.Array) -> lx.PyTreeLinearOperator:
    """``matrix`` (``y.shape * 2``) as a symmetric operator on arrays shaped like ``y``."""
    return lx.PyTreeLinearOperator(matrix, jax.eval_shape(lambda: y), lx.symmetric_tag)


class _DoglegDescent(optx.DoglegDescent):
    """optimistix's dogleg descent with its (unused) initial step norms in the dtype of ``y``.

    optimistix 0.1 starts them as default-dtype scalars: float64 under ``jax_enable_x64``, so a
    float32 solve there failed in a ``lax.cond`` whose branches then differ in dtype.
    """

    def init(self, y, f_info_struct):
        state = super().init(y, f_info_struct)
        dtype = jnp.result_type(*jax.tree.leaves(y))
        return eqx.tree_at(lambda s: (s.newton_norm, s.cauchy_norm), state, (state.newton_norm.astype(dtype), state.cauchy_norm.astype(dtype)))


@eqx.filter_jit
def _solve(lattice0, meshes, solver, max_steps: int, options: dict) -> optx.Solution:
    """The least-squares solve, compiled once per shapes and options (arrays, the positive
    weights among them, traced; the rest static)."""
    template_points, template_cells, target_points, target_cells, tree, hinges = meshes
    residuals = registration_residuals(template_cells, target_cells, tree, hinges, **options)
    solution: optx.Solution = optx.least_squares(
        residuals, solver, lattice0, args=(template_points, target_points), max_steps=max_steps, throw=False, adjoint=optx.ImplicitAdjoint()
    )
    return solution


def registration_residuals(
    template_cells, target_cells, tree, hinges, *, origin, extent, basis, strain_weight, bending_weight, regularization, implementation, brute_force
):
    """The residual function ``residuals(lattice, (template_points, target_points))`` of
    :func:`register_surface` for validated cells, the target's search tree (``None``: built in
    each search, or ``brute_force`` in JAX), the template's hinges (``None``: no bending term)
    and weights (non-negative numbers, a zero dropping its term, or scalar arrays, which keep
    it). Benchmarks hand it to other solvers.
    """

    def nearest_faces(vertices, points):
        if brute_force:
            return closest_faces_brute_force(points, vertices, target_cells)[0]
        search_tree = tree if tree is not None else (bvh_vertices32(vertices), target_cells.reshape(-1))
        return search_closest_faces(search_tree, vertices, target_cells, points)

    def residuals(lattice, args):
        template_points, target_points = args
        moved = free_form_deform_points(template_points, lattice, origin=origin, extent=extent, basis=basis, implementation=implementation)
        corner_areas = _corner_areas(template_points, template_cells)
        area = jnp.sum(corner_areas)
        # Not differentiated: the residuals are functions of the moved vertices and the chosen
        # faces' corners.
        face = nearest_faces(jax.lax.stop_gradient(target_points), jax.lax.stop_gradient(moved))
        a, b, c = (target_points[target_cells[face, k]] for k in range(3))
        distance = jnp.sum(triangle_normal(a, b, c) * (moved - a), axis=-1)
        parts = [jnp.sqrt(corner_areas / area) * distance / jnp.sqrt(area)]
        if _weighted(strain_weight):
            # Unit Lame parameters: mu = 1, lambda / 2 + mu / 2 = 1 for triangles.
            strains, _ = strain_residuals(moved[None], template_points[None], template_cells, 1.0, 1.0)
            parts.append(jnp.sqrt(strain_weight / area) * strains.reshape(-1))
        if hinges is not None:
            angles, _ = bending_residuals(moved[None], template_points[None], hinges)
            parts.append(jnp.sqrt(bending_weight / area) * angles.reshape(-1))
        if _weighted(regularization):
            parts.append(jnp.sqrt(regularization / area) * lattice.reshape(-1))
        return jnp.concatenate(parts)

    return residuals


def _weighted(weight) -> bool:
    """Whether a residual term is present: a weight given as an array (possibly traced), or a
    positive number."""
    return not isinstance(weight, int | float) or weight > 0


def _corner_areas(points: jax.Array, faces: jax.Array) -> jax.Array:
    """``(V,)`` a third of the area of each vertex's triangles."""
    a, b, c = (points[faces[:, k]] for k in range(3))
    area = 0.5 * jnp.linalg.norm(jnp.cross(b - a, c - a), axis=-1)
    return jnp.zeros(points.shape[0], points.dtype).at[faces.reshape(-1)].add(jnp.repeat(area / 3, 3))
