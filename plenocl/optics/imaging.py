"""The imaging relation of the microlens images (docs/design.md §2).

A microlens at array-plane position ``x_k`` images the main-lens aperture centred at
``c_k = x_k (1 + f_ml/d)`` on the sensor (``d``: the exit pupil's distance from the array,
``s_i`` for a thin lens; :attr:`plenocl.Camera.lens_image_scale`, the
one place the factor is computed). These helpers go the other way, from image centres
on the sensor to lens positions on the array plane, for every stage that needs it.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera

__all__ = ["array_plane_positions", "array_plane_scale"]


def array_plane_scale(camera: Camera) -> float:
    """Array-plane mm per sensor mm of a microlens image centre, ``1 / (1 + f_ml/d)``."""
    return 1.0 / camera.lens_image_scale


def array_plane_positions(camera: Camera, centres_px) -> np.ndarray:
    """Array-plane ``(x, y)`` mm of the lenses whose image centres are ``centres_px``
    (``(..., 2)`` ``(col, row)`` pixels): ``x_k = c_k / (1 + f_ml/d)``."""
    return camera.px_to_mm(centres_px) * array_plane_scale(camera)
