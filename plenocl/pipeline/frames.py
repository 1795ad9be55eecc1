"""A camera frame as the chain uses it: one colour plane, the dark frame subtracted and
the flat field divided out, cut to the camera's region of interest. The one reader of
raw and white frames for the command line and the batch."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..io.files import read_image
from ..optics.rawimage import check_exposure, check_image
from ..simulate.sensor import correct_frame, flat_gain


def load_frame(path, camera: Camera, channel: str | None = None,
               dark: np.ndarray | None = None, flat: np.ndarray | None = None,
               white: bool = False, label: str | None = None) -> np.ndarray:
    """Read ``path`` (:func:`plenocl.io.read_image` with ``channel``), correct it with
    ``dark`` and ``flat`` (:func:`plenocl.simulate.sensor.correct_frame`, when given) and cut it
    to ``camera``'s sensor (:meth:`plenocl.Camera.fit_image`).

    A frame with a NaN or Inf pixel, a blank frame, or a saturated one (not for a
    ``white`` image, whose spots may all be), is refused naming the file
    (:func:`plenocl.optics.rawimage.check_image`, :func:`~plenocl.optics.rawimage.check_exposure`);
    ``label`` names it in those messages instead of its file name (several cameras:
    ``"camera 2's frame_004.tif"``, their folders may hold the same names).
    """
    image = read_image(path, channel)
    name = Path(path).name if label is None else label
    raw = camera.fit_image(image, name)  # the shape first
    check_image(raw, camera, raw.dtype, name, copy=False)  # a NaN or Inf pixel: the file's
    check_exposure(raw, name, saturation=not white)
    if dark is None and flat is None:
        return raw
    return camera.fit_image(correct_frame(image, dark, flat), name)


def load_corrections(dark_path, flat_path, cameras: list[Camera], channel: str | None = None
                     ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The dark frame and flat field a run corrects its frames with (``None`` for a path
    not given), read with ``channel`` and checked once, before any frame is, naming the
    file: each the shape of every camera's frames (its sensor, or a whole sensor its
    region is cut from: :meth:`plenocl.Camera.fit_image`), both the same shape, finite,
    and the flat field above the dark frame at every pixel (the gain
    :func:`plenocl.simulate.sensor.correct_frame` divides by)."""
    found = {}
    for kind, path in (("dark frame", dark_path), ("flat field", flat_path)):
        if path is None:
            continue
        frame, name = read_image(path, channel), f"the {kind} {Path(path).name}"
        for camera in cameras:
            check_image(camera.fit_image(frame, name), camera, frame.dtype, name, copy=False)
        found[kind] = (frame, name)
    dark, flat = (found.get(k, (None, ""))[0] for k in ("dark frame", "flat field"))
    if dark is not None and flat is not None and dark.shape != flat.shape:
        raise ValueError(f"{found['dark frame'][1]} is {dark.shape} (rows, columns) but "
                         f"{found['flat field'][1]} is {flat.shape}: use frames of the same "
                         "camera and region")
    if flat is not None:
        flat_gain(flat, dark, found["flat field"][1])
    return dark, flat

