"""An Eulerian field from tracks (docs/design.md §7.3): the tracks' displacements per
frame interval averaged in interrogation windows, as a :class:`plenocl.PIVResult`.

Each sample is one track at one frame: its smoothed position and its velocity times the
frame interval, both in the grid's voxel indices. A window (``window`` voxels
``(wz, wy, wx)``, centres ``step`` apart, laid out as :func:`plenocl.piv3d` lays out its
windows: the first centre ``(w - 1) / 2``) averages the samples inside it; its
uncertainty is the standard error of that mean. Windows with fewer than ``min_samples``
samples hold no vector (NaN, not valid). ``frames`` chooses the frames whose samples
count: all of them for a steady flow's mean field, one for a time-resolved field.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..grid import Grid
from ..vectorfield import PIVResult
from .tracks import Tracks

#: Fewest samples for a window's vector.
MIN_SAMPLES = 3


def bin_tracks(tracks: Tracks, grid: Grid, window=(16, 16, 16), step=None, frames=None,
               min_samples: int = MIN_SAMPLES) -> PIVResult:
    """The tracks' mean displacement per frame interval in windows of ``grid``.

    Parameters
    ----------
    tracks
        :class:`plenocl.Tracks` (positions in the grid's millimetres).
    grid
        The grid whose voxels are the field's units (the reconstruction's).
    window, step
        Window size and centre spacing ``(z, y, x)`` voxels (``step``: half the window).
    frames
        Frame indices whose samples count (``None``: every frame).
    min_samples
        Fewest samples for a vector.

    Returns
    -------
    plenocl.PIVResult
        Displacements ``u, v, w`` (voxels per frame interval) with ``sigma_u/v/w``;
        ``refinement`` records the samples used.
    """
    window = np.broadcast_to(np.asarray(window, int), 3)
    step = window // 2 if step is None else np.broadcast_to(np.asarray(step, int), 3)
    if np.any(window < 1) or np.any(step < 1) or np.any(window > np.asarray(grid.shape)):
        raise ValueError(f"bin_tracks: window {tuple(window)} and step {tuple(step)} (z, y, x "
                         f"voxels) must be positive and fit the grid {grid.shape}")
    index, disp = _samples(tracks, grid, frames)
    counts = (np.asarray(grid.shape) - window) // step + 1
    sums = _window_sums(index[:, ::-1], disp, window, step, counts)
    return _field(sums, window, step, counts, min_samples, len(disp))


def _samples(tracks: Tracks, grid: Grid, frames) -> tuple[np.ndarray, np.ndarray]:
    """Sample positions (voxel indices ``(x, y, z)``) and displacements (voxels per
    frame interval) of the chosen frames, where a track has a velocity."""
    pos = tracks.positions
    moved = pos + tracks.velocities * tracks.dt
    chosen = np.arange(pos.shape[1]) if frames is None else np.atleast_1d(frames)
    p, q = pos[:, chosen].reshape(-1, 3), moved[:, chosen].reshape(-1, 3)
    ok = np.all(np.isfinite(p) & np.isfinite(q), axis=1)
    start = grid.to_index(p[ok])
    return start, grid.to_index(q[ok]) - start


def _window_sums(zyx: np.ndarray, disp: np.ndarray, window, step, counts) -> np.ndarray:
    """Per window: sample count, sums and sums of squares of the displacements
    ``(7, nz', ny', nx')``. A sample lies in every window whose centre is within half a
    window of it (overlapping windows share it)."""
    sums = np.zeros((7, *counts))
    first = (window - 1) / 2
    low = np.ceil((zyx - window / 2 - first) / step).astype(int)
    values = np.column_stack([np.ones(len(disp)), disp, disp**2]).T
    span = int(np.max(np.ceil(window / step))) + 1
    for offset in itertools.product(range(span), repeat=3):
        idx = low + np.asarray(offset)
        centre = first + idx * step
        inside = np.all((idx >= 0) & (idx < counts) & (np.abs(zyx - centre) <= window / 2),
                        axis=1)
        for row in range(7):
            np.add.at(sums[row], tuple(idx[inside].T), values[row, inside])
    return sums


def _field(sums: np.ndarray, window, step, counts, min_samples: int, used: int) -> PIVResult:
    """The windows' means and standard errors as a :class:`PIVResult`."""
    n = sums[0]
    valid = n >= max(min_samples, 2)
    safe = np.where(valid, n, 1.0)
    mean = sums[1:4] / safe
    var = np.maximum(sums[4:7] - safe * mean**2, 0.0) / np.maximum(safe - 1, 1)
    sigma = np.sqrt(var / safe)
    mean[:, ~valid], sigma[:, ~valid] = np.nan, np.nan
    centres = [(w - 1) / 2 + s * np.arange(c) for w, s, c in zip(window, step, counts)]
    flags = np.zeros(valid.shape, bool)
    return PIVResult(centres[2], centres[1], centres[0], mean[0], mean[1], mean[2], valid,
                     np.full(valid.shape, np.nan), flags, ~valid, tuple(int(w) for w in window),
                     sigma_u=sigma[0], sigma_v=sigma[1], sigma_w=sigma[2],
                     refinement={"tracks_binned": used,
                                 "median_samples": float(np.median(n[valid])) if valid.any()
                                 else 0.0})
