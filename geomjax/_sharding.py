"""Per-shard execution of batch- and point-parallel ops on explicitly sharded inputs.

Under a mesh with ``Explicit`` axes (the default of ``jax.make_mesh``), every array's type
carries its sharding, and JAX's sharding-in-types rules reject some of the gathers, scans and
sorts these ops use on a sharded axis. The Warp paths have a second problem under any mesh: an
FFI call is opaque to XLA's SPMD partitioner, which then gathers the whole input on every device
and runs the kernel there. The ops below are independent per design (leading batch axis) and per
query point, so when their inputs carry explicit shardings on those axes they run the whole
computation inside ``jax.shard_map``: each device sees its own slice of designs or points (plus
the shared inputs, replicated), no collective is needed on the way forward, and the result keeps
the inputs' sharding. Gradients of replicated inputs are summed over devices by ``shard_map``'s
transpose.

Under ``Auto`` axes (``jax.sharding.Mesh`` or ``jax.jit(in_shardings=...)``) the sharding is
unknown at trace time; the ops then run unchanged and XLA's partitioner decides (the JAX paths
stay local, Warp calls see gathered inputs).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import jax
from jax.sharding import NamedSharding, PartitionSpec


def _explicit_entries(x, num_axes: int) -> tuple:
    """Mesh-axis entries of ``x``'s first ``num_axes`` dimensions in its type (``None`` if not sharded)."""
    sharding = getattr(jax.typeof(x), "sharding", None)
    spec = tuple(getattr(sharding, "spec", ()) or ())
    spec = spec + (None,) * (num_axes - len(spec))
    return spec[:num_axes]


def _axis_names(entry) -> tuple[str, ...]:
    if entry is None:
        return ()
    return (entry,) if isinstance(entry, str) else tuple(entry)


def _mesh_of(arrays):
    """The mesh of the first explicitly sharded array (concrete when the array is, else abstract)."""
    for x in arrays:
        if any(_explicit_entries(x, x.ndim)):
            if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer):
                return x.sharding.mesh
            return jax.typeof(x).sharding.mesh
    return None


def map_local_shards(fn: Callable, args: Sequence, shared_axes: Sequence[int], *, out_axes: int, check_vma: bool = True):
    """``fn(*args)``, run once per shard of the sharded leading axes when any are explicit.

    Args:
        fn: the op's computation; every output's first ``out_axes`` dimensions are the leading
            axes shared with the inputs (e.g. ``(B, N)``), and ``fn`` must be independent along
            them (each output slice depends only on the same slice of the inputs).
        args: arrays or ``None``; ``None`` entries are passed through unchanged.
        shared_axes: per argument, how many of the leading axes it shares (``0`` = replicated,
            e.g. a mesh or a lattice box; ``1`` = the design axis; ``2`` = design and point axes).
        out_axes: how many leading axes the outputs share.
        check_vma: ``shard_map``'s replication checking; ``equinox.error_if`` inside ``fn``
            needs it off (its ``cond`` branches differ in varying axes). Off is only safe when
            no differentiated argument is replicated over a split axis, since nothing then
            sums its per-device partial cotangents.

    The sharding of each leading axis is taken from the first argument that shards it (points
    first); other arguments are resharded to match and shared arguments are replicated. Axes
    whose length is not divisible by the number of shards stay unsharded (computed redundantly).
    Without explicit shardings this is exactly ``fn(*args)``.
    """
    present = [(a, k) for a, k in zip(args, shared_axes, strict=True) if a is not None]
    mesh = _mesh_of([a for a, _ in present])
    if mesh is None:
        return fn(*args)
    num_lead = max(k for _, k in present)
    # Every entry is set below: an argument with k == num_lead spans all the leading axes.
    lead_size = [0] * num_lead
    for a, k in present:
        for axis in range(k):
            lead_size[axis] = a.shape[axis]
    used: set[str] = set()
    lead: list = [None] * num_lead
    for axis in range(num_lead):
        for a, k in present:
            names = _axis_names(_explicit_entries(a, k)[axis]) if axis < k else ()
            shards = 1
            for name in names:
                shards *= mesh.shape[name]
            if names and not used.intersection(names) and lead_size[axis] % shards == 0:
                lead[axis] = names[0] if len(names) == 1 else names
                used.update(names)
                break
    if not used:
        return fn(*args)

    def spec(k: int) -> PartitionSpec:
        return PartitionSpec(*lead[:k])

    sharded_args, in_specs, positions = [], [], []
    for i, (a, k) in enumerate(zip(args, shared_axes, strict=True)):
        if a is None:
            continue
        sharded_args.append(jax.sharding.reshard(a, NamedSharding(mesh, spec(k))))
        in_specs.append(spec(k))
        positions.append(i)

    # Inputs replicated over some of the split mesh axes are marked varying over them: a Warp
    # custom_vjp computes per-device partial cotangents for them, and the transpose of this cast
    # is the sum over devices that turns those partials into the full gradient.
    missing = [tuple(sorted(used.difference(*map(_axis_names, lead[:k])))) for a, k in zip(args, shared_axes, strict=True) if a is not None]

    def local(*local_args):
        full = list(args)
        for i, a, axes in zip(positions, local_args, missing, strict=True):
            full[i] = jax.lax.pcast(a, axes, to="varying") if axes and check_vma else a
        return fn(*full)

    return jax.shard_map(local, mesh=mesh, in_specs=tuple(in_specs), out_specs=spec(out_axes), axis_names=frozenset(used), check_vma=check_vma)(*sharded_args)


# ---------------------------------------------------------------------------------------------
# The eager host-side ops (remeshing, sampling): one process's arrays, on one device.


def on_one_device(op_name: str, name: str, x):
    """``x`` on one of this process's devices, for an op that reads it on this host.

    A replicated array (over this process's devices, or over every process's: a multi-host
    ``jax.make_array_from_process_local_data``) is its first local shard; one split over this
    process's devices is gathered onto its first. One split across processes raises
    ``ValueError``: it cannot be fetched whole, these ops run on one host, and gathering it would
    be a collective that every process must join.
    """
    if not isinstance(x, jax.Array) or isinstance(x, jax.core.Tracer) or len(x.sharding.device_set) == 1:
        return x
    if x.is_fully_replicated:
        return x.addressable_shards[0].data
    if not x.is_fully_addressable:
        raise ValueError(
            f"{op_name}: {name} is split across processes, and this op runs on one host: give every process "
            "the whole array (replicated, or a process-local array)"
        )
    return jax.device_put(x, x.addressable_shards[0].device)


def outside_context_mesh(function: Callable) -> Callable:
    """Decorator for the eager host-side ops: runs ``function`` without the mesh that
    ``jax.set_mesh`` put in context. Their jitted steps run on the input's one device, which jit
    rejects under a context mesh over other devices; inside a trace (where ``jax.set_mesh`` is not
    allowed) the op is left to raise its own error."""

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        if jax.sharding.get_abstract_mesh().empty:
            return function(*args, **kwargs)
        try:
            without_mesh = jax.set_mesh(None)
        except ValueError:  # inside jit: not ours to change
            return function(*args, **kwargs)
        with without_mesh:
            return function(*args, **kwargs)

    return wrapper
