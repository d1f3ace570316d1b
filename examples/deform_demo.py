"""Deform a real mesh with each geomjax operator, fit a shape, time both backends, and draw one figure.

Run:  python examples/deform_demo.py [--mesh fertility.off] [--output examples/output/deform_demo.png]

The mesh is ``fertility.off`` from the repository's ``../shared/meshes`` (a genus-4 scan, 4,494
vertices), scaled so its bounding-box diagonal is 1; without that folder the demo uses an
elongated icosphere. The figure ``deform_demo.png`` has eight panels:

- the input mesh, shaded;
- ``morph_points``: four compact-support handles (red dots, arrows: their displacements) pull the
  surface locally;
- ``radial_basis_function_deform_points``: eight thin-plate-spline controls on the bounding box's
  corners (red) bend the whole shape;
- ``free_form_deform_points``: a 4x3x3 Bernstein lattice (its deformed grid drawn) twists it;
- ``displace_points`` with a rough random field along the normals, and the same field smoothed by
  ``sobolev_deform_points`` (the H^1 filter used to make shape gradients smooth);
- a shape optimisation's loss curve: the FFD lattice fitted with ``optimistix.LBFGS`` so the mesh
  takes the thin-plate-bent shape (``jax.grad`` through the deformation);
- the Warp and JAX backends timed per operator: the first call (compile, or load from the caches
  on a later run) and the steady state (best of five calls) separately.

Every deformed surface is coloured by the length of its displacement, on one scale (the colorbar,
in units of the bounding-box diagonal). The script prints the same figures.
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
from _shape_problem import vertex_normals

import geomjax

jax.config.update("jax_enable_x64", True)

SHARED_MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"


def load_mesh(name: str) -> tuple[np.ndarray, np.ndarray, str]:
    """``(points, triangles, description)``: the shared mesh centred with bounding-box diagonal 1."""
    path = SHARED_MESHES / name
    if path.is_file():
        mesh = geomjax.read_mesh(path, dtype=jnp.float64)
        points, triangles = np.asarray(mesh.points), np.asarray(mesh.cells)
        description = f"{name} ({points.shape[0]:,} vertices)"
    else:
        sphere = geomjax.icosphere(4, dtype=jnp.float64)
        points, triangles = np.asarray(sphere.points) * np.array([1.6, 0.8, 0.6]), np.asarray(sphere.cells)
        description = f"an elongated icosphere ({points.shape[0]:,} vertices; {path} not found)"
    lo, hi = points.min(0), points.max(0)
    points = (points - (lo + hi) / 2) / np.linalg.norm(hi - lo)
    return points, triangles, description


def time_first_and_steady(fn) -> tuple[float, float, jax.Array]:
    """Seconds of the first call (compile or cache load included) and the best of five later calls."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    steady = []
    for _ in range(5):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        steady.append(time.perf_counter() - start)
    return first, min(steady), out


