"""Microlens image centres from a white image (docs/design.md §3, paper §II.A).

A white image is taken with the main lens stopped down: every microlens images the
small aperture as a spot centred on its image centre ``c_k = x_k (1 + f_ml/d)``.
Calibration finds those spots to sub-pixel accuracy and matches each to its lens
``(kx, ky)``:

1. **Detect** spots: Gaussian-smoothed local maxima above a threshold relative to the
   brightest spot nearby (so vignetted, dim edges are kept and dead lenses are not
   filled with noise).
2. **Centroid** each spot: background-subtracted (the median of a ring between the
   spots), Gaussian-windowed and iterated to convergence; a symmetric spot then gives
   its centre without the bias a fixed box window has toward its own middle.
3. **Match** the spots to the lattice: pitch and rotation from nearest-neighbour
   vectors, the sub-pitch shift from the phase of the lattice coordinates, the
   whole-pitch shift from the extent of the array on the sensor.
4. **Fit** a global grid model (affine: pitch, rotation, shear, shift; optionally a
   cubic polynomial for distortion, chosen by an F-test; a hexagonal array's odd rows'
   own offset) to the matched centroids,
   robustly. Its prediction carries the information of all spots instead of one
   lens's few noisy photons, but a real array's lenses also sit off any lattice by
   manufacturing errors of a fraction of a pixel.
5. **Combine** the model and each lens's own centroid by their uncertainties
   (``method="combined"``, the default): each centroid's noise is measured from the
   image itself (the two checkerboard halves of a spot's pixels see independent noise),
   the lenses' true scatter about the lattice is what the centroids scatter beyond that
   noise, and each centre moves from the model toward its centroid by
   ``τ² / (τ² + σ_k²)``. ``method="fit"`` keeps the model only, ``method="centroid"``
   the raw centroids (the paper's method).

White images are taken as they come: negative pixels (read noise after a dark frame is
subtracted) are used as they are, the background is estimated locally (gradients,
stray light), hot pixels are removed, dim vignetted edges and saturated spots are kept.

Shifts of the array of up to half a microlens-image pitch are matched without
ambiguity; larger ones are resolved by the array's edge when it is visible on the
sensor. Rotations of a few degrees (any angle within ±45° in principle) are handled.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage, stats
from scipy.spatial import cKDTree

from .camera import Camera
from .io.centres import read_centres
from .lenscentres import fit_disks
from .optics.lattice import axial_basis, axial_to_offset, offset_to_axial
from .optics.rawimage import check_image

#: Relative pitch error (measured vs the camera's) above which calibration refuses.
PITCH_TOLERANCE = 0.10
#: Fraction of the expected lenses that must show a spot.
MIN_FOUND_FRACTION = 0.25
#: Of a white image's spots, at least this fraction have their nearest neighbour within
#: REGULAR_SPREAD of the typical spacing (white images, stopped down or at full aperture,
#: with vignetting or a third of the lenses dark: 0.79-1.0; particle images: 0.1-0.4).
REGULAR_SHARE = 0.6
REGULAR_SPREAD = 0.1
#: Peaks (and centroids) closer than this many pitches are one spot.
DUPLICATE_RADIUS = 0.25
#: A spot must reach this fraction of the brightest spot around it.
RELATIVE_THRESHOLD = 0.25
#: Where the centres come from: grid model, raw centroid, or both weighted by uncertainty.
METHODS = ("combined", "fit", "centroid")
#: Negative pixels below this fraction of the spot peak warn (over-subtracted dark frame).
NEGATIVE_WARN = 0.1
#: F-test p-value below which the cubic grid model replaces the affine one.
DISTORTION_P_VALUE = 1e-3
#: ... and must move the centres by more than this (px RMS).
DISTORTION_MIN_PX = 0.05
#: Apertures a white image is taken at: ``"auto"`` tells them apart by the bright pixels.
APERTURES = ("auto", "stopped", "full")
#: Above this fraction of bright pixels (over half their local range) an image is a
#: full-aperture one (stopped down to f/16: about 2 %; full aperture: 60-75 %).
FULL_APERTURE_FRACTION = 0.3
#: Radius (pitches, plus 1 px of edge blur) of the circular window of a full-aperture disk.
DISK_WINDOW = 0.5
#: Width of the Gaussian centroid window: this many spot widths, at least WINDOW_MIN_PX
#: (a narrower window samples a sub-pixel spot too coarsely: 1 px biased 0.5 px spots by
#: 0.024 px toward the pixel grid, 1.5 px by 0.009).
WINDOW_SCALE = 1.5
WINDOW_MIN_PX = 1.5
#: Microlens images (px) from which full-aperture calibration fits each lens's disk; on
#: smaller ones the disk model's sampling error (0.06 px RMS at 7.7 px, rotated 2°)
#: exceeds what it resolves, and ``method="combined"`` keeps the grid model.
PER_LENS_MIN_PITCH_PX = 10.0


@dataclass(frozen=True)
class CenterFit:
    """Everything calibration measured; :func:`calibrate` keeps only ``centers``.

    Attributes
    ----------
    centers
        ``(rows, cols, 2)`` microlens image centres as ``(col, row)`` pixels, ``NaN``
        where no spot was found (unless filled from the model).
    centroids
        ``(rows, cols, 2)`` raw spot centroids, ``NaN`` where no spot was found; at full
        aperture with ``method="combined"``, each lens's own disk fit
        (:func:`plenocl.lenscentres.fit_disks`), ``NaN`` where it has none.
    model
        ``(rows, cols, 2)`` grid-model prediction for every lens (at full aperture with
        ``method="combined"``: refitted to the per-lens disk fits).
    found
        ``(rows, cols)`` lenses with a matched spot.
    inlier
        ``(rows, cols)`` spots used in the model fit (found, not cut by the sensor
        edge, not an outlier).
    degree
        Polynomial degree of the grid model (1: affine, 3: cubic distortion).
    rotation_deg, pitch_px, shift_px
        Measured array rotation, image pitch along the array's ``(x, y)`` axes, and
        shift of the array's centre against the camera's nominal layout.
    residual_rms_px
        RMS distance of the inlier centroids from the model (their noise and the lenses'
        true offsets from the lattice).
    method
        ``"combined"``, ``"fit"`` or ``"centroid"``: where ``centers`` came from.
    noise_px
        ``(rows, cols)`` estimated centroid noise per axis (px), from the two
        checkerboard halves of each spot's pixels; at full aperture with
        ``method="combined"``, each disk fit's deviation (``NaN`` where none).
    lattice_scatter_px
        Estimated RMS per axis (px) of the lenses' true offsets from the grid model
        (manufacturing errors), the centroid noise taken out.
    aperture
        ``"stopped"`` (small spots) or ``"full"`` (disks filling the lenses): how the
        image was read.
    """

    centers: np.ndarray
    centroids: np.ndarray
    model: np.ndarray
    found: np.ndarray
    inlier: np.ndarray
    degree: int
    rotation_deg: float
    pitch_px: tuple[float, float]
    shift_px: tuple[float, float]
    residual_rms_px: float
    method: str
    noise_px: np.ndarray
    lattice_scatter_px: float
    aperture: str = "stopped"

    @property
    def n_missing(self) -> int:
        """Lenses without a spot."""
        return int((~self.found).sum())

    @property
    def n_outliers(self) -> int:
        """Found spots left out of the model fit (outliers or cut by the sensor edge)."""
        return int((self.found & ~self.inlier).sum())


# ---- input checks -------------------------------------------------------------------
def _validate_image(image, camera: Camera) -> np.ndarray:
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


def _pitch_px(camera: Camera) -> float:
    return camera.microlens_image_pitch_mm / camera.pixel_pitch_mm


def _odd(n: float) -> int:
    n = max(3, int(round(n)))
    return n if n % 2 else n + 1


# ---- 1. detection -------------------------------------------------------------------
def _local_floor(img: np.ndarray, pitch: float) -> np.ndarray:
    """Local background: the minimum over one pitch (the gaps between spots), smoothed."""
    return ndimage.uniform_filter(ndimage.minimum_filter(img, _odd(pitch)), _odd(pitch))


def _remove_hot_pixels(img: np.ndarray, pitch: float) -> np.ndarray:
    """Replace isolated hot pixels by the median of their 3 x 3 neighbourhood.

    A pixel is hot when it exceeds the brightest of its 8 neighbours by more than twice
    the typical spot peak (the median over the image of the brightest pixel within a
    pitch, above the local background) plus 8 noise. A spot's peak pixel, however sharp
    (a 0.3 px spot keeps 5 % of its peak in its brightest neighbour) or saturated, never
    rises that far above its neighbours; comparing with the neighbours' median instead
    took the peaks of sub-pixel spots for hot pixels and pulled their centroids to the
    pixel grid (0.17 px at 0.6 px spot width).
    """
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    excess = img - ndimage.maximum_filter(img, footprint=ring, mode="nearest")
    med = ndimage.median_filter(img, 3)
    resid = img - med
    noise = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    height = ndimage.maximum_filter(img - _local_floor(img, pitch), _odd(pitch))
    typical = max(float(np.median(height)), 0.0)
    hot = excess > 2 * typical + 8 * noise
    return np.where(hot, med, img) if hot.any() else img


def _detect_spots(img: np.ndarray, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer ``(col, row)`` positions of spot peaks and their strengths.

    Peaks closer than a third of the expected pitch are resolved, so spots on a finer
    lattice than the camera predicts are seen (and refused) rather than thinned out.
    The background is local (the minimum over one pitch, i.e. the gaps between spots,
    smoothed), so a background gradient or wide spots do not raise the threshold.
    """
    smooth = ndimage.gaussian_filter(img, max(1.0, 0.06 * pitch))
    bg = _local_floor(smooth, pitch)
    resid = smooth - bg
    noise = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    peak = ndimage.maximum_filter(smooth, _odd(0.35 * pitch))
    nearby = ndimage.maximum_filter(peak - bg, _odd(2.5 * pitch))
    floor = 0.02 * float(np.percentile(peak - bg, 99.0))
    thr = bg + np.maximum(np.maximum(8 * noise, floor), RELATIVE_THRESHOLD * nearby)
    rows, cols = np.nonzero((smooth == peak) & (smooth > thr))
    pts = np.column_stack([cols, rows])
    strength = smooth[rows, cols]
    keep = _suppress_duplicates(pts, strength, DUPLICATE_RADIUS * pitch)
    return pts[keep], strength[keep]


