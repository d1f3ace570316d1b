"""Register a template sphere onto a scanned surface with an FFD lattice (geomjax.optimize.register_surface).

What it shows: a template (an icosphere, centred in the target and scaled to 70% of its size) is
moved by a Bernstein free-form lattice until its vertices lie on the target surface: one call of
``geomjax.optimize.register_surface``, which solves the least-squares problem (point-to-plane
distances to the nearest target faces, plus a small membrane-strain regulariser) with
optimistix's dogleg trust-region method, re-searching the nearest faces at every step. The
target is a real mesh from the repository's ``../shared/meshes`` (``bumpy-cube.obj``; the smoke
size uses ``decimated-knight.off``), or, where those meshes are not checked out, the analytic
peanut of ``_shape_problem.py``. Distances before and after come from
``geomjax.signed_distance_field``.

Outputs (PNG, in ``examples/output/`` or ``--output-dir``): ``register_template.png``: the
target, the template before, and the registered template over the target.

Run:
    python examples/register_template.py           # about half a minute on a 2-core CPU
    python examples/register_template.py --smoke   # seconds; used by tests/test_examples.py
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _render import overlay_with_target
from _shape_problem import peanut

import geomjax
from geomjax.optimize import register_surface

SHARED_MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"
SIZES = {
    "smoke": {"mesh": "decimated-knight.off", "subdivisions": 2, "lattice": 3},
    "default": {"mesh": "bumpy-cube.obj", "subdivisions": 4, "lattice": 6},
}


def load_target(name: str) -> tuple[np.ndarray, np.ndarray, str]:
    """``(points, triangles, description)``: a shared mesh scaled into [-1, 1]^3, or the peanut."""
    path = SHARED_MESHES / name
    if path.is_file():
        import meshio

        mesh = meshio.read(path)
        points = np.asarray(mesh.points, np.float64)
        triangles = np.asarray(mesh.cells_dict["triangle"], np.int32)
        description = f"{name} ({len(points)} vertices)"
    else:
        sphere = geomjax.icosphere(4)
        points, triangles = peanut(np.asarray(sphere.points)).astype(np.float64), np.asarray(sphere.cells)
        description = f"the analytic peanut ({len(points)} vertices; {path} not found)"
    low, high = points.min(axis=0), points.max(axis=0)
    return (points - (low + high) / 2) / (np.max(high - low) / 2), triangles, description


def main() -> None:
    geomjax.enable_compilation_cache()  # later runs load the compiled programs instead of compiling them
    jax.config.update("jax_enable_x64", True)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="tiny size for the tests (a few seconds)")
    parser.add_argument("--strain-weight", type=float, default=1e-6, help="membrane strain regulariser (0 turns it off)")
    parser.add_argument("--output-dir", type=Path, default=Path(__file__).parent / "output")
    args = parser.parse_args()
    config = SIZES["smoke" if args.smoke else "default"]

    target_points, target_triangles, description = load_target(config["mesh"])
    sphere = geomjax.icosphere(config["subdivisions"])
    template = jnp.asarray(sphere.points) * 0.7
    resolution = (config["lattice"],) * 3
    box = {"origin": [-1.2] * 3, "extent": [2.4] * 3}
    print(f"target: {description}; template: {sphere.n_points} vertices; lattice {resolution}")

    target, triangles = jnp.asarray(target_points), jnp.asarray(target_triangles)

    def distances(points) -> np.ndarray:
        return np.abs(np.asarray(geomjax.signed_distance_field(target, triangles, points)[0]))

    start = time.perf_counter()
    lattice = register_surface(template, sphere.cells, target, triangles, resolution, strain_weight=args.strain_weight, **box)
    registered = jax.block_until_ready(geomjax.free_form_deform_points(template, lattice, **box))
    seconds = time.perf_counter() - start
    before, after = distances(template), distances(registered)
    print(f"registration: {seconds:.1f} s (including compilation)")
    print(f"distance to target: mean {before.mean():.4g} -> {after.mean():.4g}, max {before.max():.4g} -> {after.max():.4g}")

    overlay_with_target(
        args.output_dir / "register_template.png",
        [("template before", np.asarray(template)), (f"registered ({resolution[0]}^3 lattice)", np.asarray(registered))],
        np.asarray(sphere.cells),
        target_points,
        target_triangles,
    )


if __name__ == "__main__":
    main()
