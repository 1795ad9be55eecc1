"""The raw image a reconstruction starts from: scaling and background (the checks and the
robust background are the optics model's, :mod:`plenocl.optics.rawimage`), and the image
prepared once for every run of a reconstruction (:class:`PreparedImage`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..opencl.arrays import upload
from ..optics.rawimage import (
    CountHistogram,
    ScaledImage,
    background_and_noise,
    check_exposure,
    check_image,
    counted,
    dark_noise,
    divided_to_float32,
)
from .deviceimage import DeviceCounts, prepares_on_device
from .operator import ProjectionOperator
from .settings import ReconstructionSettings

#: Largest image value accepted: the volume (in image units) must stay finite in float32.
FLOAT32_LIMIT = float(np.float32(1e30))  # 1e30 as float32 (1.0000000150e30): such images pass


#: With the median background removed, pixels count as light above this many noise
#: standard deviations (the default ``threshold``).
NOISE_SIGMAS = 4.0
#: How the background is handled: subtract the median (and threshold at the noise), or
#: take the image as it is.
BACKGROUNDS = ("median", None)


class UnusableImageError(ValueError):
    """The image cannot give a volume: blank, saturated, or without light above its
    background or threshold (the volume would come out empty). ``which`` names the image
    of a pair (``"a"``, ``"b"``) when known."""

    def __init__(self, message: str, which: str | None = None) -> None:
        super().__init__(message)
        self.which = which


def preprocess(image, camera, background: str | None = "median",
               threshold: float | None = None, observed: np.ndarray | None = None,
               smooth_px: float | None = None) -> tuple[np.ndarray, float, float]:
    """The one preprocessing of the API and the command line.

    Parameters
    ----------
    image, camera
        The raw image and its camera (:func:`plenocl.optics.rawimage.check_image`).
    background
        ``"median"``: subtract the median (the camera's dark level at PIV seeding, where
        most pixels see no particle), clipping at 0; an image with pixels below zero but
        not its median had its dark level subtracted already (a dark frame) and is
        clipped at 0 instead, its noise measured from those pixels
        (:func:`plenocl.optics.rawimage.background_and_noise`). ``None``: use the image
        as it is, clipping pixels below zero (noise about a subtracted dark level).
    threshold
        Pixels at or below it (image units, after the background) are dark. ``None``:
        :data:`NOISE_SIGMAS` times the noise: the median absolute deviation, or for a
        dark-subtracted image the spread of its pixels below zero (0 when none is).
    observed
        Bool per pixel, ``False`` where the image holds no data: the background, noise
        and scale come from the other pixels, and these are set to 0 (the solver gives
        them no weight; :class:`plenocl.reconstruction.Solver`).
    smooth_px
        A Gaussian's standard deviation (pixels) to smooth the image with after its
        background is removed and before it is clipped and thresholded
        (:func:`smooth_image`; docs/design.md §6.2). The background and noise are the
        raw image's; the default threshold follows the noise the smoothing leaves
        (:func:`smoothing_gain`). ``None`` or 0: no smoothing.

    Returns
    -------
    image, scale, threshold
        The float32 image scaled to a maximum of 1, the scale (0 for an image without
        light) and the threshold in the scaled units.
    """
    prepared = _preprocessed(image, camera, background, threshold, observed,
                             smooth_px=smooth_px)
    return prepared.image, prepared.scale, prepared.threshold


def gaussian_taps(sigma: float) -> np.ndarray:
    """The normalised 1-D Gaussian of standard deviation ``sigma`` (pixels), sampled at
    whole pixels out to 4 sigma (at least one pixel each side)."""
    reach = max(1, int(np.ceil(4.0 * sigma)))
    taps = np.exp(-0.5 * (np.arange(-reach, reach + 1) / sigma) ** 2)
    return taps / taps.sum()


def smoothing_gain(sigma: float) -> float:
    """The factor by which :func:`smooth_image` scales pixel-independent noise: the
    2-D kernel's Euclidean norm, ``Σ g²`` of the 1-D taps (0.28 at 1 px)."""
    return float(np.sum(gaussian_taps(sigma) ** 2))