def _suppress_duplicates(pts: np.ndarray, strength: np.ndarray, radius: float) -> np.ndarray:
    """Mask keeping the strongest of points closer than ``radius`` (one spot's plateau)."""
    keep = np.ones(len(pts), bool)
    if len(pts) < 2:
        return keep
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return keep
    a, b = pairs[:, 0], pairs[:, 1]
    weaker = np.where(strength[a] < strength[b], a, b)
    ties = strength[a] == strength[b]
    weaker[ties] = np.maximum(a, b)[ties]
    keep[weaker] = False
    return keep


# ---- 2. centroids -------------------------------------------------------------------
def _patches(padded: np.ndarray, pad: int, centre: np.ndarray, half: int):
    """Patches ``(N, 2h+1, 2h+1)`` of the padded image around integer centres."""
    off = np.arange(-half, half + 1)
    cols = centre[:, 0, None, None] + off[None, None, :] + pad
    rows = centre[:, 1, None, None] + off[None, :, None] + pad
    return padded[rows, cols], off


def _local_background(padded, pad, peaks, pitch) -> np.ndarray:
    """Median of a ring halfway between neighbouring spots, per spot."""
    half = max(2, int(0.45 * pitch))
    patch, off = _patches(padded, pad, peaks, half)
    r = np.hypot(off[None, :], off[:, None])
    ring = (r >= half - 1.5) & (r <= half + 0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rings at the corners
        return np.nanmedian(patch[:, ring], axis=1)


def _spot_sigma(patch: np.ndarray, off: np.ndarray) -> float:
    """Median per-axis RMS width (px) of the brightest, box-centroided spots."""
    w = np.clip(patch, 0, None)
    total = w.sum((1, 2))
    bright = (total >= np.percentile(total, 50)) & (total > 0)
    if not bright.any():
        return 1.0
    w, total = w[bright], total[bright]
    mx = (w * off[None, None, :]).sum((1, 2)) / total
    my = (w * off[None, :, None]).sum((1, 2)) / total
    var = ((w * (off[None, None, :] - mx[:, None, None]) ** 2).sum((1, 2))
           + (w * (off[None, :, None] - my[:, None, None]) ** 2).sum((1, 2))) / (2 * total)
    return float(np.sqrt(np.median(var)))


def _windowed_centroids(img: np.ndarray, peaks: np.ndarray, pitch: float,
                        iterations: int = 30) -> tuple[np.ndarray, float, np.ndarray]:
    """Iterated Gaussian-windowed centroids ``(N, 2)`` (``NaN``: lost), the spot width,
    and each spot's split difference (:func:`_split_difference`, its noise).

    The window is ``WINDOW_SCALE`` spot widths ``σ`` wide (``s``); a windowed centroid
    of a Gaussian spot moves ``s²/(σ²+s²)`` of the way to its centre, so each step is
    scaled by the inverse and converges in a step or two.
    """
    pad = int(pitch) + 2
    padded = np.pad(img, pad, mode="constant", constant_values=np.nan)
    bg = _local_background(padded, pad, peaks, pitch)
    bg = np.where(np.isfinite(bg), bg, float(np.median(img)))
    half = max(2, min(int(0.45 * pitch), int(round(0.3 * pitch))))
    patch, off = _patches(padded, pad, peaks, half)
    sigma = max(0.5, _spot_sigma(np.nan_to_num(patch - bg[:, None, None]), off))
    width = max(WINDOW_MIN_PX, WINDOW_SCALE * sigma)
    half = max(2, min(int(0.45 * pitch), int(math.ceil(4 * width))))
    gain = 1.0 + sigma**2 / width**2
    c = _settle(lambda at, which: _centroid_step(padded, pad, at, bg[which], half, width, gain),
                peaks, pitch, iterations)
    return c, sigma, _split_difference(padded, pad, c, bg, half, width, gain)


def _split_difference(padded, pad, c, bg, half, width, gain) -> np.ndarray:
    """Each spot's ``col`` centroid from its even rows minus that from its odd rows, and
    its ``row`` centroid from its even columns minus that from its odd columns, ``(N, 2)``
    (``NaN`` for lost spots).

    The two halves see independent noise, so the difference measures a spot's centroid
    noise from the image alone: each half has twice the variance of the whole, so
    ``E[d²] = 4 σ²`` per axis. Along the axis it measures, each half keeps every pixel,
    so for a separable spot (a Gaussian) either half's centroid is the whole spot's
    however small the spot: the difference carries no sampling bias of its own. (The
    checkerboard halves used before are each sampled on a lattice that aliases a spot
    under 0.7 px wide: on 0.6 px spots they reported 0.06 px of noise where the
    centroids scattered by 0.012, and the combined centres lost the lenses' offsets.)
    """
    return _split_halves(
        lambda at, lines: _centroid_step(padded, pad, at, bg, half, width, gain, lines), c)


def _settle(step, peaks: np.ndarray, pitch: float, iterations: int) -> np.ndarray:
    """Centres ``(N, 2)`` iterated from ``peaks`` by ``step(centres, which) -> (moves,
    ok)`` (``which``: the indices of the centres given) until each moves less than 1e-5
    px; ``NaN`` for one that loses its signal or wanders over 0.3 pitch from its peak."""
    c = peaks.astype(np.float64)
    alive, active = np.ones(len(c), bool), np.arange(len(c))
    for _ in range(iterations):
        move, ok = step(c[active], active)
        c[active] += move
        alive[active] = ok & (np.abs(c[active] - peaks[active]) <= 0.3 * pitch).all(1)
        active = active[alive[active] & (np.abs(move) >= 1e-5).any(1)]
        if len(active) == 0:
            break
    c[~alive] = np.nan
    return c


def _split_halves(step, c: np.ndarray) -> np.ndarray:
    """The ``col`` centroid from the even rows minus that from the odd rows, and the
    ``row`` centroid from the even minus the odd columns, ``(N, 2)`` (``NaN`` where ``c``
    is lost), by ``step(centres, lines) -> (moves, ok)`` (:func:`_half_lines`)."""
    lost = ~np.isfinite(c).all(1)
    at = np.where(lost[:, None], 0.0, c)
    diff = np.empty_like(at)
    for axis in (0, 1):  # rows split for the col centroid, columns for the row centroid
        halves = [step(at, (1 - axis, parity))[0] for parity in (0, 1)]
        diff[:, axis] = halves[0][:, axis] - halves[1][:, axis]
    diff[lost] = np.nan
    return diff


def _half_lines(signal: np.ndarray, base: np.ndarray, off: np.ndarray,
                lines: tuple[int, int] | None) -> np.ndarray:
    """Patches ``signal`` ``(N, rows, cols)`` around ``base`` keeping only the pixels
    whose column (``lines = (0, parity)``) or row (``(1, parity)``) index has ``parity``;
    all of them for ``lines=None``."""
    if lines is None:
        return signal
    axis, parity = lines
    keep = (base[:, axis, None] + off[None, :]) % 2 == parity  # (N, 2h+1)
    return np.where(keep[:, None, :] if axis == 0 else keep[:, :, None], signal, 0.0)


def _centroid_step(padded, pad, c, bg, half, width, gain,
                   lines: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One Gaussian-windowed centroid update ``(N, 2)`` and which spots still have signal
    (from the pixels whose column (``lines = (0, parity)``) or row (``(1, parity)``) index
    has ``parity`` only, when given)."""
    base = np.rint(c).astype(np.int64)
    patch, off = _patches(padded, pad, base, half)
    signal = _half_lines(np.nan_to_num(patch - bg[:, None, None]), base, off, lines)
    dx = base[:, 0, None] + off[None, :] - c[:, 0, None]  # (N, cols of the patch)
    dy = base[:, 1, None] + off[None, :] - c[:, 1, None]  # (N, rows of the patch)
    gx, gy = np.exp(-dx**2 / (2 * width**2)), np.exp(-dy**2 / (2 * width**2))
    rows = np.einsum("nrc,nc->nr", signal, gx)  # the Gaussian window is separable
    total = (rows * gy).sum(1)
    moment_x = (np.einsum("nrc,nc->nr", signal, gx * dx) * gy).sum(1)
    moment_y = (rows * gy * dy).sum(1)
    ok = total > 0
    safe = np.where(ok, total, 1.0)[:, None]
    step = gain * np.stack([moment_x, moment_y], -1) / safe
    return np.where(ok[:, None], np.clip(step, -1.0, 1.0), 0.0), ok


# ---- 2b. full-aperture disks --------------------------------------------------------
def _bright_fraction(img: np.ndarray, pitch: float) -> float:
    """Fraction of pixels above half their local range (the minimum and maximum over a
    pitch): a few % for stopped-down spots, most of the image for full-aperture disks."""
    smooth = ndimage.gaussian_filter(img, 1.0)
    floor = ndimage.minimum_filter(smooth, _odd(pitch))
    top = ndimage.maximum_filter(smooth, _odd(pitch))
    return float(np.mean(smooth - floor > 0.5 * (top - floor)))


def _choose_aperture(img: np.ndarray, pitch: float, aperture: str) -> str:
    """``"stopped"`` or ``"full"``: as asked, or from the bright-pixel fraction."""
    if aperture not in APERTURES:
        raise ValueError(f"aperture must be one of {APERTURES}, got {aperture!r}")
    if aperture != "auto":
        return aperture
    return "full" if _bright_fraction(img, pitch) > FULL_APERTURE_FRACTION else "stopped"


def _flatten(img: np.ndarray, pitch: float) -> np.ndarray:
    """The disks above the gaps between them, divided by their local mean over a pitch
    (two box filters): vignetting's falloff across each disk, which would pull its
    centroid toward the bright side, is
    taken out to first order (without it the grid model of a 50 % vignetted image was
    0.14 px RMS off, with it 0.005). Where almost no light arrives the result is 0."""
    signal = img - _local_floor(img, pitch)
    env = ndimage.uniform_filter(ndimage.uniform_filter(signal, _odd(pitch)), _odd(pitch))
    lit = env > 0.02 * float(np.percentile(env, 99))
    return np.where(lit, signal / np.where(lit, env, 1.0), 0.0)


def _detect_disks(flat: np.ndarray, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer ``(col, row)`` positions and strengths of full-aperture disks: maxima of
    the flattened image smoothed over a quarter pitch (a disk's centre), above half the
    brightest one within 2.5 pitches (dead lenses and the gaps stay out)."""
    smooth = ndimage.gaussian_filter(flat, 0.25 * pitch)
    peak = ndimage.maximum_filter(smooth, _odd(0.5 * pitch))
    nearby = ndimage.maximum_filter(smooth, _odd(2.5 * pitch))
    rows, cols = np.nonzero((smooth == peak) & (smooth > 0.5 * nearby) & (smooth > 0))
    pts, strength = np.column_stack([cols, rows]), smooth[rows, cols]
    keep = _suppress_duplicates(pts, strength, DUPLICATE_RADIUS * pitch)
    return pts[keep], strength[keep]


def _disk_centroids(flat: np.ndarray, peaks: np.ndarray, pitch: float,
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
    c = _settle(lambda at, which: _disk_step(padded, pad, at, radius, half), peaks, pitch,
                iterations)
    split = _split_halves(lambda at, lines: _disk_step(padded, pad, at, radius, half, lines),
                          c)  # a disk is mirror-symmetric about its centre's row and column
    return c, (radius - 1.0) / 3.0, split


def _disk_step(padded, pad, c, radius: float, half: int,
               lines: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One centroid update ``(N, 2)`` in a circular window (1 px soft edge) and which
    disks still have signal; ``lines`` as for :func:`_centroid_step`."""
    base = np.rint(c).astype(np.int64)
    patch, off = _patches(padded, pad, base, half)
    dx = base[:, 0, None] + off[None, :] - c[:, 0, None]
    dy = base[:, 1, None] + off[None, :] - c[:, 1, None]
    window = np.clip(radius + 0.5 - np.hypot(dx[:, None, :], dy[:, :, None]), 0.0, 1.0)
    signal = _half_lines(np.clip(patch, 0.0, None) * window, base, off, lines)
    total = signal.sum((1, 2))
    ok = total > 0
    safe = np.where(ok, total, 1.0)
    step = np.stack([(signal * dx[:, None, :]).sum((1, 2)),
                     (signal * dy[:, :, None]).sum((1, 2))], -1) / safe[:, None]
    return np.where(ok[:, None], np.clip(step, -2.0, 2.0), 0.0), ok


# ---- 3. lattice matching ------------------------------------------------------------
def _lattice_frame(pts: np.ndarray, pitch_nominal: float, symmetry: int = 4
                   ) -> tuple[float, float]:
    """Pitch (px) and rotation (rad) of the spot lattice from nearest-neighbour vectors
    (``symmetry``: 4 for a rectangular lattice, 6 for a hexagonal one)."""
    dist, idx = cKDTree(pts).query(pts, k=min(symmetry + 1, len(pts)))
    rough = float(np.median(dist[:, 1]))
    vec = pts[idx[:, 1:]] - pts[:, None, :]
    length = np.hypot(vec[..., 0], vec[..., 1])
    near = (length > 0.8 * rough) & (length < 1.2 * rough)
    pitch = float(np.median(length[near]))
    if abs(pitch / pitch_nominal - 1) > PITCH_TOLERANCE:
        raise ValueError(
            f"the spots of the white image are {pitch:.2f} px apart but the camera predicts "
            f"{pitch_nominal:.2f} px microlens images: check the camera file (microlens pitch, "
            "pixel pitch, focal lengths, magnification) or whether this is a white image "
            "taken with the main lens stopped down")
    theta = np.arctan2(vec[..., 1][near], vec[..., 0][near])
    return pitch, float(np.angle(np.exp(1j * symmetry * theta).mean()) / symmetry)


def _match(pts: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Lens indices ``(N, 2)`` as ``(kx, ky)`` (``-1``: off the lattice) and the distance
    (in pitches) of each spot from its lattice node.

    The lattice is anchored on the spots nearest the array's nominal centre and grown
    outward, refitting an affine index-to-pixel model at each step, so a small error
    in the initial pitch or rotation never accumulates across a large array.
    """
    cols, rows = camera.ml_count
    hexagonal = camera.ml_layout == "hexagonal"
    pitch, rot = _lattice_frame(pts, _pitch_px(camera), 6 if hexagonal else 4)
    centre = camera.ideal_microlens_centers().reshape(-1, 2).mean(0)
    c, s = math.cos(rot), math.sin(rot)
    basis = axial_basis(camera.odd_row_shift, camera.ml_row_pitch_mm / camera.ml_pitch_mm)
    lin = pitch * np.array([[c, -s], [s, c]]) @ basis.T  # columns: d(px)/d(q), d(px)/d(r)
    every = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2)
    middle = offset_to_axial(every, camera.odd_row_shift).mean(0)
    model = np.vstack([lin.T, centre - lin @ middle])
    f = _fractional_index(pts, model)
    near = np.argsort(np.hypot(*(pts - centre).T))[:100]
    phase = np.angle(np.exp(2j * np.pi * f[near]).mean(0)) / (2 * np.pi)
    model[2] += lin @ phase
    model = _grow_lattice(pts, model, near)
    f = _fractional_index(pts, model)
    base = np.rint(f).astype(np.int64)
    dev = np.abs(f - base).max(1)
    if hexagonal:
        k = _hexagonal_indices(base, dev <= 0.3, model, camera, pitch)
    else:
        k = base + _lens_count_and_shift(base[dev <= 0.3], pts[dev <= 0.3], model, camera,
                                         pitch)
    inside = (k[:, 0] >= 0) & (k[:, 0] < cols) & (k[:, 1] >= 0) & (k[:, 1] < rows)
    k[(dev > 0.3) | ~inside] = -1
    return k, dev


def _lens_count_and_shift(base: np.ndarray, pts: np.ndarray, model: np.ndarray,
                          camera: Camera, pitch: float) -> np.ndarray:
    """Check the camera file's lens count against the white image and return the index
    shift that makes lens 0 the first lens of the array; refuse a wrong count, naming
    both counts (``[microlens_array] count``).

    The rule (docs/design.md §2): the array's lenses are those whose image centre lies
    on the sensor. Along each axis the first and last lens are the outermost spots seen
    (between the 0.2 % and 99.8 % quantiles of the spots' lattice indices, so stray
    spots do not count), corrected at the sensor's edge from the fitted lattice: a spot
    whose lattice centre lies off the sensor is not a lens of the array, and a lens
    whose centre lies on the sensor within half a pitch of its edge is one, whether or
    not its cut image was detected. So an array that fills or overfills the sensor gets
    one count and one labelling, whatever the image's noise or encoding.
    """
    count = np.array(camera.ml_count)
    if len(base) < 10:
        return _whole_pitch_shift(base, *camera.ml_count)
    size = np.array(camera.pixels, float)
    lo, hi = np.rint(np.percentile(base, [0.2, 99.8], axis=0)).astype(int)
    first, last = lo.copy(), hi.copy()
    for axis in (0, 1):
        other = float(np.median(base[:, 1 - axis]))
        edge = _EdgeLattice(model, axis, other, size[axis], pitch)
        first[axis], last[axis] = edge.boundary(lo[axis], -1), edge.boundary(hi[axis], +1)
    seen = last - first + 1
    if (seen != count).any():
        raise ValueError(
            f"the white image shows about {seen[0]} x {seen[1]} microlens images (columns x "
            f"rows, counting those whose centre lies on the sensor) but the camera file has "
            f"{count[0]} x {count[1]} microlenses: correct [microlens_array] count = "
            "[columns, rows] in the camera file")
    return -first


def _hexagonal_indices(base: np.ndarray, ok: np.ndarray, model: np.ndarray,
                       camera: Camera, pitch: float) -> np.ndarray:
    """Lens indices ``(kx, ky)`` of spots at axial lattice indices ``base`` (``ok``: on
    the lattice) on a hexagonal array, with the counting rule of
    :func:`_lens_count_and_shift` (docs/design.md §3): row 0 is the first row whose
    centres lie on the sensor, lens 0 of the even rows their first such lens, and the
    odd rows sit ``odd_row_shift`` pitches from them; a camera file whose count or shift
    disagrees with the image is refused, naming the fix."""
    if ok.sum() < 10:
        raise ValueError(f"only {int(ok.sum())} spots lie on a hexagonal lattice: too few to "
                         "number the lenses; check the white image and the camera file")
    size, (cols, rows) = np.array(camera.pixels, float), camera.ml_count
    q, r = base[ok].T
    lo, hi = np.rint(np.percentile(r, [0.2, 99.8])).astype(int)
    # along the rows' normal: q drifts by -shift per row (e2 leans by shift along a row)
    middle = float(np.median(r))
    row_pitch = pitch * camera.ml_row_pitch_mm / camera.ml_pitch_mm
    edge = _EdgeLattice(model, 1, float(np.median(q)), size[1], row_pitch,
                        drift=camera.odd_row_shift, origin=middle)
    first_r, last_r = edge.boundary(lo, -1), edge.boundary(hi, +1)
    even = first_r + 2 * int(round((np.median(r) - first_r) / 2))
    row = q[r == even]
    if len(row) == 0:
        raise ValueError("no spot in the middle row of the white image; check it")
    edge = _EdgeLattice(model, 0, float(even), size[0], pitch)
    first_q, last_q = edge.boundary(int(row.min()), -1), edge.boundary(int(row.max()), +1)
    seen = (last_q - first_q + 1, last_r - first_r + 1)
    if seen != (cols, rows):
        raise ValueError(
            f"the white image shows about {seen[0]} x {seen[1]} microlens images (lenses in "
            f"an even row x rows, counting those whose centre lies on the sensor) but the "
            f"camera file has {cols} x {rows} microlenses: correct [microlens_array] count = "
            "[columns, rows] in the camera file")
    origin = np.array([first_q + camera.odd_row_shift * (even - first_r), first_r])
    k = axial_to_offset(base - origin.astype(np.int64), camera.odd_row_shift)
    _check_stagger(k[ok], camera)
    return k


def _check_stagger(k: np.ndarray, camera: Camera) -> None:
    """Refuse a hexagonal camera file whose odd rows are shifted the wrong way: then most
    odd rows show a lens just before their lens 0 (or after their last) and lack the
    lens the file puts at their other end. An array that overfills the sensor may show
    both in its odd rows (one lens more than the count): either labelling then holds,
    and the lens beyond the count is not used."""
    cols = camera.ml_count[0]
    wrong, end = (-1, cols - 1) if camera.odd_row_shift > 0 else (cols, 0)
    odd = k[:, 1] % 2 == 1
    rows_odd = np.unique(k[odd, 1])
    rows_wrong = np.unique(k[odd & (k[:, 0] == wrong), 1])
    rows_end = np.unique(k[odd & (k[:, 0] == end), 1])
    half = len(rows_odd) / 2
    if len(rows_odd) and len(rows_wrong) > half and len(rows_end) <= half:
        raise ValueError(
            f"the white image's odd rows of lenses sit {-camera.odd_row_shift:+g} pitch from "
            f"the even ones, the camera file says {camera.odd_row_shift:+g}: set "
            f"[microlens_array] odd_row_shift = {-camera.odd_row_shift:g}")


class _EdgeLattice:
    """Lattice node centres along one axis, on the lattice line through the spots'
    middle, against the sensor's extent ``[-0.5, size - 0.5]`` along that axis."""

    def __init__(self, model: np.ndarray, axis: int, other: float, size: float,
                 pitch: float, drift: float = 0.0, origin: float = 0.0) -> None:
        self.model, self.axis, self.other = model, axis, other
        self.size, self.pitch = size, pitch
        self.drift, self.origin = drift, origin  # the other index moves by -drift per step

    def centre(self, k: int) -> float:
        idx = np.empty(2)
        idx[self.axis] = k
        idx[1 - self.axis] = self.other - self.drift * (k - self.origin)
        return float((idx @ self.model[:2] + self.model[2])[self.axis])

    def margin(self, k: int) -> float:
        """Distance of node ``k``'s centre inside the sensor's edge (negative: off it)."""
        c = self.centre(k)
        return min(c + 0.5, self.size - 0.5 - c)

    def boundary(self, k: int, side: int) -> int:
        """The outermost lens index from the outermost spot ``k`` on ``side`` (-1, +1)."""
        for _ in range(3):  # spots centred off the sensor are not lenses of the array
            if self.margin(k) >= 0:
                break
            k -= side
        beyond = k + side  # a lens cut by the sensor's edge, detected or not
        if 0 <= self.margin(beyond) < self.pitch / 2:
            k = beyond
        return k


def _grow_lattice(pts: np.ndarray, model: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Refit the affine model on spots within a radius (lens units) of the anchor spots,
    doubling the radius until every spot is included."""
    radius = 8.0
    while True:
        f = _fractional_index(pts, model)
        idx = np.rint(f)
        grown = np.abs(f - f[anchor].mean(0)).max(1) <= radius
        sel = grown & (np.abs(f - idx).max(1) <= 0.3)
        if sel.sum() >= 3:
            design = np.column_stack([idx[sel], np.ones(int(sel.sum()))])
            model, *_ = np.linalg.lstsq(design, pts[sel], rcond=None)
        if grown.all():
            return model
        radius *= 2


def _fractional_index(pts: np.ndarray, model: np.ndarray) -> np.ndarray:
    """Invert the affine model ``px = [kx, ky, 1] @ model`` for fractional indices."""
    return np.linalg.solve(model[:2].T, (pts - model[2]).T).T


def _whole_pitch_shift(base: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """Shift of the indices that puts the most spots inside the array (smallest wins ties)."""
    best, best_n = np.zeros(2, np.int64), -1
    for dx, dy in sorted(((a, b) for a in range(-3, 4) for b in range(-3, 4)),
                         key=lambda t: t[0] ** 2 + t[1] ** 2):
        kx, ky = base[:, 0] + dx, base[:, 1] + dy
        n = int(((kx >= 0) & (kx < cols) & (ky >= 0) & (ky < rows)).sum())
        if n > best_n:
            best, best_n = np.array([dx, dy]), n
    return best


# ---- 4. grid model ------------------------------------------------------------------
def _design(k: np.ndarray, shape: tuple[int, int], degree: int,
            stagger: bool = False) -> np.ndarray:
    """Polynomial terms of the normalised lens index, up to total ``degree``; with
    ``stagger`` (a hexagonal array) also the odd rows' own offset from the even ones
    (``ky`` odd): a real array's odd rows may sit off the camera file's half pitch (0.46
    pitch in issue 44 finding 3), which no smooth function of the position represents."""
    cols, rows = shape
    a = (k[:, 0] - (cols - 1) / 2) / max(1.0, (cols - 1) / 2)
    b = (k[:, 1] - (rows - 1) / 2) / max(1.0, (rows - 1) / 2)
    terms = [a**i * b**j for n in range(degree + 1) for j in range(n + 1) for i in [n - j]]
    if stagger:
        terms.append(np.rint(k[:, 1]) % 2)
    return np.column_stack(terms)


def _robust_fit(k, c, shape, degree, use, stagger: bool = False):
    """Least-squares polynomial fit with iterative outlier rejection; returns coef, use."""
    design = _design(k, shape, degree, stagger)
    for _ in range(5):
        coef, *_ = np.linalg.lstsq(design[use], c[use], rcond=None)
        resid = np.hypot(*(design @ coef - c).T)
        sigma = float(np.median(resid[use])) / 1.1774  # Rayleigh median -> sigma
        new = use & (resid <= max(5 * sigma, 0.02))
        if np.array_equal(new, use) or new.sum() < design.shape[1] + 2:
            break
        use = new
    return coef, use


def _choose_degree(k, c, shape, use, degree, stagger: bool = False) -> int:
    """Affine unless ``degree`` says otherwise or, for ``"auto"``, a cubic model is both
    significantly better (F-test) and differs from the affine one by a relevant amount
    (a sub-pixel-phase bias of the centroids must not pass for distortion)."""
    if degree != "auto":
        if degree not in (1, 2, 3):
            raise ValueError(f"degree must be 1, 2, 3 or 'auto', got {degree!r}")
        return int(degree)
    p1, p3 = (2 * _design(k[:1], shape, d, stagger).shape[1] for d in (1, 3))
    common = (_robust_fit(k, c, shape, 1, use, stagger)[1]
              & _robust_fit(k, c, shape, 3, use, stagger)[1])
    n = 2 * int(common.sum())
    if n <= 3 * p3:
        return 1
    rss, models = [], []
    for deg in (1, 3):
        design = _design(k, shape, deg, stagger)
        coef, *_ = np.linalg.lstsq(design[common], c[common], rcond=None)
        rss.append(float(((design[common] @ coef - c[common]) ** 2).sum()))
        models.append(design @ coef)
    if rss[1] <= 0:
        return 1
    f_stat = (rss[0] - rss[1]) / (p3 - p1) / (rss[1] / (n - p3))
    effect = float(np.sqrt(np.mean(np.sum((models[1] - models[0]) ** 2, axis=1))))
    significant = stats.f.sf(f_stat, p3 - p1, n - p3) < DISTORTION_P_VALUE
    return 3 if significant and effect > DISTORTION_MIN_PX else 1


def _grid_model(camera: Camera, c: np.ndarray, use: np.ndarray, degree):
    """The robust grid model of the centres ``c`` (``(rows·cols, 2)``, the lenses ``use``
    fitted): its degree, the lenses it kept and its ``(rows, cols, 2)`` prediction. A
    hexagonal array's model also fits its odd rows' offset (:func:`_design`)."""
    cols, rows = camera.ml_count
    kk = camera.lens_lattice_coords().reshape(-1, 2)  # affine in the lens positions
    stagger = camera.ml_layout == "hexagonal"
    deg = _choose_degree(kk, c, (cols, rows), use, degree, stagger)
    coef, use = _robust_fit(kk, c, (cols, rows), deg, use, stagger)
    return deg, use, (_design(kk, (cols, rows), deg, stagger) @ coef).reshape(rows, cols, 2)


# ---- public -------------------------------------------------------------------------
def find_centers(white_image, camera: Camera, *, method: str = "combined",
                 degree: int | str = "auto", fill_missing: bool = False,
                 aperture: str = "auto") -> CenterFit:
    """Measure every microlens image centre in a white image.

    Parameters
    ----------
    white_image
        ``(H, W)`` raw white image (8/16-bit integer or float): stopped down (one small
        spot per microlens) or at full aperture (one disk filling most of each lens).
    camera
        The camera (nominal layout); sets the expected pitch and the lens count.
    method
        ``"combined"`` (default): the grid model's prediction and the lens's own centroid
        weighted by their uncertainties (a lens that really sits off the lattice keeps its
        offset, noise is smoothed); ``"fit"``: the global grid model's prediction for
        each found lens; ``"centroid"``: each spot's own centroid (the paper's method).
        At full aperture ``"combined"`` fits each lens's disk with its neighbours'
        (touching disks' centroids carry their neighbours' offsets) and weighs that fit
        against the grid model refitted to all of them (docs/design.md §3; on lenses
        under ``PER_LENS_MIN_PITCH_PX``, or where the image shows no lens off the
        lattice and the disk fits are noisier than the centroids, the centres are
        ``"fit"``'s); ``"fit"`` is the grid model of
        the disks' centroids, the lattice alone.
    degree
        Grid-model polynomial degree: 1 (affine), 2, 3, or ``"auto"`` (affine unless
        a cubic distortion term is significant).
    fill_missing
        Give lenses without a spot the model's prediction instead of ``NaN``.
    aperture
        ``"stopped"`` (spots: windowed centroids), ``"full"`` (disks: centroids in a
        circular window, vignetting divided out) or ``"auto"`` (default: full when
        over ``FULL_APERTURE_FRACTION`` of the pixels are bright).

    Returns
    -------
    CenterFit
        Centres, raw centroids, the model and the measured layout.

    Raises
    ------
    ValueError
        When the image is not a plausible white image for this camera.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if degree != "auto" and degree not in (1, 2, 3):
        raise ValueError(f"degree must be 1, 2, 3 or 'auto', got {degree!r}")
    pitch = _pitch_px(camera)
    img = _remove_hot_pixels(_validate_image(white_image, camera), pitch)
    kind = _choose_aperture(img, pitch, aperture)
    if kind == "full":
        flat = _flatten(img, pitch)
        peaks, strength = _detect_disks(flat, pitch)
        _check_regular(peaks, "bright disks")
        _check_count(len(peaks), camera, "bright disks")
        cents, sigma, split = _disk_centroids(flat, peaks, pitch)
    else:
        peaks, strength = _detect_spots(img, pitch)
        _check_regular(peaks, "bright spots")
        _check_count(len(peaks), camera, "bright spots")
        cents, sigma, split = _windowed_centroids(img, peaks, pitch)
    ok = np.isfinite(cents).all(1)
    cents, strength, split = cents[ok], strength[ok], split[ok]
    keep = _suppress_duplicates(cents, strength, DUPLICATE_RADIUS * pitch)
    cents, split = cents[keep], split[keep]
    _check_count(len(cents), camera, "well-formed spots")
    k, dev = _match(cents, camera)
    _check_lattice(dev, "disks" if kind == "full" else "spots")
    if kind == "full" and method == "combined":  # the disks' centroids: the lattice only
        per_lens, method = pitch >= PER_LENS_MIN_PITCH_PX, "fit"
    else:
        per_lens = False
    fit = _assemble(camera, cents, split, k, dev, sigma, img.shape, method, degree,
                    fill_missing, interior=kind == "full")
    if kind == "full" and method != "centroid":
        fit = _cut_by_the_edge(fit, flat)
    if per_lens:  # the lattice is the prior; each lens's own disk says where it is
        fit = _follow_lenses(fit, img, camera, degree, fill_missing)
    return dataclasses.replace(fit, aperture=kind)



def _follow_lenses(prior: CenterFit, img: np.ndarray, camera: Camera, degree,
                   fill_missing: bool) -> CenterFit:
    """Full aperture, ``method="combined"``: every lens's disk fitted in the image
    (:func:`plenocl.lenscentres.fit_disks`, started from the lattice model), the smooth
    grid model refitted to those fits (of the lenses whose neighbours were all found:
    a disk the sensor's edge cuts is fitted less surely), and each centre moved from the
    model toward its own fit by their uncertainties (:func:`_combine`): lenses cut by the
    sensor's edge or with too little light keep the model. Where the image shows no lens
    off the lattice and the fits are no surer than the centroids
    (:func:`_lattice_suffices`), the centres are the centroids' lattice."""
    cols, rows = camera.ml_count
    h, w = img.shape
    c = prior.model
    on = (c[..., 0] >= 0) & (c[..., 0] <= w - 1) & (c[..., 1] >= 0) & (c[..., 1] <= h - 1)
    disks = fit_disks(img, prior.model, _pitch_px(camera), lit=prior.found | ~on)
    local, noise = disks.centres, np.where(np.isfinite(disks.sigma), disks.sigma, np.nan)
    measured = prior.found & np.isfinite(noise)
    inner = measured & _surrounded(prior.found, camera, rings=1)
    fitted = inner if inner.sum() >= MIN_INTERIOR else measured  # disks the edge cuts: biased
    deg, use, model = _grid_model(camera, local.reshape(-1, 2), fitted.ravel(), degree)
    inlier = use.reshape(rows, cols) & measured
    if _lattice_suffices(prior, local, model, inlier):
        deg, model, scatter, trusted = prior.degree, prior.model, 0.0, np.zeros_like(inlier)
    else:
        scatter = _lattice_scatter(local, model, noise, inlier)
        trusted = _trusted(local, model, noise, scatter, inlier, measured) & measured
    centers = _combine(model, local, np.nan_to_num(noise, nan=np.inf), scatter, trusted)
    centers[~prior.found] = model[~prior.found] if fill_missing else np.nan
    local[~measured] = np.nan
    resid = np.hypot(*(local - model)[inlier].T)
    return CenterFit(centers, local, model, prior.found, inlier, deg, *_layout(model, camera),
                     float(np.sqrt(np.mean(resid**2))), "combined", noise, scatter)


#: Significance (standard deviations of a null correlation, ``1/√n``) that the disk fits'
#: and the centroids' offsets from the lattice must share before the lenses' own offsets
#: are followed.
DEVIATION_SIGNIFICANCE = 3.0


def _lattice_suffices(prior: CenterFit, local: np.ndarray, model: np.ndarray,
                      inlier: np.ndarray) -> bool:
    """Whether the centroids' lattice (``prior``) is kept as it is: the image shows no
    lens off the lattice (:func:`_lenses_deviate`) and the disks' centroids scatter about
    their lattice no more than the disk fits (``local``) about the model refitted to them
    (soft, noisy disks; on sharp touching disks the fits are the surer, their model
    stays)."""
    if _lenses_deviate(local - model, prior.centroids - prior.model, inlier):
        return False
    return _rms_offset(prior.centroids, prior.model, prior.inlier) <= _rms_offset(
        local, model, inlier)


def _rms_offset(points: np.ndarray, model: np.ndarray, use: np.ndarray) -> float:
    """RMS (px, per axis) of ``points`` about ``model`` over the lenses ``use``."""
    d = (points - model)[use & np.isfinite(points).all(-1)]
    return float(np.sqrt(np.mean(d**2))) if d.size else np.inf


def _lenses_deviate(own: np.ndarray, centroid: np.ndarray, inlier: np.ndarray) -> bool:
    """Whether the image shows lenses really off the lattice: two independent estimates
    of each ``inlier`` lens's offset, its disk fit's from the model refitted to the fits
    (``own``) and its centroid's from the centroids' lattice (``centroid``), correlate
    beyond chance (``DEVIATION_SIGNIFICANCE / √n``). Their errors hardly correlate (the
    centroid weighs the whole disk, the fit mostly its edge; measured ρ -0.09 and 0.08 on
    exact lattices against 0.86 and 0.40 with 0.2 and 0.05 px jitter), so a real offset
    of the lenses shows however far the fits' noise exceeds their stated deviations."""
    a, b = own[inlier].ravel(), centroid[inlier].ravel()
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3:
        return False
    a, b = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    rho = float(a @ b) / np.sqrt(max(float(a @ a) * float(b @ b), 1e-300))
    return rho * np.sqrt(ok.sum()) > DEVIATION_SIGNIFICANCE


def _cut_by_the_edge(fit: CenterFit, flat: np.ndarray) -> CenterFit:
    """At full aperture, a lens whose centre lies on the sensor but whose disk the
    sensor's edge cuts too much to be detected is still lit: where the flattened image
    is bright at the model's centre, the lens is found, at the model's centre (the
    centres there are the model's anyway)."""
    h, w = flat.shape
    c = np.rint(fit.model).astype(np.int64)
    on = (c[..., 0] >= 0) & (c[..., 0] < w) & (c[..., 1] >= 0) & (c[..., 1] < h)
    lit = np.zeros_like(on)
    lit[on] = flat[c[..., 1][on], c[..., 0][on]] > 0.5
    cut = ~fit.found & lit
    if not cut.any():
        return fit
    centers = fit.centers.copy()
    centers[cut] = fit.model[cut]
    return dataclasses.replace(fit, centers=centers, found=fit.found | cut)


#: Of a white image's spots, at least half lie within this many pitches of their lattice
#: node (real arrays: a few hundredths; maxima of noise or of a particle image: scattered).
ON_LATTICE = 0.1


def _check_lattice(dev: np.ndarray, what: str) -> None:
    """Refuse spots that do not form a lattice: ``dev`` is each one's distance (pitches)
    from its node (:func:`_match`)."""
    share = float(np.mean(dev <= ON_LATTICE))
    if share < 0.5:
        raise ValueError(
            f"the {len(dev)} {what} found do not lie on a lattice (only {share:.0%} within "
            f"{ON_LATTICE:g} pitch of a node): this does not look like a white image. Image "
            "a uniform bright target with the main lens stopped down (e.g. f/16) or at full "
            "aperture, and check the exposure and the camera file's pitch")


def _check_regular(peaks: np.ndarray, what: str) -> None:
    """Refuse spots that are not spaced like a lattice's, whatever its pitch: a white
    image's spots have their nearest neighbour one pitch away; a particle image's lie in
    clusters (one per particle) at spacings that vary with each particle's depth."""
    if len(peaks) < 8:
        return  # too few to judge: the count check names the problem
    dist = cKDTree(peaks).query(peaks, k=2)[0][:, 1]
    typical = float(np.median(dist))
    share = float(np.mean(np.abs(dist / typical - 1) <= REGULAR_SPREAD))
    if share < REGULAR_SHARE:
        raise ValueError(
            f"this does not look like a white image: the {len(peaks)} {what} found are "
            f"irregularly spaced (only {share:.0%} have their nearest neighbour within "
            f"{REGULAR_SPREAD:.0%} of the typical {typical:.3g} px, where a white image's "
            "lie on the microlens lattice): a particle image? Calibrate with a white image "
            "of a uniform bright target, the main lens stopped down (e.g. f/16) or at full "
            "aperture")


def _check_count(n: int, camera: Camera, what: str) -> None:
    """Refuse an image with far fewer spots than the camera has lenses on the sensor."""
    nominal = camera.ideal_microlens_centers().reshape(-1, 2)
    w, h = camera.pixels
    expected = int(((nominal >= 0).all(1) & (nominal[:, 0] < w) & (nominal[:, 1] < h)).sum())
    if n < max(4, MIN_FOUND_FRACTION * expected):
        raise ValueError(
            f"found only {n} {what} where the camera expects {expected} microlens images: "
            "this does not look like a white image. Image a uniform bright target with the "
            "main lens stopped down (e.g. f/16: one small spot per lens) or at full aperture "
            "(one disk filling each lens; aperture='full', --aperture full, if the automatic "
            "choice missed it), and check the exposure and the camera file")


def _lens_grid(camera: Camera, per_spot: np.ndarray, k: np.ndarray,
               dev: np.ndarray) -> np.ndarray:
    """Scatter per-spot values ``(N, 2)`` into ``(rows, cols, 2)`` (``NaN``: no spot); of
    two spots matched to one lens the one nearer its lattice node wins."""
    cols, rows = camera.ml_count
    grid = np.full((rows, cols, 2), np.nan)
    order = np.argsort(dev, kind="stable")
    per_spot, k = per_spot[order], k[order]
    ok = k[:, 0] >= 0
    flat = k[ok, 1] * cols + k[ok, 0]
    uniq, first = np.unique(flat, return_index=True)
    grid.reshape(-1, 2)[uniq] = per_spot[ok][first]
    return grid


def _assemble(camera, cents, split, k, dev, sigma, shape, method, degree,
              fill_missing, interior: bool = False) -> CenterFit:
    """The grid model, the noise and scatter, and the centres (``interior``: the model is
    fitted to the lenses whose neighbours all have a spot, see :func:`_surrounded`)."""
    cols, rows = camera.ml_count
    grid = _lens_grid(camera, cents, k, dev)
    found = np.isfinite(grid).all(-1)
    c = grid.reshape(-1, 2)
    margin = 3 * sigma + 1
    h, w = shape
    use = found.ravel() & (c[:, 0] > margin) & (c[:, 1] > margin)
    use &= (c[:, 0] < w - 1 - margin) & (c[:, 1] < h - 1 - margin)
    if use.sum() < 6:
        use = found.ravel().copy()
    if interior:
        inner = use & _surrounded(found, camera, rings=2).ravel()
        use = inner if inner.sum() >= MIN_INTERIOR else use
    deg, use, model = _grid_model(camera, c, use, degree)
    found = _drop_far_spots(found, grid, model, _pitch_px(camera))
    grid[~found] = np.nan
    inlier = use.reshape(rows, cols) & found
    noise = _centroid_noise(_lens_grid(camera, split, k, dev), found)
    scatter = _lattice_scatter(grid, model, noise, inlier)
    combined = _combine(model, grid, noise, scatter, _trusted(grid, model, noise, scatter,
                                                                inlier, found))
    centers = {"fit": model, "centroid": grid, "combined": combined}[method].copy()
    centers[~found] = model[~found] if fill_missing else np.nan
    resid = np.hypot(*(grid - model).reshape(-1, 2)[use].T)
    return CenterFit(centers, grid, model, found, inlier, deg, *_layout(model, camera),
                     float(np.sqrt(np.mean(resid**2))), method, noise, scatter)


def _centroid_noise(split: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Per-lens centroid noise (px, per axis), ``(rows, cols)``: the split differences
    (``E|d|² = 8 σ²`` over both axes) averaged over each lens's 5 x 5 neighbourhood, so
    that it follows vignetting and exposure across the array without one spot's luck."""
    d2 = np.where(found, np.nansum(split**2, axis=-1), 0.0)
    n = ndimage.uniform_filter(found.astype(float), 5, mode="nearest")
    mean = ndimage.uniform_filter(d2, 5, mode="nearest") / np.maximum(n, 1e-12)
    return np.sqrt(mean / 8.0)


def _lattice_scatter(grid, model, noise, inlier) -> float:
    """RMS (px, per axis) of the lenses' true offsets from the grid model: the centroids'
    scatter about the model with their noise taken out (0 when noise explains it all)."""
    if not inlier.any():
        return 0.0
    resid2 = ((grid - model)[inlier] ** 2).sum(-1) / 2
    return float(np.sqrt(max(float(np.mean(resid2) - np.mean(noise[inlier] ** 2)), 0.0)))


def _trusted(grid, model, noise, scatter: float, inlier, found) -> np.ndarray:
    """The spots whose centroids may move their centres: the fit's inliers, and the other
    found spots (near the sensor's edge, or outliers of the fit) whose offset from the
    model stays within 3 standard deviations of what displacement and noise explain. A
    spot cut by the sensor's edge has a biased centroid (measured: 0.6 px on a 2-degree
    array) and a blemish moves one: those keep the model."""
    r2 = np.nansum((grid - model) ** 2, axis=-1)
    return inlier | (found & (r2 <= 9 * 2 * (scatter**2 + noise**2)))


def _combine(model, grid, noise, scatter: float, trusted) -> np.ndarray:
    """Each lens's centre from the grid model and its own centroid, weighted by their
    uncertainties: ``model + w (centroid - model)`` with ``w = τ² / (τ² + σ_k²)`` (τ: the
    lenses' true scatter about the lattice, σ_k: the centroid's noise). Lenses that
    really sit off the lattice keep their offset; noise-level scatter is smoothed away.
    Only ``trusted`` spots move (not the fit's outliers: a blemish or a stray spot)."""
    w = scatter**2 / np.maximum(scatter**2 + noise**2, 1e-30)
    return model + np.where(trusted, w, 0.0)[..., None] * np.nan_to_num(grid - model)


#: Lenses with every neighbour found needed before a full-aperture grid model leaves the
#: array's outer lenses out of its fit.
MIN_INTERIOR = 12


def _surrounded(found: np.ndarray, camera: Camera, rings: int = 1) -> np.ndarray:
    """``(rows, cols)``: found lenses whose every lattice neighbour (4 in a rectangular
    array, 6 in a hexagonal one) lies in the array and was found, ``rings`` deep (2: the
    neighbours' neighbours too). A full-aperture disk's window takes in slivers of its
    neighbours' disks, symmetric about an inner lens but one-sided at the array's edge
    (0.35 px there at 65 px per lens, rectangular; 2-4 px hexagonal, where the slivers
    pull the window along), so the model is fitted to the inner lenses and predicts the
    outer ones."""
    xy = camera.lens_lattice_coords() * [1.0, camera.ml_row_pitch_mm / camera.ml_pitch_mm]
    flat = xy.reshape(-1, 2)
    want = 6 if camera.ml_layout == "hexagonal" else 4
    # each lens and its neighbours; a missing neighbour (beyond the array) is index n
    dist, near = cKDTree(flat).query(flat, k=want + 1, distance_upper_bound=1.01)
    complete = np.isfinite(dist).all(1)
    ok = found.ravel()
    for _ in range(rings):
        ok = complete & np.append(ok, False)[near].all(1)  # near holds the lens itself
    return ok.reshape(found.shape)


def _drop_far_spots(found, grid, model, pitch) -> np.ndarray:
    """Spots far from the model (a hot pixel, a stray reflection) are not that lens's."""
    dist = np.hypot(*(grid - model).transpose(2, 0, 1))
    return found & ~(dist > 0.25 * pitch)


def _layout(model: np.ndarray, camera: Camera) -> tuple:
    """Rotation (deg), pitch along the array axes (px) and shift of the array centre."""
    ax = np.nanmean(np.diff(model, axis=1), axis=(0, 1))
    ay = np.nanmean(np.diff(model, axis=0), axis=(0, 1))  # hexagonal: the mean row step
    if camera.ml_layout == "hexagonal":
        rot = math.degrees(math.atan2(ax[1], ax[0]))
    else:
        rot = math.degrees(math.atan2(ax[1] - ay[0], ax[0] + ay[1]))
    shift = model.reshape(-1, 2).mean(0) - camera.ideal_microlens_centers().reshape(-1, 2).mean(0)
    return rot, (float(np.hypot(*ax)), float(np.hypot(*ay))), (float(shift[0]), float(shift[1]))


def calibrate(white_image, camera: Camera, *, diagnostic_png: str | Path | None = None,
              method: str = "combined", degree: int | str = "auto",
              fill_missing: bool = False, aperture: str = "auto") -> Camera:
    """Calibrate the microlens image centres of ``camera`` from a white image.

    Parameters
    ----------
    white_image
        ``(H, W)`` raw white image (8/16-bit integer or float) taken with the main lens
        stopped down (one small spot per microlens) or at full aperture (one disk per
        microlens, as camera vendors supply them).
    camera
        The camera with its nominal layout (rotation and offset may be unknown).
    diagnostic_png
        Optional path of a PNG overlaying the found centres on the image; written also
        when calibration fails, then showing what was found (spots, the nominal array).
    method, degree, fill_missing, aperture
        See :func:`find_centers`.

    Returns
    -------
    Camera
        A copy with ``microlens_centers`` ``(rows, cols, 2)`` as ``(col, row)`` px and
        ``calibrated=True``; ``NaN`` marks lenses without a spot (warned about).

    Raises
    ------
    ValueError
        When the image is not a plausible white image for this camera.
    """
    try:
        fit = find_centers(white_image, camera, method=method, degree=degree,
                           fill_missing=fill_missing, aperture=aperture)
    except ValueError as exc:
        if diagnostic_png is not None:  # what was found: when it helps most
            save_failure_diagnostic(diagnostic_png, white_image, camera, str(exc))
        raise
    warn_about(fit)
    if diagnostic_png is not None:
        save_diagnostic(diagnostic_png, white_image, fit)
    return camera.with_centers(fit.centers)


#: Imported centres must lie within this many pitches (median) of the camera's nominal
#: lattice: farther, the file and the camera describe different arrays.
IMPORT_TOLERANCE = 0.5


def import_centers(path: str | Path, camera: Camera) -> Camera:
    """``camera`` calibrated with the centres of a centres CSV or of LFIT's ``.mat``
    calibration (another tool's; formats in :mod:`plenocl.io.centres`), checked against
    the camera's
    nominal layout: refused when they lie, in the median, more than
    :data:`IMPORT_TOLERANCE` pitches from its lattice (swapped x and y, indices counted
    from 1, another camera file), since every later stage would then see the wrong
    lenses."""
    centers = read_centres(path, camera.ml_count)
    found = np.isfinite(centers).all(-1)
    off = np.hypot(*(centers - camera.ideal_microlens_centers())[found].T) / _pitch_px(camera)
    if float(np.median(off)) > IMPORT_TOLERANCE:
        raise ValueError(f"the centres in {path} lie {float(np.median(off)):.2f} pitches "
                         "(median) from the camera's nominal lattice: check that x_px is the "
                         "column and y_px the row, that lens indices count from 0, and that "
                         "the camera file's pitch, count, rotation and offset are this "
                         "camera's")
    missing = int((~found).sum())
    if missing:
        warnings.warn(f"{missing} of {found.size} microlenses have no centre in {path} "
                      "(NaN: their pixels are not used)", stacklevel=2)
    return camera.with_centers(centers)


def warn_about(fit: CenterFit) -> None:
    """Warn about missing lenses and a noisy or distorted fit (what :func:`calibrate` and
    ``plenocl calibrate`` say besides the centres)."""
    total = fit.found.size
    if fit.n_missing:
        fate = "use the grid model's prediction" if np.isfinite(fit.centers).all() else \
            ("are NaN (fill_missing=True, plenocl calibrate --fill-missing, gives them the "
             "grid model's prediction)")
        warnings.warn(f"calibration found no spot for {fit.n_missing} of {total} microlenses "
                      f"(dead, occluded or off the sensor); their centres {fate}", stacklevel=3)
    if fit.residual_rms_px > 0.25:
        warnings.warn(f"the spot centroids scatter by {fit.residual_rms_px:.2f} px RMS about the "
                      f"grid model: the white image is noisy or the array distorted; check the "
                      "diagnostic image (plenocl calibrate --diagnostic FILE.png, or "
                      "calibrate(..., diagnostic_png=...))", stacklevel=3)


def save_diagnostic(path: str | Path, white_image, fit: CenterFit) -> None:
    """Write a PNG: the white image with the found centres (green) and missing lenses
    (red), and the residual map, each lens's centroid offset from the grid model (px),
    colour for its size and an arrow for its direction, with the estimated centroid
    noise and lattice scatter in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    img = np.asarray(white_image, dtype=np.float64)
    fig, (ax, res) = plt.subplots(1, 2, figsize=(13, 6.8), dpi=130)
    rows, cols = fit.found.shape
    c = fit.centers[fit.found]
    miss = fit.model[~fit.found]
    half = _zoom_panel(ax, img, np.nanmean(fit.model.reshape(-1, 2), 0),
                       float(np.mean(fit.pitch_px)))
    ax.plot(c[:, 0], c[:, 1], "x", color="lime", ms=7, mew=1.0, label="centres")
    ax.plot(miss[:, 0], miss[:, 1], "o", mfc="none", color="red", ms=9, mew=1.0,
            label=f"no spot ({fit.n_missing} in all)")
    ax.set_title(f"central {2 * half} x {2 * half} lenses of {cols} x {rows}: "
                 f"{int(fit.found.sum())} centres found in all, rotation "
                 f"{fit.rotation_deg:.3f}°", fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    _residual_panel(fig, res, fit)
    _save_figure(fig, path)


def _zoom_panel(ax, img: np.ndarray, centre, pitch: float, half: int = 6) -> int:
    """The image around ``centre`` (``half`` lenses each way, so that single spots and
    crosses stay readable on any array), square-root scaled; returns ``half``."""
    h, w = img.shape
    x0, x1 = max(centre[0] - half * pitch, -0.5), min(centre[0] + half * pitch, w - 0.5)
    y0, y1 = max(centre[1] - half * pitch, -0.5), min(centre[1] + half * pitch, h - 0.5)
    ax.imshow(np.sqrt(np.clip(img, 0, None) / max(img.max(), 1e-30)), cmap="gray",
              interpolation="nearest")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    return half


def _save_figure(fig, path) -> None:
    import matplotlib.pyplot as plt

    from .io.atomic import atomic_path

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def save_failure_diagnostic(path: str | Path, white_image, camera: Camera,
                            message: str) -> None:
    """Write a PNG of what a calibration that failed saw: the whole image with the bright
    spots found and the outline of the array the camera file describes, and the centre
    enlarged with the spots (green) and the camera's nominal centres (red), the reason
    in the title. It shows a wrong pitch, count, rotation or a white image that is not
    one at a glance."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = np.asarray(white_image, dtype=np.float64)
    pitch = _pitch_px(camera)
    try:
        peaks = _detect_spots(_remove_hot_pixels(img, pitch), pitch)[0]
    except (ValueError, IndexError):
        peaks = np.empty((0, 2))
    nominal = camera.ideal_microlens_centers().reshape(-1, 2)
    fig, (whole, zoom) = plt.subplots(1, 2, figsize=(13, 7.2), dpi=110)
    whole.imshow(np.sqrt(np.clip(img, 0, None) / max(img.max(), 1e-30)), cmap="gray")
    lo, hi = nominal.min(0) - pitch / 2, nominal.max(0) + pitch / 2
    whole.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]],
               color="red", lw=1, label="the camera file's array")
    whole.legend(loc="upper right", fontsize=7)
    whole.set_title(f"{len(peaks)} bright spots found; the camera file expects "
                    f"{camera.ml_count[0]} x {camera.ml_count[1]} lenses {pitch:.2f} px "
                    "apart", fontsize=9)
    _zoom_panel(zoom, img, np.array(img.shape[::-1]) / 2 - 0.5, pitch)
    zoom.plot(peaks[:, 0], peaks[:, 1], "+", color="lime", ms=8, label="spots found")
    zoom.plot(nominal[:, 0], nominal[:, 1], "o", mfc="none", color="red", ms=8,
              label="nominal centres")
    zoom.legend(loc="upper right", fontsize=7)
    fig.suptitle("calibration failed: " + "\n".join(textwrap.wrap(message, 150)),
                 fontsize=8)
    _save_figure(fig, path)


def _residual_panel(fig, ax, fit: CenterFit) -> None:
    """Each lens's centroid minus the grid model, on the lens grid (rows x columns)."""
    offset = np.where(fit.found[..., None], fit.centroids - fit.model, np.nan)
    size = np.hypot(offset[..., 0], offset[..., 1])
    top = max(float(np.nanpercentile(size, 99)) if np.isfinite(size).any() else 0.0, 1e-3)
    im = ax.imshow(size, cmap="viridis", vmin=0, vmax=top, interpolation="nearest")
    rows, cols = size.shape
    if rows * cols <= 4000:  # arrows stay readable up to ~60 x 60 lenses
        ky, kx = np.mgrid[0:rows, 0:cols]
        ax.quiver(kx, ky, offset[..., 0], -offset[..., 1], color="white", angles="xy",
                  scale_units="xy", scale=top / 0.45, width=0.003)
    out = fit.found & ~fit.inlier
    ax.plot(*np.nonzero(out.T), "s", mfc="none", color="orange", ms=4, mew=0.6,
            label=f"left out of the fit ({int(out.sum())})")
    if out.any():
        ax.legend(loc="upper right", fontsize=7)
    ax.set_xlabel("lens column kx")
    ax.set_ylabel("lens row ky")
    ax.set_title(f"centroid - grid model: {fit.residual_rms_px:.3f} px RMS (centres: "
                 f"{fit.method})\ncentroid noise {float(np.nanmedian(fit.noise_px)):.3f} px, "
                 f"lenses' scatter about the lattice {fit.lattice_scatter_px:.3f} px (per axis)",
                 fontsize=8)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, label="offset (px)")
