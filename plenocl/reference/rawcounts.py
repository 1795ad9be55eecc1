"""NumPy twin of ``kernels/rawcounts.cl``
(:class:`plenocl.reconstruction.deviceimage.DeviceCounts`), written for clarity: the
host's own preparation of a camera's counts."""

from __future__ import annotations

import numpy as np

__all__ = ["level_blocks", "level_counts", "scaled_counts"]


def scaled_counts(raw: np.ndarray, median: float, scale: float) -> np.ndarray:
    """``max(raw - median, 0) / scale`` computed in float64 and rounded once to float32."""
    difference = np.maximum(np.asarray(raw, np.float64) - median, 0.0)
    return (difference / scale).astype(np.float32)


def level_counts(raw: np.ndarray, low: int, levels: int) -> np.ndarray:
    """The pixels of ``raw`` at each of ``levels`` levels from ``low`` up, ``(levels,)``."""
    return np.bincount(np.asarray(raw, np.int64).ravel() - low, minlength=levels)


def level_blocks(counts: np.ndarray, block: int) -> np.ndarray:
    """The pixels in each block of ``block`` consecutive levels of the histogram
    ``counts`` (the last block holding what remains), ``(ceil(len(counts) / block),)``."""
    counts = np.asarray(counts, np.int64)
    return np.add.reduceat(counts, np.arange(0, len(counts), block))
