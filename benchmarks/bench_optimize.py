"""Shape optimisation on a real mesh: iterations and time to a given objective, per method.

Issue 26, item 1. The design is the vertex set of ``fertility.off`` (``../shared/meshes``,
4,494 vertices, genus 4; ``decimated-knight.off``, 502 vertices, with ``--quick``), normalised
to the unit box. The objective is a sparse-data fit with a membrane regulariser, the shape of
many shape-optimisation problems (a few measured points, a mesh that must stay smooth):

    f(y) = 1/2 sum_{i in S} |y_i - t_i|^2 + mu/2 sum_{(i,j) in E} |(y_i - y_j) - (x_i - x_j)|^2,

with ``t = x + 0.05 (sin 2x_1, sin 2x_2, sin 2x_0)`` a smooth target measured on 2% of the
vertices ``S`` and ``mu = 1`` on the edges ``E``. The minimiser is the smooth deformation that
the membrane spreads from the measured vertices; the raw gradient carries it one edge ring per
step (the Hessian's condition grows with the mesh's diameter in edges), so steepest descent
needs thousands of steps. Each method runs until ``f <= f* + 0.01 (f0 - f*)``, with ``f*`` the minimum over
vertex positions (a sparse direct solve: ``f`` is quadratic):

* ``steepest descent``: optimistix's steepest descent with backtracking Armijo, on the vertices;
* ``Sobolev descent``: :class:`geomjax.optimize.SobolevGradientDescent` (``length_scale`` 0.1,
  its default solve tolerance 1e-3), on the vertices;
* ``LBFGS (lattice)`` / ``BFGS (lattice)``: ``optimistix.LBFGS`` / ``optimistix.BFGS`` on the
  displacements of a 6^3 Bernstein FFD lattice around the mesh (648 parameters), whose minimum
  ``f*_lattice`` may lie above the target (reported: the lattice cannot represent every
  deformation).

Each method's step is jitted once (compile excluded); the time is the loop's to the target.
Rows: iterations, seconds, the final objective over ``f0``, and whether the target was reached.

Table ``optimize_fits`` (issue 26, item 2): :func:`geomjax.optimize.fit_free_form_deformation`
(a 6^3 Bernstein lattice, 648 parameters, ``regularization=1e-9``: the box's corner nodes hardly
touch the mesh) and :func:`geomjax.optimize.fit_morph` (40 controls of
radius 0.4) fitted to the same mesh's vertices moved by the smooth target deformation, against
``scipy.optimize.least_squares`` (``method="lm"``, exact Jacobians from ``jax.jacfwd``, jitted,
tolerances 1e-12) on the same residuals: the time of a warm call of each (compile excluded), the
final residual norm of each, and the ratio ``scipy / geomjax``.

Usage: ``python benchmarks/bench_optimize.py [--quick]``.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import meshio
import numpy as np
import optimistix as optx
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _harness import QUICK, report

jax.config.update("jax_enable_x64", True)

import geomjax as gj
from geomjax.optimize import SobolevGradientDescent

MESH_DIR = Path(os.environ.get("GEOMJAX_MESH_DIR", Path(__file__).resolve().parents[2] / "shared" / "meshes"))
MU = 1.0
FRACTION_MEASURED = 0.02
MAX_STEPS = 2000 if QUICK else 5000
TARGET_FRACTION = 0.01  # reach f* + 1% of the initial gap
FFD_RIDGE = 1e-9  # the lattice fit's regularization


class _Steepest(optx.AbstractGradientDescent):
    """optimistix's steepest descent direction with a backtracking Armijo search."""

    rtol: float
    atol: float
    norm: object
    descent: optx.SteepestDescent
    search: optx.BacktrackingArmijo

    def __init__(self, rtol, atol):
        self.rtol, self.atol, self.norm = rtol, atol, optx.max_norm
        self.descent = optx.SteepestDescent()
        self.search = optx.BacktrackingArmijo(step_init=1.0)


def _problem(file: str):
    mesh = meshio.read(MESH_DIR / file)
    x = np.asarray(mesh.points, np.float64)
    x = (x - x.min(axis=0)) / np.max(x.max(axis=0) - x.min(axis=0))
    cells = mesh.cells_dict["triangle"].astype(np.int32)
    edges = np.unique(np.sort(np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [2, 0]]]), axis=1), axis=0)
    target = x + 0.05 * np.stack([np.sin(2 * x[:, 1]), np.sin(2 * x[:, 2]), np.sin(2 * x[:, 0])], axis=1)
    rng = np.random.default_rng(0)
    measured = np.sort(rng.choice(len(x), max(8, int(FRACTION_MEASURED * len(x))), replace=False))
    return x, cells, edges, target, measured


