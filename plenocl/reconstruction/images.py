"""The raw image a reconstruction starts from: checks, scaling, background."""

from __future__ import annotations

import numpy as np

#: Largest image value accepted: the volume (in image units) must stay finite in float32.
FLOAT32_LIMIT = float(np.float32(1e30))  # 1e30 as float32 (1.0000000150e30): such images pass


#: With the median background removed, pixels count as light above this many noise
#: standard deviations (the default ``threshold``).
NOISE_SIGMAS = 4.0
#: How the background is handled: subtract the median (and threshold at the noise), or
#: take the image as it is.
BACKGROUNDS = ("median", None)


def check_pixel_mask(observed, camera) -> np.ndarray | None:
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


def check_image(image, camera) -> np.ndarray:
    """A raw image as float64, checked against the camera: its shape, numeric, real and
    finite (the first bad pixel is named)."""
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
    img = img.astype(np.float64)
    bad = ~np.isfinite(img)
    if bad.any():
        row, col = (int(v) for v in np.argwhere(bad)[0])
        raise ValueError(f"image contains {int(bad.sum())} NaN or Inf pixel(s), the first at "
                         f"row {row}, column {col}; replace bad pixels (e.g. by 0 or the "
                         "median of their neighbours) first")
    return img


def preprocess(image, camera, background: str | None = "median",
               threshold: float | None = None, observed: np.ndarray | None = None
               ) -> tuple[np.ndarray, float, float]:
    """The one preprocessing of the API and the command line.

    Parameters
    ----------
    image, camera
        The raw image and its camera (:func:`check_image`).
    background
        ``"median"``: subtract the median (the camera's dark level at PIV seeding, where
        most pixels see no particle), clipping at 0; ``None``: use the image as it is
        (it must then be non-negative).
    threshold
        Pixels at or below it (image units, after the background) are dark. ``None``:
        :data:`NOISE_SIGMAS` times the noise (median absolute deviation) with the median
        background, else 0.
    observed
        Bool per pixel, ``False`` where the image holds no data: the background, noise
        and scale come from the other pixels, and these are set to 0 (the solver gives
        them no weight; :class:`plenocl.reconstruction.Solver`).

    Returns
    -------
    image, scale, threshold
        The float32 image scaled to a maximum of 1, the scale (0 for an image without
        light) and the threshold in the scaled units.
    """
    img = check_image(image, camera)
    if observed is not None:
        img = np.where(observed, img, 0.0)  # no data: no light, no statistics
    if background == "median":
        img, noise = _without_median(img, observed)
        thr = NOISE_SIGMAS * noise if threshold is None else float(threshold)
    elif background is None:
        if img.min() < 0:
            raise ValueError("image has negative pixels; use background='median' (the "
                             "default) or clip, e.g. np.clip(image - background, 0, None)")
        thr = 0.0 if threshold is None else float(threshold)
    else:
        raise ValueError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    if observed is not None:  # 0 - a negative median would give them light
        img = np.where(observed, img, 0.0)
    scale = float(img.max())
    if scale > FLOAT32_LIMIT:
        raise ValueError(f"image maximum {scale:.10g} is above {FLOAT32_LIMIT:.10g}, the "
                         "largest value plenocl reconstructs in float32; divide the image "
                         "by a constant (the volume scales with it)")
    if scale == 0:
        return img.astype(np.float32), 0.0, thr
    return (img / scale).astype(np.float32), scale, thr / scale


def prepare_image(image, camera) -> tuple[np.ndarray, float]:
    """A non-negative raw image as it is (no background removed), checked and scaled to a
    maximum of 1; returns it and the scale (:func:`preprocess` with ``background=None``)."""
    img, scale, _ = preprocess(image, camera, None, 0.0)
    return img, scale


def subtract_background(image) -> tuple[np.ndarray, float]:
    """Remove a camera's dark level and estimate its noise, robustly.

    At PIV seeding densities most pixels see no particle, so the median is the
    background and the median absolute deviation the noise. Returns the float32 image
    ``max(I - median, 0)`` and the noise standard deviation (a sensible ``threshold`` for
    :func:`reconstruct` is 3 to 5 times it).
    """
    img, sigma = _without_median(np.asarray(image, dtype=np.float64))
    return img.astype(np.float32), sigma


def _without_median(img: np.ndarray, observed: np.ndarray | None = None
                    ) -> tuple[np.ndarray, float]:
    """``max(I - median, 0)`` in float64 and the noise ``1.4826 MAD``, both over the
    ``observed`` pixels (all by default)."""
    data = img if observed is None else img[observed]
    med = float(np.median(data))
    sigma = 1.4826 * float(np.median(np.abs(data - med)))
    return np.clip(img - med, 0, None), sigma