def smooth_image(img: np.ndarray, sigma: float, observed: np.ndarray | None = None
                 ) -> np.ndarray:
    """``img`` smoothed by a separable Gaussian (:func:`gaussian_taps`), edges reflected.

    With ``observed`` (bool per pixel, ``False`` where the image holds no data) the
    smoothing is normalised over the observed pixels alone (``G(I m) / G(m)``), so no
    pixel without data darkens its neighbours; those pixels come out 0.
    """
    taps = gaussian_taps(sigma)

    def blur(a: np.ndarray) -> np.ndarray:
        a = ndimage.correlate1d(a, taps, axis=0, mode="reflect")
        return ndimage.correlate1d(a, taps, axis=1, mode="reflect")

    if observed is None:
        return blur(img)
    weight = blur(observed.astype(img.dtype))
    out = blur(np.where(observed, img, 0.0))
    np.divide(out, weight, out=out, where=weight > 0)
    out[~observed] = 0.0
    return out


def _preprocessed(image, camera, background: str | None, threshold: float | None,
                  observed: np.ndarray | None, exposure: bool = False,
                  smooth_px: float | None = None) -> PreparedImage:
    """:func:`preprocess` as a :class:`PreparedImage` (no lit lenses), with the median
    and noise it removed; ``exposure``: a blank or saturated image is refused first."""
    img = check_image(image, camera)
    source = counted(image, img)  # the raw counts where integers: the same values, fewer bytes
    if exposure:
        try:
            check_exposure(source, "the image", observed=observed)
        except ValueError as exc:
            raise UnusableImageError(str(exc)) from None
    if observed is not None:
        img = np.where(observed, img, 0.0)  # no data: no light, no statistics
    med = noise = None
    if background == "median":
        med, noise = background_and_noise(source, observed)
    elif background is None:
        if img.min() < 0:  # a dark frame subtracted: its noise below zero, clipped
            med, noise = 0.0, dark_noise(img, observed)
    else:
        raise ValueError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    # in place on check_image's own float64 copy: no 16 MP temporaries
    np.subtract(img, med or 0.0, out=img)
    gain = 1.0
    if smooth_px:  # noise averaged before clipping: no bias from the clip
        img, gain = smooth_image(img, smooth_px, observed), smoothing_gain(smooth_px)
    np.maximum(img, 0.0, out=img)
    if observed is not None:  # 0 - a negative median would give them light
        img[~observed] = 0.0
    scale = _checked_scale(float(img.max()))
    thr = _threshold(threshold, noise, gain, scale)
    # the image fit's image where nothing but the background was removed: the same
    # division as plenocl.optics.rawimage.scaled_background_free (PreparedImage.fit_image)
    out, smoothed = divided_to_float32(img, scale), bool(smooth_px)
    return PreparedImage(out, scale, thr, observed, None, med, noise, smoothed)


def _checked_scale(scale: float) -> float:
    """The image's brightest pixel after its background, refused above float32's reach."""
    if scale > FLOAT32_LIMIT:
        raise ValueError(f"image maximum {scale:.10g} is above {FLOAT32_LIMIT:.10g}, the "
                         "largest value plenocl reconstructs in float32; divide the image "
                         "by a constant (the volume scales with it)")
    return scale


def _threshold(threshold: float | None, noise: float | None, gain: float,
               scale: float) -> float:
    """The dark-pixel threshold in the scaled image's units: ``threshold`` given, or
    :data:`NOISE_SIGMAS` times the noise (times the smoothing's ``gain``)."""
    thr = NOISE_SIGMAS * gain * (noise or 0.0) if threshold is None else float(threshold)
    return thr / scale if scale else thr


def _prepared_counts(image: np.ndarray, camera, queue, settings: ReconstructionSettings
                     ) -> PreparedImage | None:
    """:func:`prepare_on_host` of a camera's counts with the image made on ``queue``'s
    device (:class:`plenocl.reconstruction.deviceimage.DeviceCounts`): the checks, median,
    noise, scale and the image's norm from the counts' histogram (counted there too), the
    same values and image bits. ``None`` where the host prepares it instead (counts below
    zero, whose background is found otherwise, or a frame without light, which it
    refuses)."""
    raw = check_image(image, camera, image.dtype, copy=False)
    counts = DeviceCounts(queue, raw.dtype)
    on_device = counts.upload(raw)  # once, for the histogram and the image
    hist = counts.histogram(raw, on_device)
    if hist is None or hist.low < 0:
        return None
    try:
        hist.check_exposure("the image")
    except ValueError as exc:
        raise UnusableImageError(str(exc)) from None
    med, noise = (hist.median_and_noise() if settings.background == "median"
                  else (None, None))
    scale = _checked_scale(float(max(hist.high - (med or 0.0), 0.0)))
    if scale == 0:
        return None
    device = counts.scaled(on_device, med or 0.0, scale)
    prepared = PreparedImage(None, scale, _threshold(settings.threshold, noise, 1.0, scale),
                             None, None, med, noise, made_with=_preparation(settings, None),
                             norm_value=_counts_norm(hist, med or 0.0, scale))
    prepared.keep_on_device(queue, device)
    return prepared


