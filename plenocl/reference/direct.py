"""Plain twin of :mod:`plenocl.piv.direct`: one window and one lag at a time."""

from __future__ import annotations

import itertools

import numpy as np


def _taps(size: int, weighting, centre_shift: float) -> np.ndarray:
    """The weight along one axis over the window and its margin (see
    :func:`plenocl.piv.direct.axis_taps`), written out again, and the margin."""
    if weighting is None:
        return np.ones(size), 0
    sigma = weighting * size / np.sqrt(2.0)          # W = exp(-q^2 / (2 sigma^2))
    margin = max(0, int(np.ceil(3.0 * sigma - 0.5 * size)))
    q = np.arange(-margin, size + margin) - 0.5 * (size - 1) - centre_shift
    return np.exp(-0.5 * (q / sigma) ** 2), margin


def correlate_windows(vol_a, vol_b, grid, weighting):
    """Weighted Pearson coefficient of every window of ``grid`` at the 63 lags
    ``s`` in ``{-3, ..., 3} x {-1, 0, 1}^2`` ``(sz, sy, sx)`` (C order): ``a`` over the
    window (and the weight's margin) at corner ``L``, ``b`` over the same voxels moved by
    ``s``, both weighted by ``W(q + s/2)``; zero outside the volumes.

    Returns ``(63, *grid.count)``.
    """
    margins = [_taps(n, weighting, 0.0)[1] for n in grid.size]
    depth_lags = (-3, -2, -1, 0, 1, 2, 3)
    pad = max(margins) + max(depth_lags)
    a = np.pad(np.asarray(vol_a, np.float64), pad)
    b = np.pad(np.asarray(vol_b, np.float64), pad)
    lags = list(itertools.product(depth_lags, (-1, 0, 1), (-1, 0, 1)))
    out = np.zeros((len(lags), *grid.count))
    for k, lag in enumerate(lags):
        taps = [_taps(n, weighting, -0.5 * s)[0] for n, s in zip(grid.size, lag)]
        weight = taps[0][:, None, None] * taps[1][None, :, None] * taps[2]
        for index in np.ndindex(*grid.count):
            lo = [pad + o + st * i - m for o, st, i, m in
                  zip(grid.offset, grid.step, index, margins)]
            sl_a = tuple(slice(x, x + n) for x, n in zip(lo, weight.shape))
            sl_b = tuple(slice(x + s, x + s + n) for x, s, n in zip(lo, lag, weight.shape))
            out[(k, *index)] = _weighted_pearson(a[sl_a], b[sl_b], weight)
    return out


def _weighted_pearson(u: np.ndarray, v: np.ndarray, w: np.ndarray) -> float:
    mu, mv = (w * u).sum() / w.sum(), (w * v).sum() / w.sum()
    cov = (w * (u - mu) * (v - mv)).sum()
    den = np.sqrt((w * (u - mu) ** 2).sum() * (w * (v - mv) ** 2).sum())
    return float(cov / den) if den > 0 else 0.0


def column_partials(rows: np.ndarray, block: int) -> np.ndarray:
    """Twin of ``column_partials`` (``kernels/correlated.cl``): per block of ``block``
    rows of ``rows`` ``(n, cols)`` and per column, the block's values added in row order
    (float64), ``(blocks, cols)``."""
    n, cols = rows.shape
    out = np.zeros((max(-(-n // block), 1), cols))
    for k in range(out.shape[0]):
        for c in range(cols):
            for r in range(k * block, min(n, (k + 1) * block)):
                out[k, c] += float(rows[r, c])
    return out
