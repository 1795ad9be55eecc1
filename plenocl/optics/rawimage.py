"""The raw image as the camera delivers it: checks against the camera, the pixel mask,
and the robust background (dark level and noise) every stage removes alike.

Used by the reconstruction's preprocessing, the light field and the image-space
particle fit. Plain NumPy; nothing here touches a device.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera

__all__ = ["check_image", "check_pixel_mask", "median_background", "subtract_background"]


def check_pixel_mask(observed, camera: Camera) -> np.ndarray | None:
    """A pixel mask (``True``: the pixel holds data) as a bool array of the sensor's
    shape, or ``None``; refused when its shape differs or it leaves no pixel."""
    if observed is None:
        return None
    mask = np.asarray(observed)
    expected = (camera.pixels[1], camera.pixels[0])
    if mask.shape != expected:
        raise ValueError(f"pixel_mask shape {mask.shape} does not match the camera's sensor "
                         f"{expected} (rows, columns)")
    mask = mask.astype(bool)
    if not mask.any():
        raise ValueError("pixel_mask leaves no pixel with data (True marks the pixels the "
                         "image holds)")
    return mask


def check_image(image, camera: Camera, dtype=np.float64) -> np.ndarray:
    """A raw image as ``dtype`` (float64 by default), checked against the camera: its
    shape, numeric, real and finite in ``dtype`` (the first bad pixel is named)."""
    img = np.asarray(image)
    expected = (camera.pixels[1], camera.pixels[0])
    if img.shape != expected:
        raise ValueError(f"image shape {img.shape} does not match the camera's sensor "
                         f"{expected} (rows, columns); check the camera file, or cut the "
                         "frame to the camera's region of interest (camera.fit_image, "
                         "--crop)")
    if img.dtype == bool or not np.issubdtype(img.dtype, np.number):
        raise ValueError(f"image must be numeric (uint8, uint16, float), got {img.dtype}")
    if np.iscomplexobj(img):
        raise TypeError("image must hold real numbers, not complex; pass the intensity "
                        "(e.g. np.abs(image) ** 2)")
    img = img.astype(dtype)
    bad = ~np.isfinite(img)
    if bad.any():
        row, col = (int(v) for v in np.argwhere(bad)[0])
        raise ValueError(f"image contains {int(bad.sum())} NaN or Inf pixel(s), the first at "
                         f"row {row}, column {col}; replace bad pixels (e.g. by 0 or the "
                         "median of their neighbours) first")
    return img


def subtract_background(image) -> tuple[np.ndarray, float]:
    """Remove a camera's dark level and estimate its noise, robustly.

    At PIV seeding densities most pixels see no particle, so the median is the
    background and the median absolute deviation the noise. Returns the float32 image
    ``max(I - median, 0)`` and the noise standard deviation (a sensible ``threshold`` for
    :func:`plenocl.reconstruct` is 3 to 5 times it).
    """
    img, sigma = median_background(np.asarray(image, dtype=np.float64))
    return img.astype(np.float32), sigma


def median_background(img: np.ndarray, observed: np.ndarray | None = None
                    ) -> tuple[np.ndarray, float]:
    """``max(I - median, 0)`` in float64 and the noise ``1.4826 MAD``, both over the
    ``observed`` pixels (all by default)."""
    data = img if observed is None else img[observed]
    med = float(np.median(data))
    sigma = 1.4826 * float(np.median(np.abs(data - med)))
    return np.clip(img - med, 0, None), sigma