def _objective(x, edges, target, measured):
    rest = jnp.asarray(x[edges[:, 1]] - x[edges[:, 0]])
    e0, e1, t, s = jnp.asarray(edges[:, 0]), jnp.asarray(edges[:, 1]), jnp.asarray(target[measured]), jnp.asarray(measured)

    def f(y, args):
        fit = 0.5 * jnp.sum((y[s] - t) ** 2)
        membrane = 0.5 * MU * jnp.sum(((y[e1] - y[e0]) - rest) ** 2)
        return fit + membrane

    return f


def _exact_minimum(x, edges, target, measured) -> float:
    """min f over the vertices: a sparse SPD solve (f is quadratic, one system per coordinate)."""
    n = len(x)
    rows = np.arange(len(edges))
    incidence = sp.csr_matrix((np.r_[-np.ones(len(edges)), np.ones(len(edges))], (np.r_[rows, rows], np.r_[edges[:, 0], edges[:, 1]])), shape=(len(edges), n))
    selector = sp.csr_matrix((np.ones(len(measured)), (np.arange(len(measured)), measured)), shape=(len(measured), n))
    system = selector.T @ selector + MU * (incidence.T @ incidence)
    rhs = selector.T @ target[measured] + MU * incidence.T @ (x[edges[:, 1]] - x[edges[:, 0]])
    solution = np.stack([spla.spsolve(system.tocsc(), rhs[:, k]) for k in range(3)], axis=1)
    return float(_objective(x, edges, target, measured)(jnp.asarray(solution), None))


def _run(solver, fn, y0, goal: float):
    """Steps of ``solver`` until ``fn <= goal``: ``(iterations, seconds, final f)``; compile excluded."""
    options, f_struct = {}, jax.eval_shape(lambda: fn(y0, None))

    def with_aux(y, args):  # optimistix's solvers take (value, aux) functions
        return fn(y, args), None

    state = solver.init(with_aux, y0, None, options, f_struct, None, frozenset())
    step = eqx.filter_jit(lambda y, state: solver.step(with_aux, y, None, options, state, frozenset())[:2])
    value = jax.jit(lambda y: fn(y, None))
    jax.block_until_ready(step(y0, state))  # compile
    y, start, iterations = y0, time.perf_counter(), 0
    while iterations < MAX_STEPS:
        y, state = step(y, state)
        iterations += 1
        if iterations % 5 == 0 and float(value(y)) <= goal:
            break
    jax.block_until_ready(y)
    return iterations, time.perf_counter() - start, float(value(y))


def main() -> None:
    file = "decimated-knight.off" if QUICK else "fertility.off"
    x, cells, edges, target, measured = _problem(file)
    fn = _objective(x, edges, target, measured)
    y0 = jnp.asarray(x)
    f0, best = float(fn(y0, None)), _exact_minimum(x, edges, target, measured)
    goal = best + TARGET_FRACTION * (f0 - best)
    print(f"{file}: {len(x)} vertices, f0 = {f0:.4g}, f* = {best:.4g}, goal {goal:.4g}", flush=True)

    # The lattice parametrisation: y = FFD(x; lattice), a 6^3 Bernstein lattice over the unit box.
    resolution = (6, 6, 6)

    def lattice_fn(lattice, args):
        y = gj.free_form_deform_points(y0, lattice, origin=[-0.01] * 3, extent=[1.02] * 3, implementation="jax")
        return fn(y, args)

    lattice0 = jnp.zeros((*resolution, 3))
    methods = {
        "steepest descent": (_Steepest(rtol=0.0, atol=0.0), fn, y0),
        "Sobolev descent": (SobolevGradientDescent(cells, length_scale=0.1, rtol=0.0, atol=0.0), fn, y0),
        "LBFGS (lattice)": (optx.LBFGS(rtol=0.0, atol=0.0), lattice_fn, lattice0),
        "BFGS (lattice)": (optx.BFGS(rtol=0.0, atol=0.0), lattice_fn, lattice0),
    }
    rows = []
    for name, (solver, objective, start) in methods.items():
        iterations, seconds, final = _run(solver, objective, start, goal)
        reached = final <= goal
        rows.append(
            {
                "mesh": file,
                "method": name,
                "iterations": iterations,
                "time_s": seconds,
                "objective_over_f0": final / f0,
                "goal_over_f0": goal / f0,
                "reached": reached,
            }
        )
        print(f"{name}: {iterations} iterations, {seconds:.2f} s, f/f0 = {final / f0:.4g} (goal {goal / f0:.4g}), reached: {reached}", flush=True)
    report("optimize_quick" if QUICK else "optimize", rows)
    report("optimize_fits_quick" if QUICK else "optimize_fits", fit_rows(file, x, cells, target))


