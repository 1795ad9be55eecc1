"""Peaks with sub-voxel positions: the three-point Gaussian fit (correlation peaks in
:mod:`plenocl.piv`) and a volume's particles as local maxima (used by the reconstruction
metrics and by the particle refinement of :mod:`plenocl.piv.refinement`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .opencl.volume import DeviceVolume, host_volume

__all__ = ["find_particles", "gaussian_subpixel", "host_maxima"]


def gaussian_subpixel(c_minus: np.ndarray, c0: np.ndarray, c_plus: np.ndarray) -> np.ndarray:
    """Three-point Gaussian peak offset in ``[-0.5, 0.5]``; parabolic where a value is <= 0.

    The Gaussian fit needs the logarithm of all three samples; where any is non-positive
    (or the log-curvature is not negative) the parabolic three-point fit is used instead.
    """
    cm, cc, cp = (np.asarray(c, np.float64) for c in (c_minus, c0, c_plus))
    positive = (cm > 0) & (cc > 0) & (cp > 0)
    lm, lc, lp = (np.log(np.where(positive, c, 1.0)) for c in (cm, cc, cp))
    den_g = 2.0 * (lm - 2.0 * lc + lp)
    den_p = 2.0 * (cm - 2.0 * cc + cp)
    use_g = positive & (den_g < 0)
    offset = np.where(use_g, (lm - lp) / np.where(use_g, den_g, -1.0),
                      np.where(den_p < 0, (cm - cp) / np.where(den_p < 0, den_p, -1.0), 0.0))
    return np.clip(offset, -0.5, 0.5)


#: With ``reference="robust"``: the share of the brightest candidate peaks (those above
#: :data:`CANDIDATE` of the maximum) set aside before the reference level is read, and
#: the fewest set aside (while another candidate remains).
ROBUST_SHARE = 0.005
ROBUST_MIN = 2
#: Candidate peaks of the robust reference: above this fraction of the volume's maximum.
CANDIDATE = 0.01


def find_particles(vol: np.ndarray, threshold: float = 0.1, min_separation: int = 1,
                   reference: str = "max", maxima: Callable | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima above ``threshold`` times a reference level, with sub-voxel positions.

    ``reference="max"``: the volume's maximum. ``"robust"``: the brightest local maximum
    left once the brightest :data:`ROBUST_SHARE` (at least :data:`ROBUST_MIN`) of those
    above :data:`CANDIDATE` of the maximum are set aside, so that a few spuriously bright
    voxels (overlapping particles, crossing lines of sight in a densely seeded volume) do
    not hide the rest. At the paper's optics with 0.2 particles per microlens a maximum
    30 times the typical particle's kept 40-136 peaks of about 1,200 particles
    (design.md §7.3).

    ``maxima``: where the local maxima are found, a function of ``(vol, floor,
    min_separation)`` as :func:`host_maxima` (the default;
    :class:`plenocl.piv.devicepeaks.DeviceMaxima` on a device, the same maxima).

    ``vol`` may be a :class:`plenocl.opencl.volume.DeviceVolume`: its maximum and the
    peaks' neighbourhoods are then read on its device (and the maxima there too with a
    device's ``maxima``), the same particles as of its host copy.

    Returns fractional voxel indices ``(N, 3)`` as ``(ix, iy, iz)`` and peak values,
    brightest first. Positions use a three-point Gaussian fit along each axis.
    """
    if reference not in ("max", "robust"):
        raise ValueError(f"reference must be 'max' or 'robust', got {reference!r}")
    v = vol if isinstance(vol, DeviceVolume) else np.asarray(vol, np.float32)
    if v.ndim != 3:
        raise ValueError(f"expected a 3-D volume, got shape {v.shape}")
    vmax = _maximum(v)
    if vmax <= 0:
        return np.zeros((0, 3)), np.zeros(0)
    # every level below is above this floor (the robust level exceeds CANDIDATE * vmax)
    floor = vmax * (CANDIDATE * min(threshold, 1.0) if reference == "robust" else threshold)
    flat = (maxima or _host_maxima)(v, floor - abs(floor) * 1e-6, min_separation)
    near = _neighbourhoods(v, flat)  # (n, 7): the voxel, then x -/+, y -/+, z -/+
    values = near[:, 0]
    level = vmax
    if reference == "robust":
        bright = np.sort(values[values > CANDIDATE * vmax])[::-1]
        aside = max(ROBUST_MIN, int(np.ceil(ROBUST_SHARE * len(bright))))
        level = float(bright[min(aside, len(bright) - 1)])
    keep = values > threshold * level
    iz, iy, ix = np.unravel_index(flat[keep], v.shape)
    vals, near = values[keep], near[keep]
    out = np.empty((len(vals), 3))
    for k, pos in enumerate((ix, iy, iz)):
        out[:, k] = pos + gaussian_subpixel(near[:, 1 + 2 * k], vals, near[:, 2 + 2 * k])
    order = np.argsort(-vals)
    return out[order], vals[order]


