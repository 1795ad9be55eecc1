"""Step 1 and 2 of a stopped-down white image (docs/design.md §3): the spots detected
(hot pixels removed, a local floor), then centroided with a Gaussian window iterated to
convergence, each spot's background the median of a ring between the spots."""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .checks import odd_size

#: Peaks (and centroids) closer than this many pitches are one spot.
DUPLICATE_RADIUS = 0.25

#: A spot must reach this fraction of the brightest spot around it.
RELATIVE_THRESHOLD = 0.25

#: Width of the Gaussian centroid window: this many spot widths, at least WINDOW_MIN_PX
#: (a narrower window samples a sub-pixel spot too coarsely: 1 px biased 0.5 px spots by
#: 0.024 px toward the pixel grid, 1.5 px by 0.009).
WINDOW_SCALE = 1.5
WINDOW_MIN_PX = 1.5


def local_floor(img: np.ndarray, pitch: float) -> np.ndarray:
    """Local background: the minimum over one pitch (the gaps between spots), smoothed."""
    return ndimage.uniform_filter(ndimage.minimum_filter(img, odd_size(pitch)), odd_size(pitch))


def remove_hot_pixels(img: np.ndarray, pitch: float) -> np.ndarray:
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
    height = ndimage.maximum_filter(img - local_floor(img, pitch), odd_size(pitch))
    typical = max(float(np.median(height)), 0.0)
    hot = excess > 2 * typical + 8 * noise
    return np.where(hot, med, img) if hot.any() else img


def detect_spots(img: np.ndarray, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer ``(col, row)`` positions of spot peaks and their strengths.

    Peaks closer than a third of the expected pitch are resolved, so spots on a finer
    lattice than the camera predicts are seen (and refused) rather than thinned out.
    The background is local (the minimum over one pitch, i.e. the gaps between spots,
    smoothed), so a background gradient or wide spots do not raise the threshold.
    """
    smooth = ndimage.gaussian_filter(img, max(1.0, 0.06 * pitch))
    bg = local_floor(smooth, pitch)
    resid = smooth - bg
    noise = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    peak = ndimage.maximum_filter(smooth, odd_size(0.35 * pitch))
    nearby = ndimage.maximum_filter(peak - bg, odd_size(2.5 * pitch))
    floor = 0.02 * float(np.percentile(peak - bg, 99.0))
    thr = bg + np.maximum(np.maximum(8 * noise, floor), RELATIVE_THRESHOLD * nearby)
    rows, cols = np.nonzero((smooth == peak) & (smooth > thr))
    pts = np.column_stack([cols, rows])
    strength = smooth[rows, cols]
    keep = suppress_duplicates(pts, strength, DUPLICATE_RADIUS * pitch)
    return pts[keep], strength[keep]


def suppress_duplicates(pts: np.ndarray, strength: np.ndarray, radius: float) -> np.ndarray:
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


def patches(padded: np.ndarray, pad: int, centre: np.ndarray, half: int):
    """Patches ``(N, 2h+1, 2h+1)`` of the padded image around integer centres."""
    off = np.arange(-half, half + 1)
    cols = centre[:, 0, None, None] + off[None, None, :] + pad
    rows = centre[:, 1, None, None] + off[None, :, None] + pad
    return padded[rows, cols], off


def _local_background(padded, pad, peaks, pitch) -> np.ndarray:
    """Median of a ring halfway between neighbouring spots, per spot."""
    half = max(2, int(0.45 * pitch))
    patch, off = patches(padded, pad, peaks, half)
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


def windowed_centroids(img: np.ndarray, peaks: np.ndarray, pitch: float,
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
    patch, off = patches(padded, pad, peaks, half)
    sigma = max(0.5, _spot_sigma(np.nan_to_num(patch - bg[:, None, None]), off))
    width = max(WINDOW_MIN_PX, WINDOW_SCALE * sigma)
    half = max(2, min(int(0.45 * pitch), int(math.ceil(4 * width))))
    gain = 1.0 + sigma**2 / width**2
    c = settle(lambda at, which: centroid_step(padded, pad, at, bg[which], half, width, gain),
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
    return split_halves(
        lambda at, lines: centroid_step(padded, pad, at, bg, half, width, gain, lines), c)


def settle(step, peaks: np.ndarray, pitch: float, iterations: int) -> np.ndarray:
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


def split_halves(step, c: np.ndarray) -> np.ndarray:
    """The ``col`` centroid from the even rows minus that from the odd rows, and the
    ``row`` centroid from the even minus the odd columns, ``(N, 2)`` (``NaN`` where ``c``
    is lost), by ``step(centres, lines) -> (moves, ok)`` (:func:`half_lines`)."""
    lost = ~np.isfinite(c).all(1)
    at = np.where(lost[:, None], 0.0, c)
    diff = np.empty_like(at)
    for axis in (0, 1):  # rows split for the col centroid, columns for the row centroid
        halves = [step(at, (1 - axis, parity))[0] for parity in (0, 1)]
        diff[:, axis] = halves[0][:, axis] - halves[1][:, axis]
    diff[lost] = np.nan
    return diff


def half_lines(signal: np.ndarray, base: np.ndarray, off: np.ndarray,
                lines: tuple[int, int] | None) -> np.ndarray:
    """Patches ``signal`` ``(N, rows, cols)`` around ``base`` keeping only the pixels
    whose column (``lines = (0, parity)``) or row (``(1, parity)``) index has ``parity``;
    all of them for ``lines=None``."""
    if lines is None:
        return signal
    axis, parity = lines
    keep = (base[:, axis, None] + off[None, :]) % 2 == parity  # (N, 2h+1)
    return np.where(keep[:, None, :] if axis == 0 else keep[:, :, None], signal, 0.0)


def centroid_step(padded, pad, c, bg, half, width, gain,
                   lines: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One Gaussian-windowed centroid update ``(N, 2)`` and which spots still have signal
    (from the pixels whose column (``lines = (0, parity)``) or row (``(1, parity)``) index
    has ``parity`` only, when given)."""
    base = np.rint(c).astype(np.int64)
    patch, off = patches(padded, pad, base, half)
    signal = half_lines(np.nan_to_num(patch - bg[:, None, None]), base, off, lines)
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
