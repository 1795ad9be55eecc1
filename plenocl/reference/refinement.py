"""NumPy twins of :func:`plenocl.piv.refinement.window_means`: the per-window loop over
:func:`~plenocl.piv.refinement.local_gradient`, :func:`~plenocl.piv.refinement.near_median`
and :func:`~plenocl.piv.refinement.window_estimate`, written for clarity; the batched
production code is tested and timed against it (``benchmarks/window_means.py``); and of
:func:`plenocl.piv.refinement.depth_interpolation`: :func:`numpy.interp` column by
column."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..piv.refinement import (
    POSITION_SIGMA,
    SEARCH,
    SPREAD,
    FocalZone,
    ParticlePairs,
    local_gradient,
    near_median,
    pair_weights,
    window_estimate,
)
from ..vectorfield import PIVResult


def window_means_reference(pairs: ParticlePairs, field: PIVResult, min_pairs: int = 3,
                           search=SEARCH, focus: FocalZone | None = None,
                           position_sigma=POSITION_SIGMA, spread: float | None = SPREAD,
                           support: float = 1.0
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`plenocl.piv.refinement.window_means` one window at a time: the readable
    reference that it is tested and timed against (``benchmarks/window_means.py``); the
    pairs of each window from a box ``support`` times it, the gradient's twice that."""
    shape = field.u.shape
    mean, error = np.full((2, 3, *shape), np.nan)
    count = np.zeros(shape, int)
    if not len(pairs.midpoints):
        return mean, error, count
    half = np.asarray(field.window[::-1], float) / 2 * support  # (x, y, z)
    tree = cKDTree(pairs.midpoints / half)
    z, y, x = np.meshgrid(field.z, field.y, field.x, indexing="ij")
    centres = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)  # np.ndindex order
    windows = tree.query_ball_point(centres / half, 1.0, p=np.inf)  # all at once
    busy = [w for w, inside in enumerate(windows) if len(inside) >= min_pairs]
    reach = tree.query_ball_point(centres[busy] / half, 2.0, p=np.inf) if busy else []
    for w, near in zip(busy, reach):
        (k, j, i), centre, inside = np.unravel_index(w, shape), centres[w], windows[w]
        grad = local_gradient(pairs, near, centre, search, spread)
        d = pairs.displacements[inside] - (pairs.midpoints[inside] - centre) @ grad.T
        keep = near_median(d, search, spread)
        count[k, j, i] = np.count_nonzero(keep)
        if count[k, j, i] >= min_pairs:
            weight = pair_weights(pairs, np.asarray(inside)[keep])
            mean[:, k, j, i], error[:, k, j, i] = window_estimate(
                d[keep], pairs.midpoints[inside][keep, 2], grad, focus, position_sigma,
                weight)
    return mean, error, count


def depth_interpolation_reference(w: np.ndarray, sigma: np.ndarray, z: np.ndarray
                                  ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`plenocl.piv.refinement.depth_interpolation` one column at a time: each
    column's finite values interpolated by :func:`numpy.interp`, the uncertainty too with
    half the difference of the values bracketing each depth (by
    :func:`numpy.searchsorted` among the finite depths) added in quadrature."""
    nz = len(z)
    fill, fill_sigma = np.full((2, *w.shape), np.nan)
    flat_w, flat_s = w.reshape(nz, -1), sigma.reshape(nz, -1)
    out_w, out_s = fill.reshape(nz, -1), fill_sigma.reshape(nz, -1)
    for col in np.flatnonzero(np.isfinite(flat_w).any(axis=0)):
        have = np.flatnonzero(np.isfinite(flat_w[:, col]))
        values, sig = flat_w[have, col], np.nan_to_num(flat_s[have, col])
        upper = np.clip(np.searchsorted(z[have], z), 0, len(have) - 1)
        lower = np.clip(upper - 1, 0, len(have) - 1)
        out_w[:, col] = np.interp(z, z[have], values)
        out_s[:, col] = np.hypot(np.interp(z, z[have], sig),
                                 np.abs(values[upper] - values[lower]) / 2)
    return fill, fill_sigma
