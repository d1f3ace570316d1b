"""Sobolev-smoothed gradient descent: fit a sphere to a sparse point cloud with raw and with H^1 gradients.

What it shows: the loss is the mean squared distance from a few hundred sample points of a target
(the peanut of ``_shape_problem.py``) to the current surface, ``geomjax.signed_distance_field``
with the *mesh vertices* as the differentiated argument. Its raw gradient with respect to the
vertices is spiky: each sample pulls only the three corners of its closest triangle. Descent on
all vertices with that gradient (``optimistix.GradientDescent``) grows tents and crumples the
surface. ``geomjax.optimize.SobolevGradientDescent`` filters the same gradient with the
Helmholtz / H^1 smoother of ``geomjax.sobolev_deform_points`` (``(M + l^2 K) u = M d`` on the
current surface), which spreads each pull over a length ``l``: the surface stays smooth while it
converges. Both are optimistix minimisers with fixed steps (``optimistix.LearningRate``), stepped
one iteration at a time to record the history.

Outputs (PNG, in ``examples/output/`` or ``--output-dir``): ``sobolev_smoothing.png``: the first
raw gradient and the first Sobolev-smoothed step on the sphere (colour: the descent direction's
component along the outward normal, red outward), then both surfaces after the descent;
``sobolev_smoothing_loss.png``: loss and roughness (``geomjax.surface_bending_energy`` against
the sphere, which also counts the wanted change of shape) per step for both.

Run:
    python examples/sobolev_smoothing.py           # about a minute on a 2-core CPU
    python examples/sobolev_smoothing.py --full    # finer sphere, more samples and steps
    python examples/sobolev_smoothing.py --smoke   # seconds; used by tests/test_examples.py
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
from _render import figure_of_surfaces, loss_curves
from _shape_problem import peanut, vertex_normals
from tqdm import tqdm

import geomjax
from geomjax.optimize import SobolevGradientDescent

SIZES = {
    "smoke": {"subdivisions": 2, "samples": 60, "steps": 10},
    "default": {"subdivisions": 4, "samples": 800, "steps": 150},
    "full": {"subdivisions": 4, "samples": 1500, "steps": 300},
}


def main() -> None:
    geomjax.enable_compilation_cache()  # later runs load the compiled programs instead of compiling them
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="full size: subdivision-4 sphere, 1500 samples, 300 steps")
    size.add_argument("--smoke", action="store_true", help="tiny size for the tests (a few seconds)")
    parser.add_argument("--steps", type=int, help="override the number of descent steps")
    parser.add_argument("--step-size", type=float, default=0.2, help="step along the raw negative gradient")
    parser.add_argument("--sobolev-step-size", type=float, default=1.0,
                        help="step along the smoothed one (smoothing shrinks the spikes, so it can go further)")
    parser.add_argument("--length-scale", type=float, default=0.5, help="Sobolev smoothing length")
    parser.add_argument("--output-dir", type=Path, default=Path(__file__).parent / "output")
    args = parser.parse_args()
    config = SIZES["full" if args.full else "smoke" if args.smoke else "default"]
    steps = args.steps or config["steps"]

    sphere = geomjax.icosphere(config["subdivisions"], dtype=jnp.float32)
    target = peanut(np.asarray(geomjax.icosphere(config["subdivisions"] + 2, dtype=jnp.float32).points))
    samples = jnp.asarray(target[np.random.default_rng(0).choice(target.shape[0], config["samples"], replace=False)])
    triangles, hinges = sphere.cells, sphere.hinges
    print(f"sphere: {sphere.n_points} vertices; {samples.shape[0]} target samples; {steps} steps, "
          f"step size {args.step_size} (raw) / {args.sobolev_step_size} (Sobolev), Sobolev length {args.length_scale}")

    def loss(points, args):
        distance, _, _ = geomjax.signed_distance_field(points, triangles, samples)
        return jnp.sum(distance**2), None  # (value, aux), as optimistix's solvers take it

    def roughness(points):
        return geomjax.surface_bending_energy(points, sphere.points, hinges)

    solvers = {
        "raw gradient": optx.GradientDescent(learning_rate=args.step_size, rtol=0.0, atol=0.0),
        # The filter is assembled on the current surface: the step is smooth on the shape it moves.
        "Sobolev gradient": SobolevGradientDescent(triangles, length_scale=args.length_scale, rtol=0.0, atol=0.0,
                                                   search=optx.LearningRate(args.sobolev_step_size)),
    }
    history: dict[str, dict[str, list[float]]] = {}
    first_steps, final_points = {}, {}
    start = time.perf_counter()
    for name, solver in solvers.items():
        points = sphere.points
        f_struct = jax.ShapeDtypeStruct((), points.dtype)
        state = solver.init(loss, points, None, {}, f_struct, None, frozenset())
        # optimistix's step evaluates the loss at the point it moves to (y_eval), accepting it on
        # the next call: y_eval is the descent's iterate.
        step = eqx.filter_jit(lambda y, state, solver=solver: solver.step(loss, y, None, {}, state, frozenset())[:2])
        for iteration in tqdm(range(steps + 1), desc=name, unit="step"):
            value = float(loss(points, None)[0])
            history.setdefault("loss", {}).setdefault(name, []).append(value)
            history.setdefault("bending energy (roughness)", {}).setdefault(name, []).append(float(roughness(points)))
            if iteration == steps:  # the last pass only measures the final surface
                break
            _, state = step(points, state)
            if iteration == 0:
                first_steps[name] = np.asarray(state.y_eval - points)
            points = state.y_eval
        final_points[name] = np.asarray(points)
    print(f"descent: {time.perf_counter() - start:.1f} s (first steps include compilation)")
    for name in solvers:
        print(f"{name:>17}: loss {history['loss'][name][0]:.4e} -> {history['loss'][name][-1]:.4e}, "
              f"bending energy {history['bending energy (roughness)'][name][-1]:.4g}, "
              f"inverted triangles {count_inverted(final_points[name], np.asarray(triangles))}")

    normals = vertex_normals(np.asarray(sphere.points), np.asarray(triangles))
    panels = []
    for name, update in first_steps.items():
        outward = np.sum(update * normals, axis=1)
        bound = float(np.abs(outward).max()) or 1.0
        panels.append({"points": sphere.points, "triangles": triangles, "colour_by": outward, "cmap": "coolwarm",
                       "clim": (-bound, bound), "title": f"first step, {name}\n(normal component, max {bound:.2g})"})
    for name, points in final_points.items():
        panels.append({"points": points, "triangles": triangles, "colour": "tab:blue" if name.startswith("Sobolev") else "tab:red",
                       "title": f"{name} descent, {steps} steps"})
    figure_of_surfaces(args.output_dir / "sobolev_smoothing.png", panels)
    loss_curves(args.output_dir / "sobolev_smoothing_loss.png", history, title="raw vs Sobolev-smoothed descent",
                xlabel="step")
    print(f"loss: initial {history['loss']['Sobolev gradient'][0]:.6e} final {history['loss']['Sobolev gradient'][-1]:.6e}")


def count_inverted(points: np.ndarray, triangles: np.ndarray) -> int:
    """Triangles whose normal turned against the averaged vertex normals around them (folds)."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    face_normals = np.cross(b - a, c - a)
    smooth_normals = vertex_normals(points, triangles)[triangles].sum(1)
    return int(np.sum(np.einsum("fi,fi->f", face_normals, smooth_normals) < 0))


if __name__ == "__main__":
    main()
