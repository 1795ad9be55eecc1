"""Plain NumPy references for every kernel, written for clarity rather than speed.

Tests compare each OpenCL kernel against its twin here.
"""

from . import reconstruct
from .refocus import output_lens_coordinates, refocus_views
from .simulate import random_words, trace_particles, trace_white
from .weights import ApertureGrid, lens_index_map, voxel_weights, weight_matrix

__all__ = [
    "ApertureGrid",
    "lens_index_map",
    "voxel_weights",
    "weight_matrix",
    "output_lens_coordinates",
    "random_words",
    "reconstruct",
    "refocus_views",
    "trace_particles",
    "trace_white",
]
