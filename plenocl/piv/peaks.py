"""Particles in a reconstructed volume: local maxima with sub-voxel positions (used by
the reconstruction metrics and by the particle refinement of ``tracking.py``)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .correlation import gaussian_subpixel


def find_particles(vol: np.ndarray, threshold: float = 0.1, min_separation: int = 1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima above ``threshold · max`` with sub-voxel positions.

    Returns fractional voxel indices ``(N, 3)`` as ``(ix, iy, iz)`` and peak values,
    brightest first. Positions use a three-point Gaussian fit along each axis.
    """
    v = np.asarray(vol, np.float32)
    if v.ndim != 3:
        raise ValueError(f"expected a 3-D volume, got shape {v.shape}")
    vmax = float(v.max()) if v.size else 0.0
    if vmax <= 0:
        return np.zeros((0, 3)), np.zeros(0)
    size = 2 * min_separation + 1
    peaks = (v == ndimage.maximum_filter(v, size=size, mode="constant")) & (v > threshold * vmax)
    iz, iy, ix = np.nonzero(peaks)
    vals = v[iz, iy, ix]
    pad = np.pad(v, 1)
    pos = [ix, iy, iz]
    out = np.empty((len(vals), 3))
    for k, axis in enumerate((2, 1, 0)):
        step = [0, 0, 0]
        step[axis] = 1
        centre = (iz + 1, iy + 1, ix + 1)
        minus = pad[tuple(c - s for c, s in zip(centre, step))]
        plus = pad[tuple(c + s for c, s in zip(centre, step))]
        out[:, k] = pos[k] + gaussian_subpixel(minus, vals, plus)
    order = np.argsort(-vals)
    return out[order], vals[order]
