"""One process of a multi-process run (``tests/test_multiprocess.py`` starts them).

Usage: ``python -m tests.multiprocess_worker CASES PROCESS_ID NUM_PROCESSES PORT DEVICES_PER_PROCESS``
(``CASES``: comma-separated, each ``sdf``, ``rays``, ``shrinkwrap``, ``ffd``, ``rbf``, ``batch-ops`` or
``sobolev`` on both backends in turn, or with ``-jax`` / ``-warp`` on one; ``per-process-meshes``,
``global-meshes``).
The process joins ``jax.distributed`` with its coordinator on 127.0.0.1 (Gloo collectives on
CPU), builds its part of each global array with ``jax.make_array_from_process_local_data`` (the
rows that the sharding's ``addressable_devices_indices_map`` gives it), runs the case jitted on
the global arrays and, on its own devices alone, the same computation unsharded as the
reference, and prints one JSON line per case: the case, its rows and the largest relative
difference (also per backend).
"""

from __future__ import annotations

import json
import os
import sys


def _local_rows(sharding, shape) -> tuple[int, int]:
    """The contiguous rows ``[lo, hi)`` of a row-split array that this process holds."""
    bounds = [(index[0].start or 0, shape[0] if index[0].stop is None else index[0].stop) for index in sharding.addressable_devices_indices_map(shape).values()]
    return min(b[0] for b in bounds), max(b[1] for b in bounds)


def _relative_difference(actual, expected) -> float:
    import numpy as np

    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    return float(np.max(np.abs(actual - expected)) / max(float(np.max(np.abs(expected))), np.finfo(np.float64).tiny))


def _local_part(array, lo: int, hi: int):
    """This process's rows of a row-split global array, gathered from its addressable shards."""
    import numpy as np

    shards = sorted(array.addressable_shards, key=lambda s: s.index[0].start or 0)
    rows = np.concatenate([np.asarray(s.data) for s in shards])
    return rows[: hi - lo]


def per_process_mesh_summary(gj, index: int, as_array=lambda a: a) -> list[float]:
    """Remeshing and Poisson sampling of mesh ``index`` (a sphere stretched by ``index``; its
    vertices and triangles passed through ``as_array``): sizes and coordinate sums, to compare a
    multi-process run with the same calls in one process."""
    import numpy as np

    sphere = gj.icosphere(3)
    points = as_array(np.asarray(sphere.points) * np.array([1.0 + 0.5 * index, 1.0, 1.0]))
    cells = as_array(np.asarray(sphere.cells))
    vertices, triangles = gj.remeshing(points, cells, 200)
    samples = gj.mesh_poisson_disk_sample(points, cells, min_distance=0.2)
    return [float(vertices.shape[0]), float(triangles.shape[0]), float(samples.shape[0]), float(np.abs(np.asarray(vertices, np.float64)).sum()),
            float(np.abs(np.asarray(samples, np.float64)).sum())]  # fmt: skip


def _energy_calls(gj, implementation: str, rng, num_designs: int) -> list:
    """The six energies per design and cell: ``(fn, batch arrays)`` pairs."""
    import numpy as np

    box, sphere = gj.tetrahedralized_box(2, 2, 2), gj.icosphere(1)
    calls = []
    for rest, topology, energies in (
        (box.points, box.cells, (gj.simplex_strain_energy, gj.simplex_measure_energy, gj.total_measure_energy, gj.simplex_inversion_energy)),
        (sphere.points, sphere.hinges, (gj.surface_bending_energy,)),
        (sphere.points, sphere.cells, (gj.closed_surface_volume_energy,)),
    ):
        rest = np.asarray(rest)
        designs = rest + rng.normal(0, 0.03, (num_designs, *rest.shape))
        references = np.broadcast_to(rest, designs.shape).copy()
        for energy in energies:

            def per_cell(x, r, energy=energy, topology=topology):
                return energy(x, r, topology, reduction="none", implementation=implementation)

            calls.append((per_cell, (designs, references)))
    return calls


