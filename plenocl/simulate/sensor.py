"""Sensor effects applied to a noise-free image: background, shot and read noise,
gain, bit depth and saturation. Host code with NumPy's seeded generator, so the
result is the same on every device. And the inverse a real camera needs: a dark frame
subtracted and a flat field divided out (:func:`correct_frame`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorModel:
    """How a noise-free image (in counts) becomes a recorded one.

    Parameters
    ----------
    background
        Constant background added to every pixel (counts).
    photon_noise
        Poisson shot noise on signal plus background.
    electrons_per_count
        Gain: photo-electrons per count (shot noise scales as ``sqrt(counts / gain)``).
    read_noise
        Gaussian read noise, standard deviation in counts.
    bit_depth
        Digitise to unsigned integers of this many bits (``None``: keep float32).
    saturation
        Full-scale level in counts; defaults to ``2**bit_depth - 1``.
    """

    background: float = 0.0
    photon_noise: bool = False
    electrons_per_count: float = 1.0
    read_noise: float = 0.0
    bit_depth: int | None = None
    saturation: float | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.background) or self.background < 0:
            raise ValueError(f"background must be >= 0 counts, got {self.background}")
        if not (np.isfinite(self.electrons_per_count) and self.electrons_per_count > 0):
            raise ValueError(f"electrons_per_count must be a finite number > 0, got "
                             f"{self.electrons_per_count}")
        if not np.isfinite(self.read_noise) or self.read_noise < 0:
            raise ValueError(f"read_noise must be >= 0 counts, got {self.read_noise}")
        if self.bit_depth is not None and not (float(self.bit_depth).is_integer()
                                               and 1 <= self.bit_depth <= 16):
            raise ValueError(f"bit_depth must be a whole number from 1 to 16, got "
                             f"{self.bit_depth}")
        if self.saturation is not None and not self.saturation > 0:
            raise ValueError(f"saturation must be > 0 counts, got {self.saturation}")
        top = self.integer_full_scale
        if self.saturation is not None and self.saturation > top:
            raise ValueError(f"saturation {self.saturation:g} counts lies above the "
                             f"{int(self.bit_depth)}-bit full scale {top:g}: the integers "
                             "cannot hold it (brighter pixels wrapped around); give a "
                             f"saturation <= {top:g} or a larger bit_depth")

    @property
    def integer_full_scale(self) -> float:
        """The largest count the digitised integers hold (``inf`` without a bit depth)."""
        return float(2 ** int(self.bit_depth) - 1) if self.bit_depth is not None else np.inf

    @property
    def full_scale(self) -> float:
        """The saturation level in counts (``inf`` for an ideal float sensor)."""
        if self.saturation is not None:
            return float(self.saturation)
        return self.integer_full_scale

    def apply(self, image: np.ndarray, seed: int = 0) -> np.ndarray:
        """Return the recorded image for the noise-free ``image`` (counts)."""
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5E7508])
        out = np.asarray(image, dtype=np.float64) + self.background
        if self.photon_noise:
            out = rng.poisson(out * self.electrons_per_count) / self.electrons_per_count
        if self.read_noise > 0:
            out = out + rng.normal(0.0, self.read_noise, out.shape)
        out = np.clip(out, 0.0, self.full_scale)
        if self.bit_depth is None:
            return out.astype(np.float32)
        dtype = np.uint8 if int(self.bit_depth) <= 8 else np.uint16
        return np.rint(out).astype(dtype)


def correct_frame(image, dark=None, flat=None) -> np.ndarray:
    """A raw frame with the camera's dark frame subtracted and its flat field divided out.

    Parameters
    ----------
    image
        The raw frame ``(rows, cols)``.
    dark
        A dark frame (lens capped, same exposure), or ``None``.
    flat
        A flat field (a uniformly lit frame, its dark level included), or ``None``: the
        frame is divided by ``(flat - dark)`` normalised to a mean of 1, so each pixel's
        gain is evened out. Pixels where it is not positive are refused.

    Returns
    -------
    numpy.ndarray
        float64; negative pixels are kept (noise about a subtracted dark level).
    """
    img = np.asarray(image, dtype=np.float64)
    for name, other in (("dark frame", dark), ("flat field", flat)):
        if other is not None and np.shape(other) != img.shape:
            raise ValueError(f"the {name} is {np.shape(other)} (rows, columns) but the image "
                             f"is {img.shape}: use frames of the same camera and region")
    out = img - (0.0 if dark is None else np.asarray(dark, dtype=np.float64))
    if flat is not None:
        gain = flat_gain(flat, dark)
        out = out / (gain / gain.mean())
    return out


def flat_gain(flat, dark=None, name: str = "the flat field") -> np.ndarray:
    """``flat - dark`` (float64; ``dark`` ``None``: the flat field itself), the gain a
    flat field measures; refused where it is not positive (or not finite), naming
    ``name``, the pixels and the first of them."""
    gain = np.asarray(flat, dtype=np.float64) - (0.0 if dark is None else
                                                 np.asarray(dark, dtype=np.float64))
    bad = ~(gain > 0)
    if bad.any():
        row, col = (int(v) for v in np.argwhere(bad)[0])
        minus = "" if dark is None else " minus the dark frame"
        raise ValueError(f"{name}{minus} is not positive at {int(bad.sum())} pixel(s), the "
                         f"first at row {row}, column {col}: take the flat field with light "
                         "on every pixel (and the dark frame at the same exposure)")
    return gain
