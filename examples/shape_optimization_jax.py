"""Shape optimisation with ``jax.grad``: fit a free-form-deformation lattice so a sphere becomes a peanut.

What it shows: a unit icosphere is deformed by a Bernstein FFD lattice
(``geomjax.free_form_deform_points``); the lattice is optimised with ``optimistix.LBFGS`` (a
limited-memory quasi-Newton method with a backtracking line search) so the deformed surface
matches a target (an elongated body pinched at the waist, ``_shape_problem.py``).
The loss, differentiated end to end with ``jax.grad`` and compiled with ``jax.jit``, is

* the mean squared signed distance of the deformed vertices to the target
  (``geomjax.signed_distance_field``, differentiable with respect to the query points),
* ``geomjax.simplex_strain_energy`` of the surface triangles against the sphere (small weight),
* ``geomjax.simplex_inversion_energy`` of a tetrahedral grid carried by the same FFD (keeps the
  map from folding),
* ``geomjax.closed_surface_volume_energy`` towards the target's volume.

Outputs (PNG, in ``examples/output/`` or ``--output-dir``): ``shape_optimization_jax.png`` (target,
initial and optimised surfaces over the translucent target) and ``shape_optimization_jax_loss.png``
(loss history per term). It prints the initial and final loss and the two-sided distance to the
target.

The solver is stepped one iteration at a time (``solver.init`` / ``solver.step`` /
``solver.terminate``, the loop ``optimistix.minimise`` runs) so that the script can record the loss
of every accepted iterate; ``optimistix.minimise(loss, solver, lattice, has_aux=True)`` gives the
same optimum in one call.

Run:
    python examples/shape_optimization_jax.py           # under a minute on a 2-core CPU
    python examples/shape_optimization_jax.py --full    # finer sphere and lattice, more steps
    python examples/shape_optimization_jax.py --smoke   # seconds; used by tests/test_examples.py
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from _render import loss_curves, overlay_with_target
from _shape_problem import SIZES, distance_report, make_problem, objective_terms
from tqdm import tqdm

import geomjax


def main() -> None:
    geomjax.enable_compilation_cache()  # later runs load the compiled programs instead of compiling them
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="full size: subdivision-5 sphere, 8x6x6 lattice, 2000 steps")
    size.add_argument("--smoke", action="store_true", help="tiny size for the tests (a few seconds)")
    parser.add_argument("--iterations", type=int, help="override the largest number of L-BFGS steps")
    parser.add_argument("--output-dir", type=Path, default=Path(__file__).parent / "output")
    args = parser.parse_args()
    config = SIZES["full" if args.full else "smoke" if args.smoke else "default"]
    iterations = args.iterations or config["iterations"]

    problem = make_problem(config["subdivisions"], config["lattice_shape"])
    arrays = {
        name: jnp.asarray(getattr(problem, name))
        for name in ("source_points", "triangles", "target_points", "target_triangles", "probe_points", "probe_tets")
    }
    print(f"sphere: {problem.source_points.shape[0]} vertices, target: {problem.target_triangles.shape[0]} triangles, "
          f"lattice {problem.lattice_shape}, at most {iterations} L-BFGS steps")

    def loss(lattice, args):
        terms = objective_terms(geomjax, lattice, **arrays, problem=problem)
        return sum(terms.values()), terms  # (value, aux), as optimistix's solvers take it

    # Tolerances on the relative change of the loss and the lattice between accepted steps.
    solver = optx.LBFGS(rtol=1e-7, atol=1e-9)
    lattice = jnp.asarray(problem.initial_lattice())
    value_struct, terms_struct = jax.eval_shape(loss, lattice, None)
    state = solver.init(loss, lattice, None, {}, value_struct, terms_struct, frozenset())

    @eqx.filter_jit
    def step(lattice, state):
        lattice, state, _ = solver.step(loss, lattice, None, {}, state, frozenset())
        done, result = solver.terminate(loss, lattice, None, {}, state, frozenset())
        return lattice, state, done, result

    # After each step, state.f_info.f and state.aux are the loss and its terms at the accepted
    # lattice (the first step accepts the initial one).
    history: dict[str, list[float]] = {"total": []}
    start = time.perf_counter()
    progress = tqdm(range(iterations), desc="L-BFGS", unit="step")
    for _ in progress:
        lattice, state, done, result = step(lattice, state)
        history["total"].append(float(state.f_info.f))
        for name, term in state.aux.items():
            history.setdefault(name, []).append(float(term))
        progress.set_postfix(loss=f"{history['total'][-1]:.3e}")
        if bool(done):
            break
    stopped = "converged" if bool(done) and bool(result == optx.RESULTS.successful) else "step limit reached"
    print(f"optimisation: {len(history['total'])} steps ({stopped}), {time.perf_counter() - start:.1f} s "
          "(the first step includes compilation)")
    final_terms = state.aux

    surface = np.asarray(geomjax.free_form_deform_points(
        arrays["source_points"], lattice, origin=problem.origin, extent=problem.extent, basis="bernstein"))
    before = distance_report(problem.source_points, problem)
    after = distance_report(surface, problem)
    print("final terms: " + ", ".join(f"{name} {float(term):.3e}" for name, term in final_terms.items()))
    print(f"distance to target: mean {before['mean']:.4f} -> {after['mean']:.4f}, "
          f"Hausdorff {before['hausdorff']:.4f} -> {after['hausdorff']:.4f}")
    print(f"loss: initial {history['total'][0]:.6e} final {history['total'][-1]:.6e}")

    overlay_with_target(args.output_dir / "shape_optimization_jax.png",
                        [("initial sphere", problem.source_points), (f"after {len(history['total'])} L-BFGS steps", surface)],
                        problem.triangles, problem.target_points, problem.target_triangles)
    loss_curves(args.output_dir / "shape_optimization_jax_loss.png", {"loss terms": history},
                title="FFD shape fit (JAX, jax.grad + optimistix.LBFGS)", xlabel="L-BFGS step")


if __name__ == "__main__":
    main()
