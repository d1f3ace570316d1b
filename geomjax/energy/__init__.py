"""Deformation energies: strain, measure, total measure, inversion, bending and volume.

Each is a functional of current and rest coordinates over shared topology, with a pure-JAX
implementation (the specification, any-order derivatives) and Warp kernels (``D <= 3``,
hand-written first-order adjoints).
"""

from .bending import surface_bending_energy as surface_bending_energy
from .inversion import simplex_inversion_energy as simplex_inversion_energy
from .measure import simplex_measure_energy as simplex_measure_energy
from .strain import simplex_strain_energy as simplex_strain_energy
from .total_measure import total_measure_energy as total_measure_energy
from .volume import closed_surface_volume_energy as closed_surface_volume_energy
