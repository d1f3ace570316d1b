"""The clustering remesher's host-side kernels: the faces' corners, normals and areas, nearest
centroids on a Warp hash grid, the nearest face of each point among its cluster's faces, the
plane quadric terms summed into the vertices, the clusters' seeds, the relaxation's bending
measure, circumcentre sums and fold check, the flip rules and fold heights, corner angles, and
the clusters as a shortest-path forest of the edge graph.

Host-side NumPy functions; they live in :mod:`warp_ffi.host` with the other host-side entry
points and are re-exported here under the names geomjax imports.
"""

from .host import CentroidSearch as CentroidSearch
from .host import EdgeGraph as EdgeGraph
from .host import PatchSearch as PatchSearch
from .host import cluster_seeds as cluster_seeds
from .host import corner_terms as corner_terms
from .host import face_geometry as face_geometry
from .host import flip_rules as flip_rules
from .host import fold_heights as fold_heights
from .host import grow_forest as grow_forest
from .host import largest_sagittas as largest_sagittas
from .host import nearest_centroids as nearest_centroids
from .host import overturned_vertices as overturned_vertices
from .host import patch_closest_faces as patch_closest_faces
from .host import relaxation_sums as relaxation_sums
from .host import vertex_plane_terms as vertex_plane_terms
