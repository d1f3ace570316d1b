"""Shrinkwrap and voxel fractions on a 40,962-vertex icosphere against Open3D's RaycastingScene.

Target: ``geomjax.primitives.icosphere(6)`` (81,920 triangles, unit radius). Times, in one
process and on the same data (``--quick``: icosphere(5), 20,000 points, a 32^3 grid):

* shrinkwrap of 100,000 points scattered in the shell 0.8 < |x| < 1.2:
  ``shrinkwrap_points`` (jitted, compile excluded) in float32 and float64 with a BVH built in
  every call, and in float32 with a prebuilt ``build_bvh`` handle; against Open3D's
  ``RaycastingScene.compute_closest_points`` (float32), scene construction included (Open3D
  builds its BVH on the first query). Target: ratio (Open3D time / ours) >= 1. Also prints the
  largest difference between the two answers' distances to the surface.
* voxel fractions on a 64^3 grid over [-1.1, 1.1]^3: ``mesh_to_voxel_fraction`` (default 64
  stratified samples per surface voxel) against Open3D's ``compute_occupancy`` at the 2x2x2
  voxel sub-centres (the mean of 8 occupancies), scene construction included. Accuracy: the
  error of ``sum(f) h^3`` against the exact mesh volume, and the per-voxel error against a
  high-sample reference (Open3D occupancy at the 8x8x8 sub-centres of every voxel either method
  sees as partly filled). Target: at least as accurate as Open3D in no more time.

Without Open3D (the ``bench`` extra), geomjax alone is timed and the voxel volume error is still
reported (the exact volume comes from the mesh); the comparison columns stay empty.

Usage: ``python benchmarks/bench_shrinkwrap_voxel.py [--quick] [--repeat N]``
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _harness import best_time, report  # noqa: E402

jax.config.update("jax_enable_x64", True)

from geomjax import build_bvh, icosphere, mesh_to_voxel_fraction, shrinkwrap_points  # noqa: E402

REFERENCE_SUBDIVISION = 8  # high-sample reference: 8^3 sub-centre occupancies per voxel


def _scene(o3d, vertices: np.ndarray, faces: np.ndarray):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    return scene


def _sub_centres(num: int, h: float, origin: float, voxels: np.ndarray, per_axis: int) -> np.ndarray:
    """Sub-centres ``(len(voxels) * per_axis**3, 3)`` of the given flat voxel indices (z-major)."""
    i, j, k = voxels % num, (voxels // num) % num, voxels // (num * num)
    corner = np.stack([i, j, k], -1)[:, None, :] * h + origin
    offsets = (np.arange(per_axis) + 0.5) / per_axis * h
    sub = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), -1).reshape(1, -1, 3)
    return (corner + sub).reshape(-1, 3).astype(np.float32)


def _occupancy_fractions(o3d, vertices, faces, num, h, origin, voxels, per_axis):
    scene = _scene(o3d, vertices, faces)
    points = _sub_centres(num, h, origin, voxels, per_axis)
    return scene.compute_occupancy(o3d.core.Tensor(points)).numpy().reshape(len(voxels), -1).mean(axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="icosphere(5), 20,000 points, 32^3 grid")
    parser.add_argument("--repeat", type=int, default=3, help="best of this many runs")
    args = parser.parse_args()
    subdivisions, num_points, num = (5, 20_000, 32) if args.quick else (6, 100_000, 64)

    try:
        import open3d as o3d
    except ImportError:
        o3d = None
        print("open3d is not installed: skipping the Open3D baseline (pip install '.[bench]')", flush=True)

    mesh = icosphere(subdivisions)
    vertices, faces = np.asarray(mesh.points), np.asarray(mesh.cells)
    rng = np.random.default_rng(0)
    points = rng.normal(size=(num_points, 3))
    points *= rng.uniform(0.8, 1.2, (num_points, 1)) / np.linalg.norm(points, axis=1, keepdims=True)
    rows = []

    # Shrinkwrap.
    def open3d_closest():
        return _scene(o3d, vertices, faces).compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))["points"].numpy()

    reference = None if o3d is None else open3d_closest()
    open3d_s = None if o3d is None else best_time(open3d_closest, repeat=args.repeat)
    faces_j = jnp.asarray(faces, jnp.int32)
    cases = []
    for dtype in (jnp.float32, jnp.float64):
        v, p = jnp.asarray(vertices, dtype), jnp.asarray(points, dtype)
        run = jax.jit(lambda x, t: shrinkwrap_points(x, t, faces_j))
        cases.append((f"BVH built per call, {jnp.dtype(dtype).name}", lambda run=run, p=p, v=v: run(p, v)))
    v32, p32 = jnp.asarray(vertices, jnp.float32), jnp.asarray(points, jnp.float32)
    bvh = build_bvh(v32, faces_j)
    prebuilt = jax.jit(lambda x, t, b: shrinkwrap_points(x, t, faces_j, bvh=b))
    cases.append(("prebuilt BVH, float32", lambda: prebuilt(p32, v32, bvh)))
    for name, fn in cases:
        moved = np.asarray(fn())
        ours_s = best_time(fn, repeat=args.repeat)
        row = {"case": f"shrinkwrap N={num_points} F={len(faces)} [{name}]", "ours_s": ours_s}
        if reference is not None:
            ratio = open3d_s / ours_s
            # Distances, not points: equally near faces (medial near-ties) may give different points.
            difference = float(np.abs(np.linalg.norm(moved - points, axis=1) - np.linalg.norm(reference - points, axis=1)).max())
            row.update(open3d_s=open3d_s, ratio=ratio, target=1.0, met=ratio >= 1.0, max_distance_diff_vs_open3d=difference)
            print(f"shrinkwrap {name}: {ours_s:.3f} s, Open3D {open3d_s:.3f} s, ratio {ratio:.2f}x, max distance difference {difference:.1e}", flush=True)
        else:
            row["target"] = 1.0
            print(f"shrinkwrap {name}: {ours_s:.3f} s", flush=True)
        rows.append(row)

    # Voxel fractions.
    h, origin = 2.2 / num, -1.1
    everything = np.arange(num**3)
    exact_volume = float(np.einsum("ij,ij->i", vertices[faces[:, 0]], np.cross(vertices[faces[:, 1]], vertices[faces[:, 2]])).sum() / 6)
    v32 = jnp.asarray(vertices, jnp.float32)

    def open3d_fractions():
        return _occupancy_fractions(o3d, vertices, faces, num, h, origin, everything, 2)

    def ours_fractions():
        return mesh_to_voxel_fraction(v32, faces_j, [origin] * 3, h, (num, num, num))

    def volume_error(fractions):
        return abs(float(fractions.sum()) * h**3 - exact_volume) / exact_volume

    ours = np.asarray(ours_fractions()).reshape(-1)
    ours_s = best_time(ours_fractions, repeat=args.repeat)
    case = f"voxel fractions {num}^3 F={len(faces)} (64 samples vs Open3D 2x2x2 occupancy)"
    if o3d is None:
        rows.append({"case": case, "ours_s": ours_s, "target": 1.0, "volume_rel_error_ours": volume_error(ours)})
        print(f"voxels: {ours_s:.3f} s; volume error {volume_error(ours):.1e}", flush=True)
        report("shrinkwrap_voxel", rows)
        return
    theirs = open3d_fractions()
    open3d_s = best_time(open3d_fractions, repeat=args.repeat)
    partial = np.nonzero(((ours > 0) & (ours < 1)) | ((theirs > 0) & (theirs < 1)))[0]
    truth = _occupancy_fractions(o3d, vertices, faces, num, h, origin, partial, REFERENCE_SUBDIVISION)
    errors = {}
    for name, fractions in (("ours", ours), ("open3d", theirs)):
        per_voxel = fractions[partial] - truth
        errors[name] = (volume_error(fractions), float(np.sqrt(np.mean(per_voxel**2))), float(np.abs(per_voxel).max()))
    ratio = open3d_s / ours_s
    met = ratio >= 1.0 and errors["ours"][0] <= errors["open3d"][0] and errors["ours"][1] <= errors["open3d"][1]
    rows.append(
        {
            "case": case,
            "ours_s": ours_s,
            "open3d_s": open3d_s,
            "ratio": ratio,
            "target": 1.0,
            "met": met,
            "volume_rel_error_ours": errors["ours"][0],
            "volume_rel_error_open3d": errors["open3d"][0],
            "voxel_rms_error_ours": errors["ours"][1],
            "voxel_rms_error_open3d": errors["open3d"][1],
            "voxel_max_error_ours": errors["ours"][2],
            "voxel_max_error_open3d": errors["open3d"][2],
        }
    )
    print(
        f"voxels: {ours_s:.3f} s, Open3D {open3d_s:.3f} s, ratio {ratio:.2f}x; volume error ours {errors['ours'][0]:.1e} "
        f"Open3D {errors['open3d'][0]:.1e}; per-voxel RMS ours {errors['ours'][1]:.3f} Open3D {errors['open3d'][1]:.3f} "
        f"(max {errors['ours'][2]:.3f} / {errors['open3d'][2]:.3f}, {len(partial)} partial voxels)",
        flush=True,
    )
    report("shrinkwrap_voxel", rows)


if __name__ == "__main__":
    main()
