"""Tracks smoothed by local polynomial fits (docs/design.md §7.3).

At every frame a track has a particle, a polynomial in time of degree ``degree`` (2 by
default: a particle accelerates) is fitted by weighted least squares to the track's
positions within ``window`` frames centred there (fewer at its ends), each weighted by
the inverse variance of its measured position. The fit's value, first and second
derivative at that frame are the track's position, velocity and acceleration, and the
fit's covariance gives their standard deviations. A particle's depth in the camera's
focal zone, which a single image places poorly (a large variance), is then carried by
its neighbours in time. Where the window holds fewer positions than the polynomial has
coefficients, the degree falls (a line through two positions; a single position has no
velocity: NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackFit:
    """What :func:`smooth` gives, each ``(n_tracks, n_frames, 3)`` (NaN where the track
    has no particle, or no velocity or acceleration): positions, velocities and
    accelerations (per unit of time) and their standard deviations."""

    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray
    position_sigma: np.ndarray
    velocity_sigma: np.ndarray
    acceleration_sigma: np.ndarray


def smooth(measured: np.ndarray, sigma: np.ndarray, dt: float, window: int = 7,
           degree: int = 2) -> TrackFit:
    """Local polynomial fits along every track.

    Parameters
    ----------
    measured
        Positions ``(n_tracks, n_frames, 3)``, NaN where a track has no particle.
    sigma
        Their standard deviations, the same shape (positive where measured).
    dt
        The time between frames.
    window
        Frames of each local fit (odd, at least 3).
    degree
        The polynomial's degree (0-3).
    """
    if window < 3 or window % 2 == 0:
        raise ValueError(f"the track fit's window must be an odd number of frames >= 3, "
                         f"got {window}")
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"the track fit's degree must be 0, 1, 2 or 3, got {degree}")
    present = np.all(np.isfinite(measured), axis=2)
    weight = np.where(present[..., None], 1.0 / np.where(present[..., None], sigma, 1.0)**2, 0)
    values = np.where(present[..., None], measured, 0.0)
    out = [np.full(measured.shape, np.nan) for _ in range(6)]
    for j in range(measured.shape[1]):
        _fit_frame(j, values, weight, present, dt, window // 2, degree, out)
    return TrackFit(*out)


def _fit_frame(j: int, values, weight, present, dt: float, half: int, degree: int,
               out: list[np.ndarray]) -> None:
    """The fits of every track at frame ``j`` (into ``out``), one degree at a time."""
    lo, hi = max(0, j - half), min(values.shape[1], j + half + 1)
    count = present[:, lo:hi].sum(axis=1)
    tau = (np.arange(lo, hi) - j) * dt
    for d in range(degree + 1):
        rows = present[:, j] & (np.minimum(count - 1, degree) == d)
        if rows.any():
            _fit_rows(rows, j, tau, values[rows, lo:hi], weight[rows, lo:hi], d, out)


def _fit_rows(rows, j: int, tau: np.ndarray, values: np.ndarray, weight: np.ndarray,
              d: int, out: list[np.ndarray]) -> None:
    """Weighted least squares of degree ``d`` in ``tau`` per track and axis; the value and
    derivatives at ``tau = 0`` and their standard deviations into ``out``."""
    design = tau[:, None] ** np.arange(d + 1)                     # (w, d + 1)
    normal = np.einsum("wi,nwa,wj->naij", design, weight, design)  # (n, 3, d+1, d+1)
    rhs = np.einsum("wi,nwa->nai", design, weight * values)
    cov = np.linalg.inv(normal)
    coef = np.einsum("naij,naj->nai", cov, rhs)
    factor = [1.0, 1.0, 2.0]
    for k in range(min(d, 2) + 1):
        out[k][rows, j] = factor[k] * coef[..., k]
        out[3 + k][rows, j] = factor[k] * np.sqrt(cov[..., k, k])
