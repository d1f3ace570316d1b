"""A design batch split across several JAX processes: the README's multi-host recipe, run locally.

What it shows: the code of the README's "Multiple hosts" block (the function
``design_batch_on_every_process`` below, between the ``README`` markers; a test checks the two
are the same text) run by several processes at once, as it would run on several machines. Each
process joins ``jax.distributed`` (here with its coordinator on 127.0.0.1 and Gloo collectives
on CPU), builds only the rows of the design batch that its own devices hold (read from the
sharding's ``addressable_devices_indices_map`` by ``jax.make_array_from_callback``, so no device
order is assumed) into global arrays, and passes them to a jitted value-and-gradient as arguments (a jitted function may not close over arrays that span
processes). Every process then checks its rows of the gradient and the summed loss against the
same batch computed whole on one of its own devices.

Run:
    python examples/multiprocess_design_batch.py            # 2 processes x 2 host devices, seconds
    python examples/multiprocess_design_batch.py --processes 4 --devices 1

Without ``--worker`` the script is the launcher: it picks a free port on 127.0.0.1, starts the
processes (``--worker`` mode), waits for them (bounded by ``--timeout``), kills any that are left
and prints each process's result line, then ``max relative difference ...`` over all of them. On a
real cluster, run only the body of ``design_batch_on_every_process`` on every host after
``jax.distributed.initialize()`` (which reads the cluster's environment).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys


def design_batch_on_every_process():
    """The README's multi-host code; returns what the check below needs."""
    # README multi-host (start)
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    import geomjax

    num_designs = 16
    mesh = jax.make_mesh((jax.device_count(),), ("designs",))  # every process's devices
    split = NamedSharding(mesh, P("designs"))
    sphere = geomjax.icosphere(3)
    rest, cells = np.asarray(sphere.points), np.asarray(sphere.cells)  # the same on every process
    controls = rest[::40]

    def design(i):  # any per-design data: a file per design, a seed per design, ...
        return 0.05 * np.random.default_rng(i).normal(size=controls.shape)

    def rows(make_row):  # a global array of which each process builds only its devices' rows
        shape = (num_designs, *make_row(0).shape)
        # The callback gets each of this process's devices' index from the sharding
        # (split.addressable_devices_indices_map(shape)): no device order is assumed.
        return jax.make_array_from_callback(shape, split, lambda index: np.stack([make_row(i) for i in range(num_designs)[index[0]]]))

    displacements = rows(design)
    points = rows(lambda i: rest)
    batch_controls = rows(lambda i: controls)

    @jax.jit  # split arrays are arguments: a jitted function may not close over them
    def loss(displacements, points, batch_controls):
        moved = geomjax.morph_points(points, batch_controls, displacements, radius=0.6)
        energies = geomjax.closed_surface_volume_energy(moved, points, cells, reduction="none")
        return jnp.sum(energies)

    with jax.set_mesh(mesh):  # the mesh of the split arrays, for what the ops create inside
        value, grad = jax.value_and_grad(loss)(displacements, points, batch_controls)
    # value is replicated on every process; each process holds its own designs' gradient rows
    mine = {shard.index[0].indices(num_designs)[:2]: np.asarray(shard.data) for shard in grad.addressable_shards}
    # README multi-host (end)
    whole = [np.stack([make_row(i) for i in range(num_designs)]) for make_row in (design, lambda i: rest, lambda i: controls)]
    return value, mine, loss, whole


def worker(process_id: int, num_processes: int, port: int, devices: int) -> None:
    os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    import jax

    jax.config.update("jax_enable_x64", True)  # so that the comparison below is to rounding
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=num_processes, process_id=process_id,
                               initialization_timeout=60)
    import numpy as np

    import geomjax

    geomjax.enable_compilation_cache()  # processes after the first load the compiled programs
    value, mine, loss, whole = design_batch_on_every_process()
    # The same batch whole, on one of this process's devices.
    device = jax.local_devices()[0]
    expected_value, expected_grad = jax.value_and_grad(loss)(*(jax.device_put(a, device) for a in whole))
    expected_grad = np.asarray(expected_grad)
    value = float(value.addressable_shards[0].data)
    gap = abs(value - float(expected_value)) / abs(float(expected_value))
    for (lo, hi), rows in mine.items():
        gap = max(gap, float(np.max(np.abs(rows - expected_grad[lo:hi])) / np.max(np.abs(expected_grad))))
    print(json.dumps({"process": process_id, "devices": jax.device_count(), "rows": sorted(mine), "loss": value,
                      "max_relative_difference": gap}), flush=True)
    jax.distributed.shutdown()


def launch(num_processes: int, devices: int, timeout: float) -> int:
    with socket.socket() as s:  # a free port on the loopback interface only
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    command = [sys.executable, __file__, "--worker"]
    processes = [subprocess.Popen([*command, str(i), str(num_processes), str(port), str(devices)], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for i in range(num_processes)]
    outputs = []
    try:
        for process in processes:
            outputs.append(process.communicate(timeout=timeout))
    finally:
        for process in processes:  # never leave a process behind, whatever happened
            if process.poll() is None:
                process.kill()
                process.wait()
    gaps = []
    for process, (out, err) in zip(processes, outputs):
        if process.returncode != 0:
            print(f"a process exited with {process.returncode}:\n{err[-3000:]}", file=sys.stderr)
            return 1
        result = json.loads(out.strip().splitlines()[-1])
        print(f"process {result['process']}: designs {result['rows']} of the batch, {result['devices']} devices in all, "
              f"summed loss {result['loss']:.6e}")
        gaps.append(result["max_relative_difference"])
    print(f"max relative difference to one process: {max(gaps):.1e}")
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--devices", type=int, default=2, help="host devices per process")
    parser.add_argument("--timeout", type=float, default=180.0, help="seconds before the processes are killed")
    parser.add_argument("--worker", nargs=4, type=int, metavar=("PROCESS_ID", "NUM_PROCESSES", "PORT", "DEVICES"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(*args.worker)
        return
    sys.exit(launch(args.processes, args.devices, args.timeout))


if __name__ == "__main__":
    main()
