"""Particles of consecutive frames linked into tracks (docs/design.md §7.3).

Each step from frame ``k`` to ``k + 1`` predicts where every particle of frame ``k`` goes
and pairs the predictions with the particles of frame ``k + 1`` that are their mutual
nearest neighbours within ``search`` (per axis: depth is less certain than the lateral
position). The prediction of a particle already on a track of two or more frames is the
slope of a straight line fitted to the track's last :data:`HISTORY` positions; that of
a particle new to a track is the median step of its :data:`NEIGHBOURS` nearest tracked
neighbours, and, in the first step (no track has a history yet), the ``first_step``
predictor the caller gives (the correlation field of the first two volumes). A particle
of frame ``k + 1`` left unpaired starts a new track. A track whose particle finds no
partner waits up to ``gap`` frames, predicted that many steps ahead (a particle the
reconstruction lost in one frame keeps its track, with a gap there), then ends.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

#: Frames of a track whose straight-line fit predicts its next step.
HISTORY = 4
#: Tracked neighbours whose median step predicts a particle new to a track.
NEIGHBOURS = 8

#: Displacement ``(N, 3)`` of the particles at ``(N, 3)`` from one frame to the next.
Predictor = Callable[[np.ndarray], np.ndarray]


def link(points: Sequence[np.ndarray], search, first_step: Predictor | None = None,
         gap: int = 1) -> np.ndarray:
    """The tracks through ``points``, one ``(N_k, 3)`` array of positions per frame.

    Parameters
    ----------
    points
        Each frame's particle positions (any units; ``search`` in the same).
    search
        Largest distance ``(x, y, z)`` between a prediction and its partner.
    first_step
        The predicted displacement of frame 0's particles into frame 1 (``None``: no
        motion).
    gap
        Frames a track may miss and still continue (a particle the reconstruction lost
        once): a track whose last particle is up to ``gap + 1`` frames back is predicted
        that many steps ahead and competes for the next frame's particles.

    Returns
    -------
    numpy.ndarray
        ``(n_tracks, n_frames)`` integer indices into each frame's points, ``-1`` where
        the track has no particle. Every particle belongs to exactly one track.
    """
    n_frames = len(points)
    table = np.full((len(points[0]), n_frames), -1, np.int64)
    table[:, 0] = np.arange(len(points[0]))
    for k in range(n_frames - 1):
        rows, predictions = _predictions(table, points, k, search, first_step, gap)
        ia, ib = mutual_nearest(predictions, points[k + 1], search)
        table[rows[ia], k + 1] = ib
        fresh = np.setdiff1d(np.arange(len(points[k + 1])), ib)
        new = np.full((len(fresh), n_frames), -1, np.int64)
        new[:, k + 1] = fresh
        table = np.vstack([table, new])
    return table


def _predictions(table: np.ndarray, points: Sequence[np.ndarray], k: int, search,
                 first_step: Predictor | None, gap: int) -> tuple[np.ndarray, np.ndarray]:
    """The tracks that may continue into frame ``k + 1`` (their last particle at most
    ``gap + 1`` frames back) and where each is predicted there."""
    rows, predictions = [], []
    for back in range(min(gap, k) + 1):
        last = k - back
        ends = (table[:, last] >= 0) & np.all(table[:, last + 1:k + 1] < 0, axis=1)
        ended = np.flatnonzero(ends)
        if not len(ended):
            continue
        here = points[last][table[ended, last]]
        steps = _steps(table[ended, : last + 1], points, search,
                       first_step if last == 0 else None)
        rows.append(ended)
        predictions.append(here + (back + 1) * steps)
    if not rows:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(rows), np.concatenate(predictions)


def mutual_nearest(predicted: np.ndarray, targets: np.ndarray, search
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(ia, ib)`` of the predictions and targets that are each other's nearest
    neighbour within ``search`` (distances scaled per axis by ``1 / search``)."""
    if not len(predicted) or not len(targets):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    scale = 1.0 / np.asarray(search, float)
    dist_a, to_b = cKDTree(targets * scale).query(predicted * scale, distance_upper_bound=1.0)
    dist_b, to_a = cKDTree(predicted * scale).query(targets * scale, distance_upper_bound=1.0)
    ia = np.flatnonzero(np.isfinite(dist_a))
    ia = ia[np.isfinite(dist_b[to_b[ia]]) & (to_a[to_b[ia]] == ia)]
    return ia, to_b[ia]


def _steps(history: np.ndarray, points: Sequence[np.ndarray], search,
           first_step: Predictor | None) -> np.ndarray:
    """The predicted step of each track whose last frame is the last column of
    ``history`` ``(n, k + 1)``: its own straight line, else its neighbours' median."""
    k = history.shape[1] - 1
    here = points[k][history[:, k]]
    steps, known = _line_slopes(history, points)
    if known.all():
        return steps
    if known.any():
        scale = 1.0 / np.asarray(search, float)
        count = min(NEIGHBOURS, int(known.sum()))
        _, near = cKDTree(here[known] * scale).query(here[~known] * scale, k=count)
        near = np.asarray(near).reshape(int((~known).sum()), count)
        steps[~known] = np.median(steps[known][near], axis=1)
    elif first_step is not None:
        steps = np.asarray(first_step(here), float).reshape(here.shape)
    return steps


def _line_slopes(history: np.ndarray, points: Sequence[np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per track, the slope (per frame) of a least-squares line through its last
    :data:`HISTORY` positions, and whether it had at least two (else the slope is 0)."""
    n, frames = history.shape
    first = max(0, frames - HISTORY)
    t = np.arange(first, frames, dtype=float)
    pos = np.zeros((n, len(t), 3))
    present = history[:, first:] >= 0
    for j in range(len(t)):
        rows = present[:, j]
        pos[rows, j] = points[first + j][history[rows, first + j]]
    count = present.sum(axis=1)
    w = present.astype(float)
    t_mean = (w * t).sum(axis=1) / np.maximum(count, 1)
    dt = (t[None, :] - t_mean[:, None]) * w
    p_mean = (w[:, :, None] * pos).sum(axis=1) / np.maximum(count, 1)[:, None]
    var = (dt**2).sum(axis=1)
    cov = (dt[:, :, None] * (pos - p_mean[:, None, :])).sum(axis=1)
    known = count >= 2
    slopes = np.zeros((n, 3))
    slopes[known] = cov[known] / var[known, None]
    return slopes, known