def _batch_op_calls(gj, implementation: str, rng, num_designs: int) -> list:
    """Morphing, displacement, farthest-point sampling and (vmapped) voxel fractions of a batch
    of sphere designs: ``(fn, batch arrays)`` pairs (the ops each backend has)."""
    import jax
    import numpy as np

    sphere = gj.icosphere(1)
    rest = np.asarray(sphere.points)
    designs = rest + rng.normal(0, 0.03, (num_designs, *rest.shape))
    controls = np.broadcast_to(rest[::4], (num_designs, *rest[::4].shape)).copy()
    moves = rng.normal(0, 0.05, controls.shape)

    def morph(x, c, d):
        return gj.morph_points(x, c, d, radius=0.6, implementation=implementation)

    calls = [(morph, (designs, controls, moves))]
    if implementation == "jax":  # the ops without a Warp kernel on CPU, and JAX's voxels
        # (vmap over a split axis does not reach Warp's FFI calls: their sequential batching
        # is a scan, which JAX refuses over a split axis)
        def voxels(x):
            return gj.mesh_to_voxel_fraction(x, sphere.cells, [-1.2] * 3, 0.3, (8, 8, 8), n_samples=8, implementation="jax")

        calls += [
            (lambda x, d: gj.displace_points(x, d), (designs, rng.normal(0, 0.01, designs.shape))),
            (lambda x: gj.farthest_point_sampling(x, 12), (designs,)),
            (jax.vmap(voxels), (designs,)),
        ]
    return calls


def main() -> None:
    case, process_id, num_processes, port, devices = sys.argv[1], *map(int, sys.argv[2:6])
    os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=num_processes, process_id=process_id, initialization_timeout=60)
    # Starting and joining the processes costs more than most cases: CASE may list several
    # (comma-separated), run one after the other, and a case without a backend suffix runs on
    # both backends in turn, each from the same inputs. One JSON line per listed case.
    for listed in case.split(","):
        backend_cases = [listed] if listed.endswith(("-jax", "-warp")) or listed.endswith("meshes") else [f"{listed}-jax", f"{listed}-warp"]
        results = [_run_case(one, process_id) for one in backend_cases]
        result = dict(results[-1], case=listed, max_relative_difference=max(r["max_relative_difference"] for r in results))
        result["per_backend"] = {r["case"]: r["max_relative_difference"] for r in results}
        print(json.dumps(result), flush=True)
    jax.distributed.shutdown()


