"""NumPy twins of ``kernels/imagefit.cl``: the image fit's model image and per-particle
sums, one particle and one sensor pixel at a time, in float64.

Patches are given as ``(offset, col0, row0, width, height)`` arrays
(:class:`plenocl.optics.raybundle.Patches`); patch rows as ``(k, total)`` arrays of the
rendered rows (value, d/dX', d/dY', d/dd', d/dI). Patch elements off the sensor are
left out.
"""

from __future__ import annotations

import numpy as np


def _patch(rows: np.ndarray, patches, p: int, shape: tuple[int, int]):
    """Particle ``p``'s rows ``(k, h, w)`` on the sensor and their sensor slice."""
    offset, col0, row0, width, height = (int(a[p]) for a in (
        patches.offset, patches.col0, patches.row0, patches.width, patches.height))
    block = rows[:, offset:offset + width * height].reshape(len(rows), height, width)
    h, w = min(height, max(shape[0] - row0, 0)), min(width, max(shape[1] - col0, 0))
    return block[:, :h, :w], (slice(row0, row0 + h), slice(col0, col0 + w))


def patch_model(values: np.ndarray, patches, shape: tuple[int, int]) -> np.ndarray:
    """The sum of every particle's value patch on the sensor ``shape`` ``(rows, cols)``."""
    model = np.zeros(shape)
    for p in range(len(patches.width)):
        block, where = _patch(values[None], patches, p, shape)
        model[where] += block[0]
    return model


def normal_sums(rows: np.ndarray, data: np.ndarray, model: np.ndarray, patches,
                jac: np.ndarray) -> np.ndarray:
    """Per particle ``(n, 16)``: ``J^T J`` (upper triangle, row by row), ``J^T r``, the
    lit elements (value above 1 % of the particle's brightest) and their summed squared
    residuals, where ``J`` holds the position columns in object coordinates
    (``jac[p]`` ``d (X', Y', d') / d (x, y, z)``) and the intensity column, and
    ``r = data - model`` (sensor-shaped)."""
    out = np.zeros((len(patches.width), 16))
    for p in range(len(out)):
        block, where = _patch(rows, patches, p, data.shape)
        res = (data[where] - model[where]).ravel()
        flat = block.reshape(5, -1)
        cols = np.vstack([jac[p].T @ flat[1:4], flat[4]])  # (4, elements)
        upper = np.triu_indices(4)
        out[p, :10] = (cols @ cols.T)[upper]
        out[p, 10:14] = cols @ res
        peak = flat[0].max(initial=0.0)
        lit = flat[0] > 0.01 * peak
        out[p, 14], out[p, 15] = lit.sum(), (res[lit] ** 2).sum()
    return out


def unit_sums(unit: np.ndarray, data: np.ndarray, patches) -> np.ndarray:
    """Per particle ``(n, 2)``: ``sum(unit * data)`` and ``sum(unit^2)`` over its patch."""
    out = np.zeros((len(patches.width), 2))
    for p in range(len(out)):
        block, where = _patch(unit[None], patches, p, data.shape)
        out[p] = (block[0] * data[where]).sum(), (block[0] ** 2).sum()
    return out
