"""A camera frame as the chain uses it: one colour plane, the dark frame subtracted and
the flat field divided out, cut to the camera's region of interest. The one reader of
raw and white frames for the command line and the batch."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..io.files import read_image
from ..optics.rawimage import check_exposure
from ..simulate.sensor import correct_frame


def load_frame(path, camera: Camera, channel: str | None = None,
               dark: np.ndarray | None = None, flat: np.ndarray | None = None,
               white: bool = False) -> np.ndarray:
    """Read ``path`` (:func:`plenocl.io.read_image` with ``channel``), correct it with
    ``dark`` and ``flat`` (:func:`plenocl.simulate.sensor.correct_frame`, when given) and cut it
    to ``camera``'s sensor (:meth:`plenocl.Camera.fit_image`).

    A blank frame, or a saturated one (not for a ``white`` image, whose spots may all
    be), is refused naming the file (:func:`plenocl.optics.rawimage.check_exposure`).
    """
    image = read_image(path, channel)
    raw = camera.fit_image(image, Path(path).name)  # the shape first
    check_exposure(raw, Path(path).name, saturation=not white)
    if dark is None and flat is None:
        return raw
    return camera.fit_image(correct_frame(image, dark, flat), Path(path).name)
