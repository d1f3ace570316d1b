"""Shape optimisation from PyTorch: the FFD peanut fit of ``shape_optimization_jax.py`` through ``torch_bridge``.

What it shows: the same problem and the same objective (``_shape_problem.py``) written against
``torch_bridge``, which exposes geomjax's ops to PyTorch with the reference signatures:
``free_form_deform_points``, ``signed_distance_field`` (differentiable in the query points),
``simplex_strain_energy``, ``simplex_inversion_energy`` and ``closed_surface_volume_energy``.
The lattice is a ``torch`` leaf tensor optimised with ``torch.optim.Adam``; gradients flow back
through the bridge's autograd formulas (JAX VJPs).

What is compiled: the whole loss function (lattice -> deformed surface and probe grid -> the four
weighted terms and their sum) goes through ``torch.compile(..., fullgraph=True)``, so the graph
has no breaks: every geomjax op appears as one custom op (``torch.ops.geomjax.*``) and the
arithmetic between them is compiled by the chosen backend (``--backend``, default ``inductor``;
``--smoke`` uses ``eager``, which still captures the full graph but skips Inductor's C++ code
generation, to stay fast in the tests). The backward pass and the optimiser step run eagerly.

Outputs (PNG, in ``examples/output/`` or ``--output-dir``): ``shape_optimization_torch.png``
(target, initial and optimised surfaces) and ``shape_optimization_torch_loss.png`` (loss history
per term). It prints the initial and final loss and the two-sided distance to the target.

Run:
    python examples/shape_optimization_torch.py           # about a minute on a 2-core CPU (300 steps)
    python examples/shape_optimization_torch.py --full    # finer sphere and lattice, more steps
    python examples/shape_optimization_torch.py --smoke   # seconds; used by tests/test_examples.py
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from _render import loss_curves, overlay_with_target
from _shape_problem import LEARNING_RATE, SIZES, distance_report, make_problem, objective_terms
from tqdm import tqdm

import geomjax
import torch_bridge

# Each bridged op is a separate JAX call (forward, then its VJP in backward), where the JAX example
# compiles the whole step into one program, so a step costs several times more here; the default
# run takes fewer steps to stay near a minute.
DEFAULT_ITERATIONS = 300


def main() -> None:
    geomjax.enable_compilation_cache()  # later runs load the compiled programs instead of compiling them
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="full size: subdivision-5 sphere, 8x6x6 lattice, 2000 steps")
    size.add_argument("--smoke", action="store_true", help="tiny size for the tests (a few seconds)")
    parser.add_argument("--iterations", type=int, help="override the number of Adam steps")
    parser.add_argument("--learning-rate", type=float, default=LEARNING_RATE)
    parser.add_argument("--backend", help="torch.compile backend (default: inductor; eager with --smoke)")
    parser.add_argument("--output-dir", type=Path, default=Path(__file__).parent / "output")
    args = parser.parse_args()
    config = SIZES["full" if args.full else "smoke" if args.smoke else "default"]
    iterations = args.iterations or (config["iterations"] if args.full or args.smoke else DEFAULT_ITERATIONS)
    backend = args.backend or ("eager" if args.smoke else "inductor")

    problem = make_problem(config["subdivisions"], config["lattice_shape"])
    tensors = {
        name: torch.tensor(getattr(problem, name))
        for name in ("source_points", "triangles", "target_points", "target_triangles", "probe_points", "probe_tets")
    }
    print(f"sphere: {problem.source_points.shape[0]} vertices, target: {problem.target_triangles.shape[0]} triangles, "
          f"lattice {problem.lattice_shape}, {iterations} Adam steps, torch.compile backend {backend!r}")

    def loss(lattice):
        terms = objective_terms(torch_bridge, lattice, **tensors, problem=problem)
        return sum(terms.values()), terms

    compiled_loss = torch.compile(loss, fullgraph=True, backend=backend)

    lattice = torch.tensor(problem.initial_lattice(), requires_grad=True)
    optimizer = torch.optim.Adam([lattice], lr=args.learning_rate)
    history: dict[str, list[float]] = {"total": []}
    start = time.perf_counter()
    progress = tqdm(range(iterations + 1), desc="Adam", unit="step")
    for iteration in progress:
        value, terms = compiled_loss(lattice)
        history["total"].append(value.item())
        for name, term in terms.items():
            history.setdefault(name, []).append(term.item())
        progress.set_postfix(loss=f"{value.item():.3e}")
        if iteration == iterations:  # the last pass only measures the final lattice
            break
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
    print(f"optimisation: {time.perf_counter() - start:.1f} s (first step includes compilation)")

    with torch.no_grad():
        surface = torch_bridge.free_form_deform_points(
            tensors["source_points"], lattice, origin=problem.origin, extent=problem.extent, basis="bernstein").numpy()
    before = distance_report(problem.source_points, problem)
    after = distance_report(surface, problem)
    print("final terms: " + ", ".join(f"{name} {values[-1]:.3e}" for name, values in history.items() if name != "total"))
    print(f"distance to target: mean {before['mean']:.4f} -> {after['mean']:.4f}, "
          f"Hausdorff {before['hausdorff']:.4f} -> {after['hausdorff']:.4f}")
    print(f"loss: initial {history['total'][0]:.6e} final {history['total'][-1]:.6e}")

    overlay_with_target(args.output_dir / "shape_optimization_torch.png",
                        [("initial sphere", problem.source_points), (f"after {iterations} steps", np.asarray(surface))],
                        problem.triangles, problem.target_points, problem.target_triangles)
    loss_curves(args.output_dir / "shape_optimization_torch_loss.png", {"loss terms": history},
                title=f"FFD shape fit (PyTorch, torch_bridge + torch.compile[{backend}])")


if __name__ == "__main__":
    main()