def _maximum(v) -> float:
    """The volume's maximum as NumPy gives it (a :class:`DeviceVolume`'s found on the
    device where it is finite, :meth:`DeviceVolume.maximum`), at most 0 for an empty
    volume."""
    if isinstance(v, DeviceVolume):
        return v.maximum()
    return float(v.max()) if v.size else 0.0


def _host_maxima(v, floor: float, reach: int = 1) -> np.ndarray:
    """:func:`host_maxima` of a host volume, or of a :class:`DeviceVolume` copied to the
    host."""
    return host_maxima(host_volume(v), floor, reach)


def _neighbourhoods(v, flat: np.ndarray) -> np.ndarray:
    """``(n, 7)`` float32: the voxels at the C-order indices ``flat`` and their face
    neighbours (x - 1, x + 1, y - 1, y + 1, z - 1, z + 1), 0 beyond the volume's faces
    (as a zero-padded copy would give, without making one: 34 MB at the paper's grid);
    a :class:`DeviceVolume`'s read on the device (only these come to the host)."""
    if isinstance(v, DeviceVolume):
        return v.neighbourhoods(flat)
    centre = np.unravel_index(np.asarray(flat, np.int64), v.shape)
    near = [v[centre]]
    for axis in (2, 1, 0):
        near += [_beside(v, centre, axis, step) for step in (-1, 1)]
    return np.stack(near, axis=1).astype(np.float32, copy=False)


def _beside(v: np.ndarray, centre: tuple, axis: int, step: int) -> np.ndarray:
    """The voxels ``step`` along ``axis`` from the voxels ``centre`` (index arrays
    ``(iz, iy, ix)``) of ``v``, 0 beyond its faces."""
    index = list(centre)
    index[axis] = centre[axis] + step
    inside = (index[axis] >= 0) & (index[axis] < v.shape[axis])
    index[axis] = np.clip(index[axis], 0, v.shape[axis] - 1)
    return np.where(inside, v[tuple(index)], np.float32(0))


def host_maxima(vol: np.ndarray, floor: float, reach: int = 1) -> np.ndarray:
    """The flat indices (C order, ascending) of ``vol``'s voxels above ``floor`` that no
    voxel within ``reach`` per axis exceeds (``scipy.ndimage.maximum_filter``, 0 beyond
    the faces): the candidates of :func:`find_particles`, and the reference of
    ``kernels/peaks.cl``."""
    v = np.asarray(vol, np.float32)
    peak = v == ndimage.maximum_filter(v, size=2 * reach + 1, mode="constant")
    return np.flatnonzero(peak & (v > np.float32(floor)))


def merge_close(index: np.ndarray, intensities: np.ndarray, radius
                ) -> tuple[np.ndarray, np.ndarray]:
    """Which particles to keep when several lie within ``radius`` of each other: one
    particle seen twice (two peaks of its depth-elongated image in a volume, each
    fitted to the same raw image).

    Greedy from the brightest: a particle keeps every not yet merged one within the
    ellipsoid ``radius`` ``(x, y, z)`` around it (in the units of ``index``, e.g.
    voxels) and takes its intensity.

    Parameters
    ----------
    index
        Positions ``(N, 3)`` as ``(x, y, z)``.
    intensities
        ``(N,)``.
    radius
        ``(x, y, z)`` half-axes; a zero on any axis merges nothing.

    Returns
    -------
    keep, merged
        The particles kept ``(N,)`` (bool) and every particle's intensity with those
        it took (``(N,)``; meaningful where kept).
    """
    radius = np.asarray(radius, float)
    merged = np.asarray(intensities, float).copy()
    keep = np.ones(len(index), bool)
    if len(index) < 2 or np.any(radius <= 0):
        return keep, merged
    scaled = np.asarray(index, float) / radius
    tree = cKDTree(scaled)
    for i in np.argsort(-merged, kind="stable"):
        if keep[i]:
            near = [j for j in tree.query_ball_point(scaled[i], 1.0) if j != i and keep[j]]
            keep[near] = False
            merged[i] += merged[near].sum()
    return keep, merged