def main() -> None:
    geomjax.enable_compilation_cache()  # later runs load the compiled programs instead of compiling them
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default="fertility.off", help="a mesh file in ../shared/meshes")
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "output" / "deform_demo.png")
    args = parser.parse_args()

    points, triangles, description = load_mesh(args.mesh)
    body = jnp.asarray(points)
    normals = vertex_normals(points, triangles)
    lo, hi = points.min(0), points.max(0)
    print(f"mesh: {description}, {triangles.shape[0]:,} triangles, scaled to bounding-box diagonal 1")

    # The four deformations, each with its controls, on both backends.
    handles = jnp.asarray(points[np.argmax(points, 0)[:2].tolist() + np.argmin(points, 0)[:2].tolist()])
    pulls = jnp.asarray(0.1 * normals[np.argmax(points, 0)[:2].tolist() + np.argmin(points, 0)[:2].tolist()])
    radius = 0.2
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T
    bend = np.where(corners[:, :1] > 0, [0.0, 0.0, 0.12], [0.0, 0.0, -0.04]) + 0.05 * np.sign(corners) * [0, 1, 0]
    origin, extent = lo - 0.02, (hi - lo) + 0.04
    lattice_shape = (4, 3, 3)
    nodes = origin + extent * np.stack(np.meshgrid(*[np.linspace(0, 1, n) for n in lattice_shape], indexing="ij"), -1)
    angle = 0.8 * ((nodes[..., 0] - origin[0]) / extent[0] - 0.5)  # a twist about x growing along the body
    centre = (lo + hi) / 2
    y, z = nodes[..., 1] - centre[1], nodes[..., 2] - centre[2]
    twist = np.stack([np.zeros_like(y), np.cos(angle) * y - np.sin(angle) * z - y, np.sin(angle) * y + np.cos(angle) * z - z], -1)
    box = {"origin": tuple(origin), "extent": tuple(extent), "basis": "bernstein"}

    operators = {
        "morph_points": lambda impl: geomjax.morph_points(body, handles, pulls, radius=radius, implementation=impl),
        "radial_basis_function": lambda impl: geomjax.radial_basis_function_deform_points(
            body, jnp.asarray(corners), jnp.asarray(bend), implementation=impl),
        "free_form_deform": lambda impl: geomjax.free_form_deform_points(body, jnp.asarray(twist), **box, implementation=impl),
    }
    rng = np.random.default_rng(0)
    # A smooth swelling along the body plus noise of the same size: the filter keeps the first.
    swell = 0.05 * np.cos(2 * np.pi * points[:, 0] / (hi[0] - lo[0]))
    rough = jnp.asarray((swell + 0.015 * rng.standard_normal(points.shape[0]))[:, None] * normals)
    operators["sobolev_deform_points"] = lambda impl: geomjax.sobolev_deform_points(
        body, jnp.asarray(triangles), rough, length_scale=0.02, implementation=impl)
    timings: dict[str, dict[str, tuple[float, float]]] = {}
    results = {}
    print("Warp and JAX per operator: first call (compile or cache load included) | steady state (best of 5)")
    for name, call in operators.items():
        for impl in ("jax", "warp"):
            first, steady, results[name, impl] = time_first_and_steady(lambda call=call, impl=impl: call(impl))
            timings.setdefault(name, {})[impl] = (first, steady)
        gap = float(jnp.max(jnp.abs(results[name, "warp"] - results[name, "jax"])))
        print(f"  {name:<24} jax {1e3 * timings[name]['jax'][0]:7.1f} | {1e3 * timings[name]['jax'][1]:6.2f} ms   "
              f"warp {1e3 * timings[name]['warp'][0]:7.1f} | {1e3 * timings[name]['warp'][1]:6.2f} ms   "
              f"max difference {gap:.1e}")
    displaced = geomjax.displace_points(body, rough)

    # A shape optimisation: the FFD lattice that makes the mesh take the thin-plate-bent shape.
    target = results["radial_basis_function", "jax"]

    def misfit(lattice, args):
        moved = geomjax.free_form_deform_points(body, lattice, **box)
        return jnp.mean(jnp.sum((moved - target) ** 2, axis=1)), None  # (value, aux), as optimistix takes it

    solver = optx.LBFGS(rtol=1e-10, atol=1e-12)
    lattice = jnp.zeros((*lattice_shape, 3))
    state = solver.init(misfit, lattice, None, {}, jax.ShapeDtypeStruct((), body.dtype), None, frozenset())
    step = eqx.filter_jit(lambda y, state: solver.step(misfit, y, None, {}, state, frozenset())[:2])
    losses = []
    start = time.perf_counter()
    for _ in range(40):
        lattice, state = step(lattice, state)
        losses.append(float(state.f_info.f))  # the loss at the accepted lattice
    print(f"FFD lattice fitted to the bent shape with optimistix.LBFGS: mean squared distance {losses[0]:.2e} -> "
          f"{losses[-1]:.2e} in {len(losses)} steps, {time.perf_counter() - start:.1f} s (first step compiles)")

    surfaces = [
        ("input", points, None),
        ("morph_points\n4 handles (red), radius 0.2", results["morph_points", "jax"], "handles"),
        ("radial_basis_function_deform_points\n8 thin-plate controls (red)", results["radial_basis_function", "jax"], "corners"),
        ("free_form_deform_points\n4x3x3 Bernstein lattice, twisted", results["free_form_deform", "jax"], "lattice"),
        ("displace_points\nswelling plus noise, along the normals", displaced, None),
        ("sobolev_deform_points\nthe same field, smoothed (length 0.02)", results["sobolev_deform_points", "jax"], None),
    ]
    overlays = {"handles": (np.asarray(handles), np.asarray(pulls)), "corners": (corners, bend),
                "lattice": (nodes + twist, None)}
    render(args.output, points, triangles, surfaces, overlays, losses, timings)
    print(f"wrote {args.output}")


