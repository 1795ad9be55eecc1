"""Projection between a voxel grid and a plenoptic raw image (docs/design.md §5).

- :mod:`.weighting`: the paper's weighting model as plain NumPy tables (aperture
  sampling, lens index map, per-depth coefficients, lens tables, geometry checks);
- :mod:`.model`: :class:`WeightingModel`, those tables and checks for one camera and
  grid, built without a device;
- :mod:`.plan`: how the work is split so every buffer fits the device;
- :mod:`.lenses`: which microlenses an image lights (dark-microlens skipping);
- :mod:`.projector`: :class:`Projector`, the matrix-free OpenCL forward and back
  projection.
"""

from .lenses import LensSet
from .model import WeightingModel
from .plan import Plan, make_plan
from .projector import BACK_MODES, METHODS, Projector
from .weighting import ApertureGrid, LensIndexMap, lens_index_map

__all__ = ["BACK_MODES", "METHODS", "ApertureGrid", "LensIndexMap", "LensSet", "Plan",
           "Projector", "WeightingModel", "lens_index_map", "make_plan"]