def _counts_norm(hist: CountHistogram, median: float, scale: float) -> float:
    """The Euclidean norm of the scaled image of ``hist``'s frame, from its levels'
    float32 values (float64 sums)."""
    values = divided_to_float32(np.maximum(hist.levels() - median, 0.0), scale)
    return float(np.sqrt(np.dot(hist.counts, values.astype(np.float64) ** 2)))


def scale_raw_image(image, camera) -> tuple[np.ndarray, float]:
    """A raw image as it is (no background removed; pixels below zero clipped), checked
    and scaled to a maximum of 1; returns it and the scale (:func:`preprocess` with
    ``background=None``)."""
    img, scale, _ = preprocess(image, camera, None, 0.0)
    return img, scale


@dataclass(frozen=True)
class PreparedImage:
    """A raw image as the solver takes it, prepared once per reconstruction and shared by
    its runs (the coarse and the fine one of a coarse-to-fine reconstruction).

    Attributes
    ----------
    image, scale, threshold
        :func:`preprocess`'s scaled float32 image, scale (0: no light) and threshold.
    observed
        Bool per pixel, ``False`` where the image holds no data (``None``: all data).
    lit
        Bool per microlens, the lenses that see a pixel above the threshold
        (:meth:`plenocl.reconstruction.operator.ProjectionOperator.lit_lenses`); ``None``
        without dark-microlens skipping. A camera's, so a refined operator's are the same.
    background, noise
        The median and noise (image units) the median background removed (``None``
        with ``background=None``): the particle fit reuses them
        (:class:`plenocl.reconstruction.ReconstructionInfo`).
    smoothed
        Whether the image was smoothed (``smooth_px``) before it was scaled.
    """

    image: np.ndarray | None
    scale: float
    threshold: float
    observed: np.ndarray | None = None
    lit: np.ndarray | None = None
    background: float | None = None
    noise: float | None = None
    smoothed: bool = False
    #: What it was prepared with (:func:`prepare_on_host`: background, threshold,
    #: smoothing, a pixel mask or not).
    made_with: tuple | None = dataclasses.field(default=None, compare=False, repr=False)
    #: The image's norm where it was found without the host image (:meth:`norm`).
    norm_value: float | None = dataclasses.field(default=None, compare=False, repr=False)
    #: The image's device copies by queue (:meth:`on_device`): uploaded once, not once
    #: per run (a coarse-to-fine reconstruction's three runs read the same image).
    _device: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)

    def keep_on_device(self, queue, device) -> None:
        """Keep ``device``, this image made on ``queue``'s device, as its copy there
        (:meth:`on_device`); an image prepared on the device has no other."""
        self._device[queue.int_ptr] = device

    def on_device(self, queue):
        """:attr:`image` on ``queue``'s device, uploaded at the first call (the solver
        only reads it)."""
        key = queue.int_ptr
        if key not in self._device:
            self._device[key] = upload(queue, self.host_image())
        return self._device[key]

    def host_image(self) -> np.ndarray:
        """:attr:`image`, or for an image prepared on a device (``image`` ``None``) its
        copy from there, made once."""
        if self.image is None:
            if "host" not in self._device:
                self._device["host"] = next(iter(self._device.values())).get()
            return self._device["host"]
        return self.image

    def norm(self) -> float:
        """The image's Euclidean norm (the solver's residuals are relative to it)."""
        if self.norm_value is not None:
            return self.norm_value
        return float(np.linalg.norm(self.image))

    def fit_image(self, queue=None) -> ScaledImage | None:
        """The image fit's image where it is this one, to the bit
        (:func:`plenocl.optics.rawimage.scaled_background_free`): a background removed
        (:attr:`background`), not smoothed, every pixel observed; with its device copy on
        ``queue`` (:meth:`on_device`; ``None``: none). ``None`` otherwise. An image
        prepared on ``queue``'s device gives its device copy alone (the host's is made
        where something reads :attr:`ScaledImage.values`)."""
        if self.background is None or self.smoothed or self.observed is not None:
            return None
        device = None if queue is None else self.on_device(queue)
        values = self.host_image() if device is None else self.image
        return ScaledImage(values, self.scale, device)