def render(path: Path, points, triangles, surfaces, overlays, losses, timings) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    moved_by = [np.linalg.norm(np.asarray(p) - points, axis=1) for _, p, _ in surfaces[1:]]
    scale = Normalize(0.0, max(float(m.max()) for m in moved_by))
    cmap = plt.get_cmap("viridis")
    fig = plt.figure(figsize=(18, 7.4), layout="constrained")
    grid = fig.add_gridspec(2, 4)
    for i, (title, surface, overlay) in enumerate(surfaces):
        ax = fig.add_subplot(grid[i // 4, i % 4], projection="3d")
        surface = np.asarray(surface)
        faces = surface[triangles]
        if i == 0:
            colours = np.tile(np.array([0.75, 0.78, 0.85, 1.0]), (len(triangles), 1))
        else:
            colours = cmap(scale(moved_by[i - 1][triangles].mean(1)))
        # Shade by the face normals so the shape reads in 3-D, and colour by the displacement.
        face_normals = np.cross(faces[:, 1] - faces[:, 0], faces[:, 2] - faces[:, 0])
        face_normals /= np.maximum(np.linalg.norm(face_normals, axis=1, keepdims=True), 1e-30)
        shade = 0.55 + 0.45 * np.clip(face_normals @ np.array([0.4, -0.5, 0.75]) / np.linalg.norm([0.4, -0.5, 0.75]), 0, 1)
        # Markers and lines are drawn over the surface (matplotlib does not sort them against it).
        ax.computed_zorder = False
        ax.add_collection3d(Poly3DCollection(faces, facecolors=colours[:, :3] * shade[:, None], linewidths=0.0, zorder=1))
        if overlay is not None:
            anchors, arrows = overlays[overlay]
            if overlay == "lattice":
                grid_points = anchors
                for axis in range(3):
                    lines = np.moveaxis(grid_points, axis, 0)
                    for line in lines.reshape(lines.shape[0], -1, 3).transpose(1, 0, 2):
                        ax.plot(*line.T, color="crimson", linewidth=0.8, alpha=0.8, zorder=2)
                ax.scatter(*grid_points.reshape(-1, 3).T, color="crimson", s=8, depthshade=False, zorder=3)
            else:
                ax.scatter(*anchors.T, color="red", s=30, depthshade=False, zorder=3)
                ax.quiver(*anchors.T, *np.asarray(arrows).T, color="red", linewidth=1.5, arrow_length_ratio=0.25, zorder=3)
        ax.set_title(title, fontsize=11)
        # Each panel's box holds its surface, controls and lattice nodes, with a thin margin.
        drawn = [surface]
        if overlay is not None:
            anchors, arrows = overlays[overlay]
            drawn += [anchors.reshape(-1, 3)] + ([] if arrows is None else [anchors + np.asarray(arrows)])
        lo, hi = np.min([d.min(0) for d in drawn], 0) - 0.01, np.max([d.max(0) for d in drawn], 0) + 0.01
        ax.set_xlim(lo[0], hi[0]), ax.set_ylim(lo[1], hi[1]), ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(hi - lo, zoom=1.0 if overlay in ("corners", "lattice") else 1.2)  # corners reach out
        ax.view_init(elev=18, azim=-62)
        ax.set_axis_off()
    colorbar = fig.colorbar(plt.cm.ScalarMappable(norm=scale, cmap=cmap), ax=fig.axes, location="left", shrink=0.6, pad=0.01)
    colorbar.set_label("displacement length (bounding-box diagonals)")

    ax = fig.add_subplot(grid[1, 2])
    ax.semilogy(np.arange(1, len(losses) + 1), losses, marker=".", color="tab:blue")
    ax.set_xlabel("L-BFGS step")
    ax.set_ylabel("mean squared distance to the bent shape")
    ax.set_title("shape fit: FFD lattice by optimistix.LBFGS\n(jax.grad through free_form_deform_points)", fontsize=11)
    ax.grid(True, which="both", alpha=0.3)

    ax = fig.add_subplot(grid[1, 3])
    names = list(timings)
    rows = np.arange(len(names))
    bars = [("jax", 0, "first call", "tab:blue", 0.35), ("jax", 1, "steady state", "tab:blue", 1.0),
            ("warp", 0, "first call", "tab:orange", 0.35), ("warp", 1, "steady state", "tab:orange", 1.0)]
    for k, (impl, which, label, colour, alpha) in enumerate(bars):
        values = [1e3 * timings[name][impl][which] for name in names]
        ax.barh(rows + (k - 1.5) * 0.2, values, height=0.2, color=colour, alpha=alpha, label=f"{impl}: {label}")
    ax.set_xscale("log")
    labels = {"morph_points": "morph", "radial_basis_function": "thin-plate RBF", "free_form_deform": "FFD", "sobolev_deform_points": "Sobolev"}
    ax.set_yticks(rows, [labels[name] for name in names])
    ax.invert_yaxis()
    ax.set_xlabel("milliseconds (log scale)")
    ax.set_title("Warp vs JAX on this mesh: first call\n(compile or cache load) and steady state", fontsize=11)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncols=2)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
