"""Poisson-disk sampling on Warp: hash-grid conflict tests and exact sample elimination.

These are host-side NumPy functions; they live in :mod:`warp_ffi.host` with the other host-side
entry points and are re-exported here under the names geomjax imports.
"""

from .host import eliminate as eliminate
from .host import neighbour_lists as neighbour_lists
from .host import reject_near_accepted as reject_near_accepted
from .host import resolve_conflicts as resolve_conflicts