def prepare_on_host(image, camera, settings: ReconstructionSettings,
                    observed: np.ndarray | None = None) -> PreparedImage:
    """:func:`prepare_image`'s host part, without the lit lenses and its refusals of an
    empty image: :func:`preprocess` with ``settings``' background and threshold, a blank
    or saturated image refused (:class:`UnusableImageError`). NumPy alone, so it may run
    on another thread while the device reconstructs (:func:`plenocl.process_pair` makes
    the second exposure's so on a GPU)."""
    prepared = _preprocessed(image, camera, settings.background, settings.threshold,
                             observed, exposure=True, smooth_px=settings.smooth_px)
    return dataclasses.replace(prepared, made_with=_preparation(settings, observed))


def _preparation(settings: ReconstructionSettings, observed) -> tuple:
    """What a host preparation depends on beside the image (:attr:`PreparedImage.made_with`)."""
    return (settings.background, settings.threshold, settings.smooth_px,
            observed is not None)


def prepare_image(image, projector: ProjectionOperator, settings: ReconstructionSettings,
                  observed: np.ndarray | None = None,
                  ahead: PreparedImage | None = None) -> PreparedImage:
    """:func:`preprocess` with ``settings``' background and threshold, and the lit
    lenses when ``settings.skip_dark``. A blank or saturated image
    (:func:`plenocl.optics.rawimage.check_exposure`), or one whose every pixel is dark
    (the volume would be empty), is refused: :class:`UnusableImageError`.
    ``ahead``: :func:`prepare_on_host` of this image with these settings and
    ``observed``, made beforehand (``image`` is then not read)."""
    if ahead is not None and ahead.made_with != _preparation(settings, observed):
        raise ValueError("ahead was prepared with other settings than this reconstruction's "
                         "(background, threshold, smoothing or pixel mask): prepare it with "
                         "prepare_on_host and the same ones")
    queue = getattr(projector, "queue", None)
    prepared = ahead
    if prepared is None and queue is not None and prepares_on_device(
            image, settings.background, settings.smooth_px, observed):
        prepared = _prepared_counts(image, projector.camera, queue, settings)
    if prepared is None:
        prepared = prepare_on_host(image, projector.camera, settings, observed)
    if prepared.scale == 0:
        raise UnusableImageError(
            "the image holds no light above its background, so the volume would be empty: "
            "check the exposure and the file (or background=None, --background none, for an "
            "image whose dark level is already removed)")
    if prepared.threshold >= 1.0:
        _refuse_all_dark(prepared.threshold * prepared.scale, prepared.scale,
                         settings.threshold is None)
    if not settings.skip_dark:
        return prepared
    # lenses without data give no update either: skipped alike. Where the operator has a
    # device, found there on the image the solver then reads (uploaded once)
    image = prepared.image if queue is None else prepared.on_device(queue)
    return dataclasses.replace(prepared, lit=projector.lit_lenses(image, prepared.threshold))


def _refuse_all_dark(threshold: float, peak: float, estimated: bool) -> None:
    """Every pixel is at or below the dark-pixel threshold: the volume would be empty."""
    why = (f"the default, {NOISE_SIGMAS:g} x the noise estimated from the median absolute "
           "deviation, fails on a dense image whose median is not its background"
           if estimated else "the threshold given")
    raise UnusableImageError(
        f"the dark-pixel threshold {threshold:.4g} is at or above the image's brightest "
        f"pixel {peak:.4g} ({why}): every pixel counts as dark and the volume would be "
        "empty. Subtract the camera's dark frame (--dark; its noise below zero then sets "
        "the threshold), take the image as it is where its dark level is already removed "
        "(background=None, --background none), or give a lower threshold (threshold=, "
        "--threshold)")
