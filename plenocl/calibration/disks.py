"""A white image at full aperture (docs/design.md §3): whether an image is one, its
flattened disks detected and centroided (the disks' own fit is
:func:`plenocl.lenscentres.fit_disks`)."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from .checks import odd_size
from .spots import (
    DUPLICATE_RADIUS,
    half_lines,
    local_floor,
    patches,
    settle,
    split_halves,
    suppress_duplicates,
)

#: Apertures a white image is taken at: ``"auto"`` tells them apart by the bright pixels.
APERTURES = ("auto", "stopped", "full")

#: Above this fraction of bright pixels (over half their local range) an image is a
#: full-aperture one (stopped down to f/16: about 2 %; full aperture: 60-75 %).
FULL_APERTURE_FRACTION = 0.3

#: Radius (pitches, plus 1 px of edge blur) of the circular window of a full-aperture disk.
DISK_WINDOW = 0.5


def _bright_fraction(img: np.ndarray, pitch: float) -> float:
    """Fraction of pixels above half their local range (the minimum and maximum over a
    pitch): a few % for stopped-down spots, most of the image for full-aperture disks."""
    smooth = ndimage.gaussian_filter(img, 1.0)
    floor = ndimage.minimum_filter(smooth, odd_size(pitch))
    top = ndimage.maximum_filter(smooth, odd_size(pitch))
    return float(np.mean(smooth - floor > 0.5 * (top - floor)))


def choose_aperture(img: np.ndarray, pitch: float, aperture: str) -> str:
    """``"stopped"`` or ``"full"``: as asked, or from the bright-pixel fraction."""
    if aperture not in APERTURES:
        raise ValueError(f"aperture must be one of {APERTURES}, got {aperture!r}")
    if aperture != "auto":
        return aperture
    return "full" if _bright_fraction(img, pitch) > FULL_APERTURE_FRACTION else "stopped"


def flatten_disks(img: np.ndarray, pitch: float) -> np.ndarray:
    """The disks above the gaps between them, divided by their local mean over a pitch
    (two box filters): vignetting's falloff across each disk, which would pull its
    centroid toward the bright side, is
    taken out to first order (without it the grid model of a 50 % vignetted image was
    0.14 px RMS off, with it 0.005). Where almost no light arrives the result is 0."""
    signal = img - local_floor(img, pitch)
    env = ndimage.uniform_filter(ndimage.uniform_filter(signal, odd_size(pitch)), odd_size(pitch))
    lit = env > 0.02 * float(np.percentile(env, 99))
    return np.where(lit, signal / np.where(lit, env, 1.0), 0.0)


def detect_disks(flat: np.ndarray, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer ``(col, row)`` positions and strengths of full-aperture disks: maxima of
    the flattened image smoothed over a quarter pitch (a disk's centre), above half the
    brightest one within 2.5 pitches (dead lenses and the gaps stay out)."""
    smooth = ndimage.gaussian_filter(flat, 0.25 * pitch)
    peak = ndimage.maximum_filter(smooth, odd_size(0.5 * pitch))
    nearby = ndimage.maximum_filter(smooth, odd_size(2.5 * pitch))
    rows, cols = np.nonzero((smooth == peak) & (smooth > 0.5 * nearby) & (smooth > 0))
    pts, strength = np.column_stack([cols, rows]), smooth[rows, cols]
    keep = suppress_duplicates(pts, strength, DUPLICATE_RADIUS * pitch)
    return pts[keep], strength[keep]


def disk_centroids(flat: np.ndarray, peaks: np.ndarray, pitch: float,
                    iterations: int = 30) -> tuple[np.ndarray, float, np.ndarray]:
    """Centroids ``(N, 2)`` of full-aperture disks in a circular window centred on each,
    iterated until the window sits on the disk's centre of symmetry; the equivalent spot
    width for the sensor-edge margin; the split differences (their noise).

    The window (``DISK_WINDOW`` pitches plus 1 px for the edge's blur) holds the whole
    disk, so the centroid follows it one to one; what it takes of the neighbours' edges
    is symmetric about a lens on a regular lattice.
    """
    radius = DISK_WINDOW * pitch + 1.0
    half = int(math.ceil(radius)) + 1
    pad = half + 2
    padded = np.pad(flat, pad, mode="constant", constant_values=0.0)
    c = settle(lambda at, which: _disk_step(padded, pad, at, radius, half), peaks, pitch,
                iterations)
    split = split_halves(lambda at, lines: _disk_step(padded, pad, at, radius, half, lines),
                          c)  # a disk is mirror-symmetric about its centre's row and column
    return c, (radius - 1.0) / 3.0, split


def _disk_step(padded, pad, c, radius: float, half: int,
               lines: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One centroid update ``(N, 2)`` in a circular window (1 px soft edge) and which
    disks still have signal; ``lines`` as for :func:`centroid_step`."""
    base = np.rint(c).astype(np.int64)
    patch, off = patches(padded, pad, base, half)
    dx = base[:, 0, None] + off[None, :] - c[:, 0, None]
    dy = base[:, 1, None] + off[None, :] - c[:, 1, None]
    window = np.clip(radius + 0.5 - np.hypot(dx[:, None, :], dy[:, :, None]), 0.0, 1.0)
    signal = half_lines(np.clip(patch, 0.0, None) * window, base, off, lines)
    total = signal.sum((1, 2))
    ok = total > 0
    safe = np.where(ok, total, 1.0)
    step = np.stack([(signal * dx[:, None, :]).sum((1, 2)),
                     (signal * dy[:, :, None]).sum((1, 2))], -1) / safe[:, None]
    return np.where(ok[:, None], np.clip(step, -2.0, 2.0), 0.0), ok
