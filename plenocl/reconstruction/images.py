"""The raw image a reconstruction starts from: checks, scaling, background."""

from __future__ import annotations

import numpy as np

#: Largest image value accepted: the volume (in image units) must stay finite in float32.
FLOAT32_LIMIT = 1e30


def prepare_image(image, camera) -> tuple[np.ndarray, float]:
    """Validate a raw image against the camera; return it as float32 scaled to max 1,
    and the scale. Integer and float16 input is accepted."""
    img = np.asarray(image)
    expected = (camera.pixels[1], camera.pixels[0])
    if img.shape != expected:
        raise ValueError(f"image shape {img.shape} does not match the camera's sensor "
                         f"{expected} (rows, columns); check the camera file")
    if img.dtype == bool or not np.issubdtype(img.dtype, np.number):
        raise ValueError(f"image must be numeric (uint8, uint16, float), got {img.dtype}")
    if np.iscomplexobj(img):
        raise TypeError("image must hold real numbers, not complex; pass the intensity "
                        "(e.g. np.abs(image) ** 2)")
    img = img.astype(np.float64)
    if not np.all(np.isfinite(img)):
        raise ValueError("image contains NaN or Inf; replace bad pixels (e.g. by 0) first")
    if img.min() < 0:
        raise ValueError("image has negative pixels; subtract the background with clipping, "
                         "e.g. np.clip(image - background, 0, None)")
    scale = float(img.max())
    if scale > FLOAT32_LIMIT:
        raise ValueError(f"image maximum {scale:.3g} is beyond the float32 range plenocl "
                         f"reconstructs in (up to {FLOAT32_LIMIT:.0e}); rescale the image")
    if scale == 0:
        return img.astype(np.float32), 0.0
    return (img / scale).astype(np.float32), scale


def subtract_background(image) -> tuple[np.ndarray, float]:
    """Remove a camera's dark level and estimate its noise, robustly.

    At PIV seeding densities most pixels see no particle, so the median is the
    background and the median absolute deviation the noise. Returns the float32 image
    ``max(I - median, 0)`` and the noise standard deviation (a sensible ``threshold`` for
    :func:`reconstruct` is 3 to 5 times it).
    """
    img = np.asarray(image, dtype=np.float64)
    med = float(np.median(img))
    sigma = 1.4826 * float(np.median(np.abs(img - med)))
    return np.clip(img - med, 0, None).astype(np.float32), sigma
