"""The simulator: raw and white images of the camera, ray traced (docs/design.md §2).

- :mod:`.raytrace`: :class:`Simulator`, :func:`simulate_image`, :func:`simulate_white_image`
  (the OpenCL ray tracer, ``kernels/simulate.cl``), and the lenses' manufacturing
  errors (:func:`lens_displacements_mm`, :func:`centre_shift_px`);
- :mod:`.sensor`: the sensor model the simulator applies (:class:`SensorModel`: photon and
  read noise, dark frame, flat field, bit depth) and its inverse for recorded frames
  (:func:`correct_frame`).
"""

from .raytrace import (
    Simulator,
    centre_shift_px,
    lens_displacements_mm,
    seeded_beyond_view,
    simulate_image,
    simulate_white_image,
)
from .sensor import SensorModel, correct_frame

__all__ = ["SensorModel", "Simulator", "centre_shift_px", "correct_frame",
           "lens_displacements_mm", "seeded_beyond_view", "simulate_image",
           "simulate_white_image"]
