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


def resample_matrix_3d(grid: Grid, frame: Grid, pose, normalised: bool = True
                       ) -> sparse.csr_matrix:
    """``S`` of a posed camera (``kernels/resample.cl``'s ``to_frame_3d``):
    ``(frame.size, grid.size)`` trilinear weights, flat C order, of the world ``grid``'s
    voxels at every frame voxel's centre (the frame lies in the camera's frame: its points
    go into the world through ``pose``); taps outside ``grid`` are dropped; columns
    normalised to sum to 1 (or the raw taps, ``normalised=False``)."""
    nz, ny, nx = grid.shape
    fnz, fny, fnx = frame.shape
    rows, cols, weights = [], [], []
    for c in range(fnz):
        for b in range(fny):
            for a in range(fnx):
                world = pose.to_world(frame.from_index([[a, b, c]]))
                p = grid.to_index(world)[0]
                base = np.floor(p).astype(int)
                frac = p - base
                for corner in np.ndindex(2, 2, 2):  # (x, y, z) offsets
                    x, y, z = base + corner
                    w = np.prod([f if o else 1 - f for f, o in zip(frac, corner, strict=True)])
                    if 0 <= x < nx and 0 <= y < ny and 0 <= z < nz and w > 0:
                        rows.append((c * fny + b) * fnx + a)
                        cols.append((z * ny + y) * nx + x)
                        weights.append(w)
    s = sparse.csr_matrix((weights, (rows, cols)), shape=(fnz * fny * fnx, nz * ny * nx))
    if not normalised:
        return s
    sums = np.asarray(s.sum(axis=0)).ravel()
    return sparse.csr_matrix(s @ sparse.diags(np.where(sums > 0, 1 / np.maximum(sums, 1e-300),
                                                       0.0)))
