"""``ray_mesh_intersect`` for torch tensors, with the reference's reusable ``warp_mesh``.

The reference passes a prepared ``wp.Mesh`` in and out. A custom op can only carry tensors, so the
op (``torch.ops.geomjax.ray_mesh_intersect``) takes the BVH's handle words as an optional integer
tensor, and this wrapper converts between that handle and the :class:`geomjax.MeshBVH` that
torch users pass around exactly as reference users pass a ``wp.Mesh``.
"""

from __future__ import annotations

import inspect

import jax.numpy as jnp
import numpy as np
import torch

import geomjax
from geomjax.query.bvh import MeshBVH

from ._dlpack import to_jax
from ._signature import BridgedOp, publish_wrapper


def _intersect_with_handle(mesh_vertices, mesh_indices, ray_origins, ray_directions, max_distance, warp_mesh_handle, implementation):
    warp_mesh = None
    if warp_mesh_handle is not None:
        # geomjax only searches the BVH through its handle (hits are replayed on mesh_vertices and
        # mesh_indices), so a view with the mesh's arrays and the handle is all it needs. The
        # caller's MeshBVH keeps the Warp mesh alive.
        faces = jnp.reshape(mesh_indices, (-1, 3)).astype(jnp.int32)
        warp_mesh = MeshBVH(mesh_vertices, faces, warp_mesh_handle.astype(jnp.uint32), False, None)
    return geomjax.ray_mesh_intersect(
        mesh_vertices, mesh_indices, ray_origins, ray_directions, max_distance, warp_mesh,
        implementation=implementation,
    )  # fmt: skip


_intersect_with_handle.__doc__ = geomjax.ray_mesh_intersect.__doc__

RAY_MESH_INTERSECT = BridgedOp(
    geomjax.ray_mesh_intersect,
    _intersect_with_handle,
    rename={"warp_mesh": "warp_mesh_handle"},
    annotations={"warp_mesh_handle": "Tensor | None"},
    exclude=("return_warp_mesh",),
    returns="tuple[Tensor, Tensor, Tensor, Tensor, Tensor]",  # the BVH is added by the wrapper
    index_outputs=(3,),  # face ids: int64, as in the reference
)
# The wrapper's defaults are geomjax's (one place for them).
_DEFAULTS = {name: p.default for name, p in inspect.signature(geomjax.ray_mesh_intersect).parameters.items()}


def ray_mesh_intersect(
    mesh_vertices,
    mesh_indices,
    ray_origins,
    ray_directions,
    max_distance=_DEFAULTS["max_distance"],
    warp_mesh=_DEFAULTS["warp_mesh"],
    return_warp_mesh=_DEFAULTS["return_warp_mesh"],
    *,
    implementation=_DEFAULTS["implementation"],
):
    if warp_mesh is not None and not isinstance(warp_mesh, MeshBVH):
        raise TypeError(
            f"ray_mesh_intersect: warp_mesh must be None or a geomjax.MeshBVH (from an earlier call with "
            f"return_warp_mesh=True or geomjax.build_bvh), got {type(warp_mesh).__name__}"
        )
    if not isinstance(return_warp_mesh, (bool, np.bool_)):
        raise TypeError(f"ray_mesh_intersect: return_warp_mesh must be a bool, got {type(return_warp_mesh).__name__}")
    handle = None
    if return_warp_mesh or warp_mesh is not None:
        if not isinstance(mesh_vertices, torch.Tensor) or not isinstance(mesh_indices, torch.Tensor):
            raise TypeError("ray_mesh_intersect: mesh_vertices and mesh_indices must be torch.Tensor")
        if warp_mesh is None:
            warp_mesh = geomjax.build_bvh(to_jax(mesh_vertices.detach()), to_jax(mesh_indices))
        elif warp_mesh.vertices.shape != tuple(mesh_vertices.shape) or 3 * warp_mesh.faces.shape[0] != mesh_indices.numel():
            # The op sees only the handle: a BVH of another mesh would be searched silently.
            raise ValueError(
                f"ray_mesh_intersect: warp_mesh was built for {warp_mesh.vertices.shape[0]} vertices and "
                f"{warp_mesh.faces.shape[0]} faces, got a mesh of shape {tuple(mesh_vertices.shape)} with "
                f"indices of shape {tuple(mesh_indices.shape)}"
            )
        # Two words; int64 because torch's uint32 support is partial.
        handle = torch.from_numpy(np.asarray(warp_mesh.mesh_words).astype(np.int64)).to(mesh_vertices.device)
    result = RAY_MESH_INTERSECT(mesh_vertices, mesh_indices, ray_origins, ray_directions, max_distance, handle, implementation)
    return (*result, warp_mesh) if return_warp_mesh else result


publish_wrapper(
    ray_mesh_intersect, RAY_MESH_INTERSECT, "(which takes the BVH as its handle words, ``warp_mesh_handle``, instead of ``warp_mesh``/``return_warp_mesh``)"
)
