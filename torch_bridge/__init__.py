"""torch_bridge: geomjax's ops for PyTorch, with the reference API's names and signatures.

``from torch_bridge import morph_points`` replaces ``from physicsnemo.nn.functional import
morph_points``: same parameters and defaults, same values, same exception types, gradients of any
order the JAX path supports, ``torch.compile(fullgraph=True)`` without graph breaks (and, with
``dynamic=True``, one graph for every value of a real option), and
``torch.func`` transforms (``grad``, ``vjp``, ``jvp``, ``jacrev``, ``jacfwd``, ``hessian``, ``vmap``)
through ``jax.vjp``, ``jax.jvp`` and ``jax.vmap``. Tensors cross to JAX and back with zero-copy
DLPack; float64 tensors run under a local x64 context, so no JAX configuration is needed.
``implementation="torch"`` means geomjax's portable ``"jax"`` path.

Every function is generated from the op table in :mod:`torch_bridge._ops`; each is also available as
the custom op ``torch.ops.geomjax.<name>``. CUDA tensors stay on their device (JAX orders its work
after PyTorch's current stream and back); set ``XLA_PYTHON_CLIENT_PREALLOCATE=false`` before
importing so JAX does not reserve most of the GPU memory PyTorch also needs. CPU tensors allocated
by PyTorch are shared with JAX without a copy (unaligned memory, e.g. from ``torch.from_numpy``,
is copied once per call).

Example:
    >>> import torch
    >>> from torch_bridge import displace_points
    >>> points = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], requires_grad=True)
    >>> displacement = torch.tensor([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]], requires_grad=True)
    >>> moved = displace_points(points, displacement, point_weights=torch.tensor([0.0, 0.5, 1.0]))
    >>> moved
    tensor([[0.0000, 0.0000],
            [1.0000, 0.5000],
            [2.0000, 1.0000]], grad_fn=<...>)
    >>> moved.square().sum().backward()
    >>> displacement.grad  # 2 * moved * w
    tensor([[0.0000, 0.0000],
            [1.0000, 0.5000],
            [4.0000, 2.0000]])
"""

from ._farthest import farthest_point_sampling
from ._ops import MESH_OPS, OPS
from ._ray import ray_mesh_intersect
from ._signature import make_public_function

__all__ = [op.name for op in (*OPS, *MESH_OPS)] + ["ray_mesh_intersect", "farthest_point_sampling"]
globals().update({op.name: make_public_function(op) for op in (*OPS, *MESH_OPS)})

del make_public_function
