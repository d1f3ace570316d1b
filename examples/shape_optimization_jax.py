"""Shape optimisation with ``jax.grad``: fit a free-form-deformation lattice so a sphere becomes a peanut.

What it shows: a unit icosphere is deformed by a Bernstein FFD lattice
(``geomjax.free_form_deform_points``); the lattice is optimised with a hand-written Adam so the
deformed surface matches a target (an elongated body pinched at the waist, ``_shape_problem.py``).
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

Run:
    python examples/shape_optimization_jax.py           # about a minute on a 2-core CPU
    python examples/shape_optimization_jax.py --full    # finer sphere and lattice, more steps
    python examples/shape_optimization_jax.py --smoke   # seconds; used by tests/test_examples.py
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _render import loss_curves, overlay_with_target
from _shape_problem import (
    LEARNING_RATE,
    SIZES,
    distance_report,
    make_problem,
    objective_terms,
)
from tqdm import tqdm

import geomjax


def adam(learning_rate: float, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-8):
    """Adam as ``(init, update)``, a few lines instead of a dependency on an optimiser library."""

    def init(params):
        return jnp.zeros_like(params), jnp.zeros_like(params), jnp.zeros((), jnp.int32)

    def update(params, grad, state):
        first, second, count = state
        count = count + 1
        first = beta1 * first + (1 - beta1) * grad
        second = beta2 * second + (1 - beta2) * grad**2
        step = jnp.asarray(count, params.dtype)
        first_hat = first / (1 - beta1**step)
        second_hat = second / (1 - beta2**step)
        return params - learning_rate * first_hat / (jnp.sqrt(second_hat) + eps), (first, second, count)

    return init, update


def main() -> None:
    geomjax.enable_compilation_cache()  # later runs load the compiled programs instead of compiling them
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="full size: subdivision-5 sphere, 8x6x6 lattice, 2000 steps")
    size.add_argument("--smoke", action="store_true", help="tiny size for the tests (a few seconds)")
    parser.add_argument("--iterations", type=int, help="override the number of Adam steps")
    parser.add_argument("--learning-rate", type=float, default=LEARNING_RATE)
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
          f"lattice {problem.lattice_shape}, {iterations} Adam steps")

    def loss(lattice):
        terms = objective_terms(geomjax, lattice, **arrays, problem=problem)
        return sum(terms.values()), terms

    init, update = adam(args.learning_rate)

    @jax.jit
    def step(lattice, state):
        (value, terms), grad = jax.value_and_grad(loss, has_aux=True)(lattice)
        lattice, state = update(lattice, grad, state)
        return lattice, state, value, terms

    lattice = jnp.asarray(problem.initial_lattice())
    state = init(lattice)
    history: dict[str, list[float]] = {"total": []}
    start = time.perf_counter()
    progress = tqdm(range(iterations), desc="Adam", unit="step")
    for _ in progress:
        lattice, state, value, terms = step(lattice, state)
        history["total"].append(float(value))
        for name, term in terms.items():
            history.setdefault(name, []).append(float(term))
        progress.set_postfix(loss=f"{float(value):.3e}")
    # One more evaluation of the compiled step gives the loss of the final lattice (its update is dropped).
    _, _, final_value, final_terms = step(lattice, state)
    history["total"].append(float(final_value))
    for name, term in final_terms.items():
        history[name].append(float(term))
    print(f"optimisation: {time.perf_counter() - start:.1f} s (first step includes compilation)")

    surface = np.asarray(geomjax.free_form_deform_points(
        arrays["source_points"], lattice, origin=problem.origin, extent=problem.extent, basis="bernstein"))
    before = distance_report(problem.source_points, problem)
    after = distance_report(surface, problem)
    print("final terms: " + ", ".join(f"{name} {float(term):.3e}" for name, term in final_terms.items()))
    print(f"distance to target: mean {before['mean']:.4f} -> {after['mean']:.4f}, "
          f"Hausdorff {before['hausdorff']:.4f} -> {after['hausdorff']:.4f}")
    print(f"loss: initial {history['total'][0]:.6e} final {history['total'][-1]:.6e}")

    overlay_with_target(args.output_dir / "shape_optimization_jax.png",
                        [("initial sphere", problem.source_points), (f"after {iterations} steps", surface)],
                        problem.triangles, problem.target_points, problem.target_triangles)
    loss_curves(args.output_dir / "shape_optimization_jax_loss.png", {"loss terms": history},
                title="FFD shape fit (JAX, jax.grad + hand-written Adam)")


if __name__ == "__main__":
    main()
