"""The light field stage: a raw image's light field ``LF(x, y, u, v)``, its perspective
views and computational refocusing (docs/design.md §2 and §4, paper §II).

- :mod:`.views`: :class:`LightField` (the views resampled onto one plaid aperture grid,
  refocusing on the device, ``kernels/lightfield.cl``), the lens lattice in the array's
  frame (:func:`lens_lattice`, :func:`lens_positions_mm`) and each pixel's light-field
  coordinates (:func:`pixel_coordinates`).
"""

from .views import (
    LightField,
    PixelCoordinates,
    lens_index_to_mm,
    lens_lattice,
    lens_positions_mm,
    output_lens_coordinates,
    pixel_coordinates,
    plaid_uv,
    resample_light_field,
)

__all__ = ["LightField", "PixelCoordinates", "lens_index_to_mm", "lens_lattice",
           "lens_positions_mm", "output_lens_coordinates", "pixel_coordinates", "plaid_uv",
           "resample_light_field"]
