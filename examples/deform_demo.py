"""Deform one surface mesh with each geomjax deformation operator and render the results.

Run:  python examples/deform_demo.py [--subdivisions 5] [--output examples/output/deform_demo.png]

What it shows:
- displace_points: a dense bump field along the vertex normals;
- morph_points: a few compact-support handles pull the surface locally;
- radial_basis_function_deform_points: a global thin-plate-spline bend from eight controls;
- free_form_deform_points: a Bernstein lattice twists the body;
- one gradient step: jax.grad of a target-matching loss with respect to the FFD lattice;
- the Warp and JAX backends agree on the same call.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _shape_problem import vertex_normals

import geomjax

jax.config.update("jax_enable_x64", True)


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: ``(V, 3)`` float64 vertices and ``(F, 3)`` int32 outward-wound triangles."""
    t = (1.0 + 5.0**0.5) / 2.0
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
             (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(v, float) / np.linalg.norm(v) for v in verts]
    for _ in range(subdivisions):
        midpoint_of: dict[tuple[int, int], int] = {}

        def midpoint(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in midpoint_of:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                midpoint_of[key] = len(verts) - 1
            return midpoint_of[key]

        new_faces = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new_faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new_faces
    return np.array(verts), np.array(faces, np.int32)


def enclosed_volume(points: jax.Array, faces: np.ndarray) -> jax.Array:
    a, b, c = (points[faces[:, k]] for k in range(3))
    return jnp.sum(jnp.einsum("fi,fi->f", a, jnp.cross(b, c))) / 6.0


def timed(label: str, fn):
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    print(f"  {label:<34s} {1e3 * (time.perf_counter() - start):8.1f} ms")
    return out


def main() -> None:
    geomjax.enable_compilation_cache()  # later runs load the compiled programs instead of compiling them
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subdivisions", type=int, default=4, help="icosphere refinement (4: 2,562 vertices)")
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "output" / "deform_demo.png")
    args = parser.parse_args()

    sphere, faces = icosphere(args.subdivisions)
    body = jnp.asarray(sphere * np.array([1.6, 0.8, 0.6]))  # an elongated, streamlined body
    normals = jnp.asarray(vertex_normals(np.asarray(body), faces))
    lo, hi = np.asarray(body).min(0), np.asarray(body).max(0)
    print(f"mesh: {body.shape[0]} vertices, {faces.shape[0]} triangles, volume {float(enclosed_volume(body, faces)):.4f}")
    print("deformations (first call includes compilation):")

    x, y, z = body[:, 0], body[:, 1], body[:, 2]
    bumps = 0.05 * jnp.sin(6 * x) * jnp.cos(5 * y) * jnp.cos(4 * z)
    displaced = timed("displace_points (normal bumps)", lambda: geomjax.displace_points(body, bumps[:, None] * normals))

    handles = jnp.array([[1.6, 0.0, 0.0], [0.0, 0.8, 0.0], [0.0, -0.8, 0.0], [-1.6, 0.0, 0.0]])
    pulls = jnp.array([[0.5, 0.0, 0.2], [0.0, 0.35, 0.0], [0.0, -0.35, 0.0], [-0.3, 0.0, -0.2]])
    morphed = timed(
        "morph_points (4 handles, r=0.7)",
        lambda: geomjax.morph_points(body, handles, pulls, radius=0.7),
    )

    corners = jnp.asarray(np.array(np.meshgrid([-2.0, 2.0], [-1.0, 1.0], [-1.0, 1.0], indexing="ij")).reshape(3, -1).T)
    tip_up = jnp.where(corners[:, :1] > 0, jnp.array([0.0, 0.0, 0.5]), jnp.array([0.0, 0.0, -0.2]))
    bent = timed(
        "radial_basis_function_deform (TPS)",
        lambda: geomjax.radial_basis_function_deform_points(body, jnp.concatenate([corners, jnp.zeros((1, 3))]),
                                                            jnp.concatenate([tip_up, jnp.array([[0.0, 0.0, 0.15]])])),
    )

    origin, extent = lo - 0.05, (hi - lo) + 0.1
    lattice_shape = (5, 4, 4)
    nodes = np.stack(np.meshgrid(*[np.linspace(0, 1, n) for n in lattice_shape], indexing="ij"), -1)
    nodes = origin + extent * nodes
    angle = 0.9 * (nodes[..., 0] - origin[0]) / extent[0]  # twist grows along the body axis
    twisted = np.stack([nodes[..., 0],
                        np.cos(angle) * nodes[..., 1] - np.sin(angle) * nodes[..., 2],
                        np.sin(angle) * nodes[..., 1] + np.cos(angle) * nodes[..., 2]], -1)
    lattice = jnp.asarray(twisted - nodes)
    ffd = lambda lat, impl=None: geomjax.free_form_deform_points(  # noqa: E731
        body, lat, origin=tuple(origin), extent=tuple(extent), basis="bernstein", implementation=impl)
    twisted_body = timed("free_form_deform (5x4x4 Bernstein)", lambda: ffd(lattice))

    for name, moved in [("displace", displaced), ("morph", morphed), ("rbf", bent), ("ffd", twisted_body)]:
        moved_by = jnp.linalg.norm(moved - body, axis=1)
        print(f"  {name:>8}: max move {float(moved_by.max()):.3f}, mean move {float(moved_by.mean()):.3f}, "
              f"volume {float(enclosed_volume(moved, faces)):.4f}")

    # Differentiability: fit the lattice so that the body matches the twisted target, starting from zero.
    def loss(lat):
        return jnp.mean(jnp.sum((ffd(lat) - twisted_body) ** 2, axis=1))

    value_and_grad = jax.jit(jax.value_and_grad(loss))
    lat = jnp.zeros_like(lattice)
    start_loss, _ = value_and_grad(lat)
    for _ in range(50):
        value, grad = value_and_grad(lat)
        lat = lat - 2.0 * grad
    print(f"gradient descent on the FFD lattice (50 steps): loss {float(start_loss):.2e} -> {float(value):.2e}")

    for impl in ("jax", "warp"):
        timed(f"free_form_deform implementation={impl}", lambda: ffd(lattice, impl))
    gap = float(jnp.max(jnp.abs(ffd(lattice, "warp") - ffd(lattice, "jax"))))
    print(f"Warp vs JAX max difference: {gap:.2e}")

    render(args.output, faces, [("input", body), ("displace", displaced), ("morph", morphed),
                                ("thin-plate RBF", bent), ("FFD twist", twisted_body)], body)
    print(f"wrote {args.output}")


def render(path: Path, faces: np.ndarray, panels, reference) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(4 * len(panels), 4.2))
    for i, (title, pts) in enumerate(panels):
        pts = np.asarray(pts)
        ax = fig.add_subplot(1, len(panels), i + 1, projection="3d")
        moved = np.linalg.norm(pts - np.asarray(reference), axis=1)[faces].mean(1)
        surf = ax.plot_trisurf(pts[:, 0], pts[:, 1], pts[:, 2], triangles=faces, linewidth=0.0, antialiased=False)
        surf.set_array(moved)
        surf.set_cmap("viridis")
        surf.set_clim(0.0, max(moved.max(), 1e-9))
        ax.set_title(title)
        ax.set_box_aspect((3.2, 1.8, 1.6))
        ax.set_xlim(-1.8, 1.8), ax.set_ylim(-1.0, 1.0), ax.set_zlim(-0.9, 0.9)
        ax.view_init(elev=22, azim=-58)
        ax.set_axis_off()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
