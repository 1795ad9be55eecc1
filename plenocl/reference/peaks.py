"""NumPy twin of :func:`plenocl.peaks.merge_along_lines`, written for clarity: the
greedy merge one peak at a time, each kept peak tested against every other kept peak.
The production code (a k-d tree's pairs, the greedy loop over the peaks that reach
another) is tested and timed against it (``benchmarks/host_work.py``)."""

from __future__ import annotations

import numpy as np


def merge_along_lines_reference(points: np.ndarray, values: np.ndarray,
                                directions: np.ndarray, along: float, across: float
                                ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`plenocl.peaks.merge_along_lines`: from the brightest (ties in index
    order), each peak not yet merged takes every peak not yet merged within ``along``
    of it along its own line ``directions[i]`` and within ``across`` of that line, and
    moves to their value-weighted mean position."""
    pts = np.asarray(points, float).reshape(-1, 3)
    w = np.asarray(values, float)
    keep, out = np.ones(len(pts), bool), pts.copy()
    if len(pts) < 2 or along <= 0:
        return keep, out
    for i in np.argsort(-w, kind="stable"):
        if not keep[i]:
            continue
        d = pts - pts[i]
        t = d @ directions[i]
        off = np.linalg.norm(d - t[:, None] * directions[i], axis=1)
        near = keep & (np.abs(t) <= along) & (off <= across)
        near[i] = False
        if near.any():
            group = np.append(np.flatnonzero(near), i)
            out[i] = np.average(pts[group], axis=0, weights=w[group])
            keep[near] = False
    return keep, out
