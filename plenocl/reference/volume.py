"""NumPy twins of ``kernels/volume.cl`` (:class:`plenocl.opencl.volume.DeviceVolume`),
written for clarity: each row's extremes and counts, and voxels' face neighbourhoods
read from a zero-padded copy of the volume."""

from __future__ import annotations

import numpy as np

__all__ = ["neighbourhoods", "row_summary"]


def row_summary(vol: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per ``(z, y)`` row: its smallest and largest finite value (``inf`` and ``-inf``
    without one), its values not finite and its non-zero values."""
    rows = np.asarray(vol, np.float32).reshape(-1, vol.shape[-1])
    finite = np.isfinite(rows)
    low = np.where(finite, rows, np.inf).min(axis=1)
    high = np.where(finite, rows, -np.inf).max(axis=1)
    return low, high, (~finite).sum(axis=1), np.count_nonzero(rows, axis=1)


def neighbourhoods(vol: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``(n, 7)``: the voxels at the C-order indices ``flat`` and their face neighbours
    (x - 1, x + 1, y - 1, y + 1, z - 1, z + 1), 0 beyond the volume's faces."""
    padded = np.pad(np.asarray(vol, np.float32), 1)
    iz, iy, ix = (i + 1 for i in np.unravel_index(np.asarray(flat, np.int64), vol.shape))
    steps = [(0, 0, 0), (0, 0, -1), (0, 0, 1), (0, -1, 0), (0, 1, 0), (-1, 0, 0), (1, 0, 0)]
    return np.stack([padded[iz + dz, iy + dy, ix + dx] for dz, dy, dx in steps], axis=1)