def _timed(call, repeat: int = 3):
    """``(best seconds of a warm call, result)``; the first call compiles."""
    result = jax.block_until_ready(call())
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        result = jax.block_until_ready(call())
        best = min(best, time.perf_counter() - start)
    return best, result


def fit_rows(file: str, x: np.ndarray, cells: np.ndarray, target: np.ndarray) -> list[dict]:
    """geomjax's fits and registration against scipy's Levenberg-Marquardt on the same residuals."""
    from scipy.optimize import least_squares

    from geomjax.optimize import fit_free_form_deformation, fit_morph, register_surface
    from geomjax.optimize._registration import registration_residuals
    from geomjax.query.bvh import closest_face_tree

    points, targets = jnp.asarray(x), jnp.asarray(target)
    box = {"origin": [-0.01] * 3, "extent": [1.02] * 3}
    controls = jnp.asarray(x[np.random.default_rng(1).choice(len(x), 40, replace=False)])
    cases = {
        # The box's corner nodes barely touch the mesh: a tiny ridge keeps them determined.
        "FFD lattice 6^3 (648 parameters)": (
            jax.jit(lambda p, t: fit_free_form_deformation(p, t, (6, 6, 6), regularization=FFD_RIDGE, **box)),
            lambda params: jnp.concatenate(
                [
                    (gj.free_form_deform_points(points, params.reshape(6, 6, 6, 3), **box, implementation="jax") - targets).reshape(-1),
                    math.sqrt(FFD_RIDGE) * params,
                ]
            ),
            216 * 3,
        ),
        "morph, 40 controls (120 parameters)": (
            jax.jit(lambda p, t: fit_morph(p, t, controls, radius=0.4)),
            lambda params: gj.morph_points(points, controls, params.reshape(40, 3), radius=0.4, implementation="jax") - targets,
            120,
        ),
    }
    # Registration: the mesh's surface onto its moved copy, by nearest faces (no correspondences),
    # with a 5^3 lattice and a small membrane regulariser.
    register_options = {"strain_weight": 1e-6, "regularization": 1e-10, **box}
    device_cells = jnp.asarray(cells)
    tree = closest_face_tree("register_surface", targets, cells)  # what register_surface builds
    register_residuals = registration_residuals(
        device_cells, device_cells, tree, None, basis="bernstein", bending_weight=0.0, implementation=None, brute_force=False, **register_options
    )
    cases["registration onto the moved surface, 5^3 lattice (375 parameters)"] = (
        lambda p, t: register_surface(p, cells, t, cells, (5, 5, 5), **register_options),  # eager: the target's search tree is built once
        lambda params: register_residuals(params.reshape(5, 5, 5, 3), (points, targets)),
        125 * 3,
    )
    rows = []
    for name, (fit, residual, size) in cases.items():
        ours_s, params = _timed(lambda fit=fit: fit(points, targets))
        ours_norm = float(jnp.linalg.norm(residual(params.reshape(-1))))
        fun = jax.jit(lambda v, residual=residual: residual(v).reshape(-1))
        jac = jax.jit(jax.jacfwd(lambda v, residual=residual: residual(v).reshape(-1)))
        x0 = np.zeros(size)
        fun(x0), jac(x0)  # compile

        def scipy_fit(fun=fun, jac=jac, x0=x0):
            return least_squares(lambda v: np.asarray(fun(v)), x0, jac=lambda v: np.asarray(jac(v)), method="lm", ftol=1e-12, xtol=1e-12, gtol=1e-12)

        scipy_s, result = _timed(scipy_fit)
        scipy_norm = float(np.linalg.norm(result.fun))
        rows.append(
            {
                "mesh": file,
                "fit": name,
                "geomjax_s": ours_s,
                "scipy_s": scipy_s,
                "speedup": scipy_s / ours_s,
                "geomjax_residual": ours_norm,
                "scipy_residual": scipy_norm,
            }
        )
        print(f"{name}: geomjax {ours_s * 1e3:.1f} ms (residual {ours_norm:.6g}), scipy {scipy_s * 1e3:.1f} ms (residual {scipy_norm:.6g})", flush=True)
    return rows


if __name__ == "__main__":
    main()
