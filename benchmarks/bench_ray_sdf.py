"""Ray casting and signed distance on a 40,962-vertex icosphere against Open3D, embreex and pysdf.

Mesh: ``geomjax.icosphere(6)`` (81,920 triangles), float32. Cases (``--quick``: 100,000 queries):

* rays: 1,000,000 rays from inside the sphere (origins ~ N(0, 0.3^2), random directions), first
  hit, BVH build included. geomjax ``ray_mesh_intersect`` (jitted, Warp BVH built inside the
  call) against Open3D ``RaycastingScene`` (``add_triangles`` + ``cast_rays``; target: no more
  than 1.5x its time) and embreex (scene + ``run``), reported.
* sdf shell: 1,000,000 points in the shell 0.9 < |x| < 1.1: ``signed_distance_field`` (BVH build
  included) against Open3D ``compute_signed_distance`` (target: no slower).
* sdf cube: 1,000,000 points uniform in [-1.5, 1.5]^3, against pysdf ``SDF(vertices, faces)(points)``
  (target: no slower) and Open3D.

Prints time ratios (baseline time / ours: above 1 means faster) and the agreement with each
baseline (hit masks, largest distance difference, sign agreement). Baselines that are not
installed are skipped.

Usage: ``python benchmarks/bench_ray_sdf.py [--quick] [--repeat N]``
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

from geomjax import icosphere, ray_mesh_intersect, signed_distance_field  # noqa: E402

RAY_TARGET = 1 / 1.5  # ours may take up to 1.5x Open3D's time
SDF_TARGET = 1.0


def _open3d_scene(vertices, faces):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces.astype(np.uint32)))
    return scene, o3d


def open3d_rays(vertices, faces, origins, unit_directions):
    scene, o3d = _open3d_scene(vertices, faces)
    out = scene.cast_rays(o3d.core.Tensor(np.concatenate([origins, unit_directions], axis=1)))
    return out["t_hit"].numpy(), out["primitive_ids"].numpy()


def embreex_rays(vertices, faces, origins, unit_directions):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, vertices[faces])
    return scene.run(origins, unit_directions, query="DISTANCE")


def open3d_sdf(vertices, faces, points):
    scene, o3d = _open3d_scene(vertices, faces)
    return scene.compute_signed_distance(o3d.core.Tensor(points)).numpy()


def pysdf_sdf(vertices, faces, points):
    from pysdf import SDF

    # pysdf is positive inside; negate to compare with the usual convention.
    return -SDF(vertices, faces)(points)


def _available(module: str) -> bool:
    try:
        __import__(module)
    except Exception:  # noqa: BLE001 - a broken install (missing system library) counts as absent
        return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="100,000 queries instead of 1,000,000")
    parser.add_argument("--repeat", type=int, default=3, help="best of this many runs")
    args = parser.parse_args()
    num = 100_000 if args.quick else 1_000_000

    sphere = icosphere(6, dtype=jnp.float32)
    vertices, faces = np.asarray(sphere.points), np.asarray(sphere.cells, np.int32)
    vertices_j, faces_j = jnp.asarray(vertices), jnp.asarray(faces)
    rng = np.random.default_rng(0)
    rows = []

    # Rays.
    origins = (0.3 * rng.normal(size=(num, 3))).astype(np.float32)
    directions = rng.normal(size=(num, 3)).astype(np.float32)
    unit = (directions / np.linalg.norm(directions, axis=1, keepdims=True)).astype(np.float32)
    cast = jax.jit(lambda v, f, o, d: ray_mesh_intersect(v, f, o, d)[:4])
    origins_j, directions_j = jnp.asarray(origins), jnp.asarray(directions)
    hit, distance, _, face_ids = (np.asarray(x) for x in cast(vertices_j, faces_j, origins_j, directions_j))
    ours = best_time(lambda: cast(vertices_j, faces_j, origins_j, directions_j), repeat=args.repeat)
    print(f"rays: geomjax {ours:.3f} s, {hit.mean():.3f} hit", flush=True)
    baselines = {"open3d": (open3d_rays, "open3d"), "embreex": (embreex_rays, "embreex")}
    for name, (fn, module) in baselines.items():
        if not _available(module):
            print(f"rays: {name} not installed, skipped")
            continue
        result = fn(vertices, faces, origins, unit)
        t_hit = np.asarray(result[0] if isinstance(result, tuple) else result, np.float64)
        t_hit = np.where(t_hit > 1e30, np.inf, t_hit)
        base = best_time(lambda fn=fn: fn(vertices, faces, origins, unit), repeat=args.repeat)
        both = np.isfinite(t_hit) & hit
        row = {
            "case": f"rays N={num} F={faces.shape[0]} f32, build included [{name}]",
            "ours_s": ours,
            "baseline_s": base,
            "ratio": base / ours,
            "hit_agreement": float(np.mean(np.isfinite(t_hit) == hit)),
            "max_abs_distance_diff": float(np.max(np.abs(t_hit[both] - distance[both]))) if both.any() else 0.0,
        }
        if name == "open3d":
            row.update(target=RAY_TARGET, met=base / ours >= RAY_TARGET)
        rows.append(row)
        print(f"rays: {name} {base:.3f} s, ratio {base / ours:.2f}x", flush=True)

    # Signed distance.
    direction = rng.normal(size=(num, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    shell = (direction * rng.uniform(0.9, 1.1, (num, 1))).astype(np.float32)
    cube = rng.uniform(-1.5, 1.5, (num, 3)).astype(np.float32)
    sdf = jax.jit(lambda v, f, p: signed_distance_field(v, f, p)[0])
    targets = {"shell": "open3d", "cube": "pysdf"}
    for case, points in (("shell", shell), ("cube", cube)):
        points_j = jnp.asarray(points)
        values = np.asarray(sdf(vertices_j, faces_j, points_j), np.float64)
        ours = best_time(lambda points_j=points_j: sdf(vertices_j, faces_j, points_j), repeat=args.repeat)
        print(f"sdf {case}: geomjax {ours:.3f} s", flush=True)
        for name, fn in (("open3d", open3d_sdf), ("pysdf", pysdf_sdf)):
            if not _available(name):
                print(f"sdf {case}: {name} not installed, skipped")
                continue
            reference = np.asarray(fn(vertices, faces, points), np.float64)
            base = best_time(lambda fn=fn: fn(vertices, faces, points), repeat=max(1, args.repeat - 1))
            row = {
                "case": f"sdf {case} N={num} F={faces.shape[0]} f32, build included [{name}]",
                "ours_s": ours,
                "baseline_s": base,
                "ratio": base / ours,
                "max_abs_diff": float(np.max(np.abs(np.abs(reference) - np.abs(values)))),
                "sign_agreement": float(np.mean(np.sign(reference) == np.sign(values))),
            }
            if targets[case] == name:
                row.update(target=SDF_TARGET, met=base / ours >= SDF_TARGET)
            rows.append(row)
            print(f"sdf {case}: {name} {base:.3f} s, ratio {base / ours:.2f}x", flush=True)

    report("ray_sdf", rows)


if __name__ == "__main__":
    main()
