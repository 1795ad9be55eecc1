"""The white image checked and the microlens-image pitch it is read at (docs/design.md §3)."""

from __future__ import annotations

import warnings

import numpy as np

from ..camera import Camera
from ..optics.rawimage import check_image

#: Negative pixels below this fraction of the spot peak warn (over-subtracted dark frame).
NEGATIVE_WARN = 0.1


def validate_image(image, camera: Camera) -> np.ndarray:
    """The white image as float32 (:func:`plenocl.optics.rawimage.check_image`), or a
    ValueError naming the problem and the fix."""
    img = check_image(image, camera, np.float32, name="the white image")
    if img.max() <= img.min():
        raise ValueError(f"the white image is blank (every pixel is {img.min():.4g}): take it "
                         "with the main lens stopped down, imaging a uniform bright target")
    _warn_if_very_negative(img)
    return img


def _warn_if_very_negative(img: np.ndarray) -> None:
    """Negative pixels are normal after a dark frame is subtracted (read noise around 0):
    the background is estimated locally, so they are used as they are. Only values below
    NEGATIVE_WARN of the spot peak suggest an over-subtracted dark frame, and warn."""
    low = float(img.min())
    if low >= 0:
        return
    peak = float(np.percentile(img, 99.9)) - float(np.median(img))
    if peak > 0 and -low > NEGATIVE_WARN * peak:
        warnings.warn(f"the white image has pixels down to {low:.4g}, {-low / peak:.0%} of the "
                      f"spot peak ({int((img < 0).sum())} negative pixels): was the dark frame "
                      "over-subtracted? Calibration goes on (the background is estimated "
                      "locally)", stacklevel=4)


def image_pitch_px(camera: Camera) -> float:
    return camera.microlens_image_pitch_mm / camera.pixel_pitch_mm


def odd_size(n: float) -> int:
    n = max(3, int(round(n)))
    return n if n % 2 else n + 1