def _run_case(case: str, process_id: int) -> dict:
    """One case on one backend: this process's rows and its largest relative difference."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    import geomjax as gj

    mesh = jax.make_mesh((jax.device_count(),), ("rows",))
    split = NamedSharding(mesh, P("rows"))
    rng = np.random.default_rng(0)
    points = rng.uniform(-1.2, 1.2, (16 * jax.device_count(), 3))  # the same in every process
    lo, hi = _local_rows(split, points.shape)
    global_points = jax.make_array_from_process_local_data(split, points[lo:hi], points.shape)
    local_device = jax.local_devices()[0]
    unsharded_points = jax.device_put(points, local_device)
    result = {"case": case, "process": process_id, "rows": [lo, hi], "devices": jax.device_count()}

    if case.startswith("sdf"):
        implementation = case.split("-")[1]
        sphere = gj.icosphere(2)

        def distances(q):
            return gj.signed_distance_field(sphere.points, sphere.cells, q, implementation=implementation)[0]

        reference = np.asarray(distances(unsharded_points))[lo:hi]
        # Jitted and eager: an eager op must not read rows held by other processes.
        split_values = [_local_part(call(global_points), lo, hi) for call in (jax.jit(distances), distances)]
        result["max_relative_difference"] = max(_relative_difference(v, reference) for v in split_values)
    elif case.startswith(("rays", "shrinkwrap")):
        # Split query points (ray origins, points to project), the mesh replicated; jitted and
        # eager.
        implementation = case.split("-")[1]
        sphere = gj.icosphere(2)
        if case.startswith("rays"):
            directions = -points / np.linalg.norm(points, axis=1, keepdims=True)  # towards the sphere
            global_directions = jax.make_array_from_process_local_data(split, directions[lo:hi], directions.shape)
            unsharded_directions = jax.device_put(directions, local_device)

            def query(q, d):
                hit = gj.ray_mesh_intersect(sphere.points, sphere.cells, q, d, implementation=implementation)
                return hit[1]  # the distances (inf where missed)

            arguments, unsharded = (global_points, global_directions), (unsharded_points, unsharded_directions)
        else:

            def query(q):
                return gj.shrinkwrap_points(q, sphere.points, sphere.cells, implementation=implementation)

            arguments, unsharded = (global_points,), (unsharded_points,)
        reference = np.asarray(query(*unsharded))[lo:hi]
        split_values = [_local_part(call(*arguments), lo, hi) for call in (jax.jit(query), query)]
        finite = np.isfinite(reference)
        assert all(np.array_equal(np.isfinite(v), finite) for v in split_values), "misses differ"
        result["max_relative_difference"] = max(_relative_difference(v[finite], reference[finite]) for v in split_values)
    elif case.startswith(("ffd", "rbf")):
        implementation = case.split("-")[1]
        if case.startswith("ffd"):
            parameters = rng.normal(0, 0.1, (3, 3, 3, 3))  # the lattice
            box = {"origin": [-1.3] * 3, "extent": [2.6] * 3, "basis": "bernstein", "implementation": implementation}

            def deform(params, q):
                return gj.free_form_deform_points(q, params, **box)
        else:
            controls = rng.uniform(-1, 1, (12, 3))  # NumPy: a constant of every process's program
            parameters = rng.normal(0, 0.1, (12, 3))  # the control displacements

            def deform(params, q):
                return gj.radial_basis_function_deform_points(q, jnp.asarray(controls), params, implementation=implementation)

        def loss(params, q):  # the value and the gradient of replicated parameters: cross-process sums
            return jnp.sum(jnp.sin(deform(params, q)))

        # Replicated: every process gives the whole array (a device_put of a local array onto the
        # global mesh would be a cross-host transfer).
        global_parameters = jax.make_array_from_process_local_data(NamedSharding(mesh, P()), parameters, parameters.shape)
        ref_value, ref_gradient = jax.value_and_grad(loss)(jax.device_put(parameters, local_device), unsharded_points)
        differences = []
        for call in (jax.jit(jax.value_and_grad(loss)), jax.value_and_grad(loss)):  # jitted and eager
            # Eager value_and_grad on process-spanning arrays needs the mesh (JAX's own seed
            # cotangent is made on it), as the README says.
            with jax.set_mesh(mesh):
                value, gradient = call(global_parameters, global_points)
            # Replicated results: every process holds the whole value and gradient.
            value, gradient = value.addressable_shards[0].data, gradient.addressable_shards[0].data
            differences += [_relative_difference(value, ref_value), _relative_difference(np.asarray(gradient), ref_gradient)]
        result["max_relative_difference"] = max(differences)
    elif case.startswith("batch-ops"):
        # A split batch of designs: each process holds some designs (and their reference shapes
        # and controls); every op jitted and eagerly (an eager op must not read other processes'
        # rows), against the same call on this process's devices alone.
        implementation = case.split("-")[-1]
        num_designs = 2 * jax.device_count()
        lo, hi = _local_rows(split, (num_designs,))
        calls = _energy_calls(gj, implementation, rng, num_designs) + _batch_op_calls(gj, implementation, rng, num_designs)
        differences = []
        for fn, batch in calls:
            global_batch = [jax.make_array_from_process_local_data(split, a[lo:hi], a.shape) for a in batch]
            reference = np.asarray(fn(*(jax.device_put(a, local_device) for a in batch)))[lo:hi]
            for call in (jax.jit(fn), fn):
                with jax.set_mesh(mesh):
                    value = _local_part(call(*global_batch), lo, hi)
                if np.issubdtype(reference.dtype, np.integer):  # sample indices: exactly equal
                    differences.append(0.0 if np.array_equal(value, reference) else float("inf"))
                else:
                    differences.append(_relative_difference(value, reference))
        result["rows"] = [lo, hi]
        result["max_relative_difference"] = max(differences)
    elif case.startswith("sobolev"):
        # A split batch of designs and displacements, the surface mesh replicated; eager (host
        # checks see only this process's rows) and jitted.
        implementation = case.split("-")[1]
        sphere = gj.icosphere(1)
        num_designs = 2 * jax.device_count()
        lo, hi = _local_rows(split, (num_designs,))
        rest = np.asarray(sphere.points)
        designs = rest + rng.normal(0, 0.01, (num_designs, *rest.shape))
        displacements = rng.normal(0, 0.02, designs.shape)
        global_designs, global_displacements = (jax.make_array_from_process_local_data(split, a[lo:hi], a.shape) for a in (designs, displacements))

        def smooth(x, d):
            return gj.sobolev_deform_points(x, sphere.cells, d, length_scale=0.3, implementation=implementation)

        reference = np.asarray(smooth(jax.device_put(designs, local_device), jax.device_put(displacements, local_device)))[lo:hi]
        eager = _local_part(smooth(global_designs, global_displacements), lo, hi)
        jitted = _local_part(jax.jit(smooth)(global_designs, global_displacements), lo, hi)
        result["rows"] = [lo, hi]
        result["max_relative_difference"] = max(_relative_difference(eager, reference), _relative_difference(jitted, reference))
    elif case == "per-process-meshes":
        # Each process remeshes and samples its own mesh (local arrays, not global ones): the
        # data-dependent ops must use this process's devices only.
        result["rows"] = [process_id, process_id + 1]
        result["summary"] = per_process_mesh_summary(gj, process_id)
        result["max_relative_difference"] = 0.0  # compared with one process by the test
    elif case == "global-meshes":
        # One mesh as arrays that span every process (replicated: each process holds all of it),
        # remeshed and sampled with and without the mesh in context; a split vertex array is a
        # ValueError (these ops run on one host).
        replicated = NamedSharding(mesh, P())

        def as_global(a):
            return jax.make_array_from_process_local_data(replicated, a, a.shape)

        result["rows"] = [process_id, process_id + 1]
        result["summaries"] = [per_process_mesh_summary(gj, 0, as_global)]
        with jax.set_mesh(mesh):
            result["summaries"].append(per_process_mesh_summary(gj, 0, as_global))
        # Voxel fractions of the replicated mesh (an op that takes no batch), jitted and eager.
        sphere = gj.icosphere(2)
        global_vertices = as_global(np.asarray(sphere.points))
        differences = []
        for implementation in ("jax", "warp"):

            def voxels(v, implementation=implementation):
                return gj.mesh_to_voxel_fraction(v, sphere.cells, [-1.2] * 3, 0.3, (8, 8, 8), n_samples=8, implementation=implementation)

            reference = np.asarray(voxels(jax.device_put(np.asarray(sphere.points), local_device)))
            for call in (jax.jit(voxels), voxels):
                with jax.set_mesh(mesh):
                    value = call(global_vertices)
                differences.append(_relative_difference(value.addressable_shards[0].data, reference))
        try:
            gj.remeshing(global_points, np.array([[0, 1, 2]]), 3)
            result["split_error"] = ""
        except ValueError as error:
            result["split_error"] = str(error)
        result["max_relative_difference"] = max(differences)  # the summaries: compared by the test
    else:
        raise SystemExit(f"unknown case {case!r}")
    return result


if __name__ == "__main__":
    main()
