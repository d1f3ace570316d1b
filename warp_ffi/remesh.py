"""Nearest-centroid assignment for the clustering remesher, on a Warp hash grid.

A host-side NumPy function; it lives in :mod:`warp_ffi.host` with the other host-side entry
points and is re-exported here under the name geomjax imports.
"""

from .host import nearest_centroids as nearest_centroids
