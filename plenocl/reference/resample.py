"""NumPy reference of the frame resampling (``kernels/resample.cl``), written for clarity.

Every voxel of the frame grid takes the bilinear interpolation of the user's grid at its
centre, plane by plane (docs/design.md §5.1): row ``f`` of the matrix holds the weights
of the user's voxels at frame voxel ``f``'s centre; each column is then divided by its
sum, so that every user voxel spreads its light onto the frame with weights summing to 1.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from ..grid import Grid

__all__ = ["resample_matrix", "resample_volume"]


def resample_matrix(grid: Grid, frame: Grid, normalised: bool = True) -> sparse.csr_matrix:
    """``S``: ``(fny * fnx, ny * nx)`` bilinear weights of one depth plane, flat C order
    (taps outside ``grid`` are dropped), columns normalised to sum to 1 (or the raw taps,
    ``normalised=False``)."""
    _, ny, nx = grid.shape
    _, fny, fnx = frame.shape
    rows, cols, weights = [], [], []
    for b in range(fny):
        for a in range(fnx):
            centre = frame.from_index([[a, b, 0.0]])
            px, py, _ = grid.to_index(centre)[0]
            x0, y0 = int(np.floor(px)), int(np.floor(py))
            tx, ty = px - x0, py - y0
            for x, wx in ((x0, 1 - tx), (x0 + 1, tx)):
                for y, wy in ((y0, 1 - ty), (y0 + 1, ty)):
                    if 0 <= x < nx and 0 <= y < ny and wx * wy > 0:
                        rows.append(b * fnx + a)
                        cols.append(y * nx + x)
                        weights.append(wx * wy)
    s = sparse.csr_matrix((weights, (rows, cols)), shape=(fny * fnx, ny * nx))
    if not normalised:
        return s
    sums = np.asarray(s.sum(axis=0)).ravel()
    return sparse.csr_matrix(s @ sparse.diags(1 / sums))


def resample_volume(vol: np.ndarray, grid: Grid, frame: Grid) -> np.ndarray:
    """``S vol``: every depth plane of ``vol`` (on ``grid``) resampled onto ``frame``."""
    s = resample_matrix(grid, frame)
    _, fny, fnx = frame.shape
    return np.stack([(s @ plane.ravel()).reshape(fny, fnx) for plane in vol])
