"""The camera's optics as a model every stage shares (docs/design.md §2).

- :mod:`.imaging`: the imaging relation ``c_k = x_k (1 + f_ml/d)`` between a lens's
  array-plane position and its image centre on the sensor;
- :mod:`.ownership`: which lens a sensor pixel lies behind;
- :mod:`.rawimage`: the raw image's checks against the camera, the pixel mask, the
  robust background;
- :mod:`.raybundle`: the camera's exact rays, a point particle's raw image and its
  derivatives (the image-space particle fit's forward model).
- :mod:`.depthrange`: the depths the camera resolves, its field of view there, and the
  one check of a grid against them (:func:`check_grid`).
- :mod:`.sightline`: the lines of sight, along which the camera places a point worst,
  and the frames and priors that lean with them off the axis.

Device-free NumPy; it imports only the camera model (:mod:`plenocl.camera`, whose
:mod:`~plenocl.camera.lattice` holds the array's layout and fitted lattice).
"""

from .depthrange import check_grid, field_of_view_mm, resolved_depth_range
from .imaging import array_plane_positions, array_plane_scale
from .ownership import lens_owner, pixel_lenses
from .rawimage import check_image, check_pixel_mask, median_background, subtract_background
from .raybundle import RayBundle
from .sightline import line_of_sight, sight_frames, sight_information

__all__ = ["RayBundle",
           "array_plane_positions", "array_plane_scale", "check_grid", "check_image",
           "check_pixel_mask", "field_of_view_mm", "lens_owner",
           "line_of_sight", "median_background", "pixel_lenses", "resolved_depth_range",
           "sight_frames", "sight_information", "subtract_background"]