def merge_along_lines(points: np.ndarray, values: np.ndarray, directions: np.ndarray,
                      along: float, across: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge the peaks of one particle stretched along a line into one.

    A reconstructed particle is a ridge along its line of sight, several voxels long
    (the camera reads depth several times less precisely than lateral position), and the
    ridge often holds two or three local maxima: off the optical axis, where the line
    leans across the grid, a particle 20-25 mm off the axis at the paper's optics gives
    2.1 peaks on average (docs/design.md §7.4). Greedy from the brightest, each peak takes
    every peak not yet merged that lies within ``along`` of it along its line and within
    ``across`` of that line, and moves to their value-weighted mean position (the
    ridge's centre, between its maxima).

    Parameters
    ----------
    points
        Peak positions ``(N, 3)`` in an isotropic unit (e.g. mm).
    values
        Peak values ``(N,)`` (the weights; positive).
    directions
        Unit vectors ``(N, 3)`` of each peak's line.
    along, across
        The merge reach along and across the line (the unit of ``points``).

    Returns
    -------
    keep, positions
        Which peaks remain ``(N,)`` and every peak's position ``(N, 3)``: merged where
        kept, as given where not (a peak that took others and was taken later too
        included).
    """
    pts = np.asarray(points, float).reshape(-1, 3)
    w = np.asarray(values, float)
    keep = np.ones(len(pts), bool)
    out = pts.copy()
    if len(pts) < 2 or along <= 0:
        return keep, out
    start, reach = _line_neighbours(pts, np.asarray(directions, float), along, across)
    taker = greedy_takers(np.argsort(-w, kind="stable"), start, reach)
    keep = taker == np.arange(len(pts))
    merged = np.unique(taker[~keep])
    merged = merged[keep[merged]]  # a peak taken later keeps nothing of its own
    weight = np.bincount(taker, w, len(pts))[merged]
    for axis in range(3):
        out[merged, axis] = np.bincount(taker, w * pts[:, axis], len(pts))[merged] / weight
    return keep, out


def greedy_takers(order: np.ndarray, start: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Which peak takes each peak in :func:`merge_along_lines`' greedy merge: visited in
    ``order`` (brightest first), a peak not yet taken takes every peak in its reach
    (``reach[start[i]:start[i + 1]]``, :func:`_line_neighbours`) not yet taken, itself
    taken by none; ``(N,)``, a peak's own index where none took it. A peak that took
    others may be taken later by a peak whose line reaches it (the reach is not
    symmetric); those it took stay with it, merged away. The loop runs on Python lists
    (NumPy's per-call costs outweighed a peak's few elements), over the peaks that
    reach another (the others take nothing)."""
    taker = list(range(len(start) - 1))
    taken = [False] * len(taker)
    bounds, near = start.tolist(), reach.tolist()
    for i in order[start[order + 1] > start[order]].tolist():
        if taken[i]:
            continue
        for j in near[bounds[i]:bounds[i + 1]]:
            if not taken[j]:
                taken[j], taker[j] = True, i
    return np.asarray(taker, dtype=np.intp)


def _line_neighbours(pts: np.ndarray, directions: np.ndarray, along: float, across: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """For every peak ``i``, the other peaks within ``along`` of it along its line
    ``directions[i]`` and within ``across`` of that line, as a CSR table: peak ``i``'s
    are ``reach[start[i]:start[i + 1]]``, ascending. The tree's pairs within the
    cylinder's enclosing ball (radius ``hypot(along, across)``: the ball of the larger
    of the two missed the cylinder's rims), both ways, then one vectorised test
    (each pair twice, once on each peak's line)."""
    ball = np.hypot(along, across) * (1.0 + 1e-9)  # a peak on the rim: not lost to rounding
    close = cKDTree(pts).query_pairs(ball, output_type="ndarray")
    owner = np.concatenate([close[:, 0], close[:, 1]])
    other = np.concatenate([close[:, 1], close[:, 0]])
    d = pts[other] - pts[owner]
    line = directions[owner]
    t = np.einsum("ij,ij->i", d, line)
    off = np.linalg.norm(d - t[:, None] * line, axis=1)
    ok = (np.abs(t) <= along) & (off <= across)
    owner, other = owner[ok], other[ok]
    rank = np.lexsort((other, owner))
    start = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=len(pts)))])
    return start, other[rank]
