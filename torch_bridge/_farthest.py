"""``farthest_point_sampling`` for torch tensors, with the reference's ``random_start``.

The reference draws the random start of each cloud from torch's global generator. geomjax takes a
``jax.random`` key instead, so this wrapper draws the starts with ``torch.randint`` (seeded by
``torch.manual_seed`` like the reference's, and traced by ``torch.compile``) and passes them to the
op (``torch.ops.geomjax.farthest_point_sampling``) as its ``start_index`` tensor.
"""

from __future__ import annotations

import inspect

import numpy as np
import torch

import geomjax

from ._signature import BridgedOp, publish_wrapper

FARTHEST_POINT_SAMPLING = BridgedOp(
    geomjax.farthest_point_sampling,
    exclude=("random_start",),  # drawn here, passed on as start_index
    annotations={"start_index": "Tensor | int | None"},
    index_outputs=(0,),  # int64, as in the reference
)
# The wrapper's defaults are geomjax's (one place for them).
_DEFAULTS = {name: p.default for name, p in inspect.signature(geomjax.farthest_point_sampling).parameters.items()}


def farthest_point_sampling(
    points, num_samples, random_start=_DEFAULTS["random_start"], implementation=_DEFAULTS["implementation"], *, start_index=_DEFAULTS["start_index"]
):
    if not isinstance(random_start, (bool, np.bool_)):
        raise TypeError(f"farthest_point_sampling: random_start must be a bool, got {type(random_start).__name__}")
    if random_start:
        if start_index is not None:
            raise ValueError("farthest_point_sampling: give random_start or start_index, not both")
        if isinstance(points, torch.Tensor) and points.ndim in (2, 3) and points.shape[-2] > 0:
            # One start per cloud, uniform over its points (other inputs: the op raises).
            start_index = torch.randint(points.shape[-2], points.shape[:-2], device=points.device)
    return FARTHEST_POINT_SAMPLING(points, num_samples, implementation, start_index)


publish_wrapper(
    farthest_point_sampling,
    FARTHEST_POINT_SAMPLING,
    "(which takes the start as ``start_index``; ``random_start=True`` draws it per cloud with torch's global generator)",
)
