"""The unfocused plenoptic camera (docs/design.md §2): its optics, its microlens array's
layout and lattice, its TOML files.

- :mod:`.model`: :class:`Camera`, the camera file, the presets;
- :mod:`.lattice`: the array's layout (:class:`LensLayout`: rectangular, hexagonal, and a
  hexagonal array's axial view, the one object every stage asks about the layout, held
  as ``Camera.layout``) and the lattice fitted to calibrated centres
  (:class:`RectangularLattice`, :func:`lattice_fit`);
- :mod:`.pose`: where the camera stands in the world (:class:`Pose`, ``Camera.pose``).

Plain NumPy; it imports nothing of plenocl's stages, so every stage builds on it.
"""

from .lattice import (
    AXIAL,
    DEFAULT_SHEAR_TOL,
    LAYOUTS,
    AxialView,
    HexagonalLayout,
    LensLattice,
    LensLayout,
    RectangularLattice,
    RectangularLayout,
    lattice_fit,
    lens_layout,
)
from .model import CAMERA_KEYS, OVERLAP_WARN, PRESETS, UNDERFILL_WARN, Camera, load_camera
from .pose import Pose, pose_rotation, require_world_frame

__all__ = ["AXIAL", "CAMERA_KEYS", "DEFAULT_SHEAR_TOL", "LAYOUTS", "OVERLAP_WARN", "PRESETS",
           "UNDERFILL_WARN", "AxialView", "Camera", "HexagonalLayout", "LensLattice",
           "LensLayout", "Pose", "RectangularLattice", "RectangularLayout", "lattice_fit",
           "lens_layout", "load_camera", "pose_rotation", "require_world_frame"]
