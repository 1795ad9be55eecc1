"""NumPy twin of ``kernels/rawcounts.cl``
(:class:`plenocl.reconstruction.deviceimage.DeviceCounts`), written for clarity: the
host's own preparation of a camera's counts."""

from __future__ import annotations

import numpy as np

__all__ = ["scaled_counts"]


def scaled_counts(raw: np.ndarray, median: float, scale: float) -> np.ndarray:
    """``max(raw - median, 0) / scale`` computed in float64 and rounded once to float32."""
    difference = np.maximum(np.asarray(raw, np.float64) - median, 0.0)
    return (difference / scale).astype(np.float32)
