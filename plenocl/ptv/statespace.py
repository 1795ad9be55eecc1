"""Tracks smoothed by a constant-velocity state-space model (docs/design.md §7.3).

Along a track, each frame ``j`` has a state: a position ``p_j`` and a velocity ``v_j``
per axis. From one frame to the next the particle moves with its velocity while the
velocity changes by a random acceleration of standard deviation ``q`` (white noise in
continuous time: the state's step has the covariance ``q² [[1/3, 1/2], [1/2, 1]]`` per
frame). Each frame's fitted position measures ``p_j`` with its variance, and an
optional prior (e.g. what the neighbouring tracks say, :mod:`.neighbours`) measures
``v_j``. The states are the weighted least-squares solution of all these at once (the
Rauch-Tung-Striebel smoother's answer, solved directly: a track has a few dozen
unknowns), their covariance the inverse normal matrix.

Unlike local polynomial fits over sliding windows (:mod:`.smoothing`), the positions and
the velocities are one consistent trajectory: a position that its frame's image places
poorly (a large variance) follows from its neighbours in time and the velocity, so the
step from one frame to the next is the velocity, not the difference of two windows'
intercepts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The state step's covariance per frame for a unit acceleration noise (position,
#: velocity).
_STEP_COVARIANCE = np.array([[1.0 / 3.0, 1.0 / 2.0], [1.0 / 2.0, 1.0]])


@dataclass(frozen=True)
class StateFit:
    """What :func:`smooth_states` gives, each ``(n_tracks, n_frames, 3)`` and NaN where
    the track has no particle: positions and velocities (per frame) and their standard
    deviations; ``birge`` ``(3,)``, the factor per axis by which those deviations were
    scaled up (the fit's pooled reduced chi-square's root, at least 1)."""

    positions: np.ndarray
    velocities: np.ndarray
    position_sigma: np.ndarray
    velocity_sigma: np.ndarray
    birge: np.ndarray


def smooth_states(measured: np.ndarray, sigma: np.ndarray, acceleration,
                  prior: np.ndarray | None = None, prior_sigma: np.ndarray | None = None
                  ) -> StateFit:
    """Every track's constant-velocity smoothing.

    Parameters
    ----------
    measured
        Positions ``(n_tracks, n_frames, 3)``, NaN where a track has no particle.
    sigma
        Their standard deviations, the same shape (positive where measured).
    acceleration
        The acceleration noise ``q`` per axis ``(3,)`` (or one value): the standard
        deviation of a velocity's change over one frame, in position units per frame².
    prior, prior_sigma
        Optional velocity priors per frame and axis (position units per frame) and
        their standard deviations, the same shape as ``measured``; NaN or infinite
        ``prior_sigma``: no prior there.

    Returns
    -------
    StateFit
        Velocities in position units per frame (divide by the frame interval). Where the
        residuals of all tracks together scatter more than the given deviations and the
        acceleration noise say (the pooled reduced chi-square per axis above 1: the
        fit's variances too small, or a flow that accelerates more than ``q``), the
        standard deviations are scaled up by its square root (Birge's ratio).
    """
    q = np.broadcast_to(np.asarray(acceleration, float), (3,))
    if not np.all(np.isfinite(q) & (q > 0)):
        raise ValueError(f"the acceleration noise must be positive, got {acceleration!r}")
    present = np.all(np.isfinite(measured), axis=2)
    out = [np.full(measured.shape, np.nan) for _ in range(4)]
    chi2, dof = np.zeros(3), np.zeros(3)
    first, last = _spans(present)
    for length in np.unique(last - first + 1):
        rows = np.flatnonzero((last - first + 1 == length) & (length >= 2))
        if len(rows):
            c, d = _smooth_group(rows, first[rows], int(length), measured, sigma, q, prior,
                                 prior_sigma, out)
            chi2, dof = chi2 + c, dof + d
    birge = np.sqrt(np.maximum(chi2 / np.maximum(dof, 1), 1.0))
    for k, array in enumerate(out):
        array[~present] = np.nan
        if k >= 2:
            array *= birge
    return StateFit(*out, birge)


def _spans(present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each track's first and last frame (-1 and -2 for a track without particles)."""
    seen = present.any(axis=1)
    first = np.where(seen, np.argmax(present, axis=1), -1)
    last = np.where(seen, present.shape[1] - 1 - np.argmax(present[:, ::-1], axis=1), -2)
    return first, last


def _smooth_group(rows: np.ndarray, first: np.ndarray, length: int, measured, sigma,
                  q: np.ndarray, prior, prior_sigma, out: list[np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The tracks ``rows``, all spanning ``length`` frames from ``first``: one batched
    solve of their ``2 length`` states per axis (into ``out``). Returns the group's
    chi-square and degrees of freedom per axis."""
    take = (rows[:, None], first[:, None] + np.arange(length))
    w, m = _weights(measured[take], sigma[take])                       # (n, L, 3)
    pw, pm = _weights(*((prior[take], prior_sigma[take]) if prior is not None
                        else (np.full(w.shape, np.nan),) * 2))
    normal = np.repeat(_dynamics(length)[None, None] / (q ** 2)[None, :, None, None],
                       len(rows), axis=0)                                # (n, 3, 2L, 2L)
    idx = np.arange(length)
    normal[:, :, 2 * idx, 2 * idx] += np.moveaxis(w, 2, 1)
    normal[:, :, 2 * idx + 1, 2 * idx + 1] += np.moveaxis(pw, 2, 1)
    rhs = np.zeros(normal.shape[:3])
    rhs[:, :, 0::2] = np.moveaxis(w * m, 2, 1)
    rhs[:, :, 1::2] = np.moveaxis(pw * pm, 2, 1)
    cov = np.linalg.inv(normal)
    state = np.einsum("naij,naj->nai", cov, rhs)
    var = np.diagonal(cov, axis1=2, axis2=3)
    for k, values in enumerate((state[..., 0::2], state[..., 1::2],
                                np.sqrt(var[..., 0::2]), np.sqrt(var[..., 1::2]))):
        out[k][take] = np.moveaxis(values, 1, 2)
    # At the optimum the weighted squared residuals are c - x·b (c: Σ w m², b: rhs).
    chi2 = np.sum(w * m**2 + pw * pm**2, axis=1) - np.einsum("nai,nai->na", state, rhs)
    dof = np.sum((w > 0) + (pw > 0), axis=1) - 2
    return np.maximum(chi2, 0.0).sum(axis=0), dof.sum(axis=0).astype(float)


def _weights(values: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse variances (0 where a value or its deviation is missing) and the values
    (0 there)."""
    ok = np.isfinite(values) & np.isfinite(sigma) & (sigma > 0)
    return (np.where(ok, 1.0 / np.where(ok, sigma, 1.0) ** 2, 0.0),
            np.where(ok, values, 0.0))


def _dynamics(length: int) -> np.ndarray:
    """The normal matrix ``(2L, 2L)`` of the state steps for a unit acceleration noise:
    ``Dᵀ Q⁻¹ D`` with ``D`` the steps' residuals ``x_{j+1} - F x_j``."""
    step_inv = np.linalg.inv(_STEP_COVARIANCE)
    transition = np.array([[1.0, 1.0], [0.0, 1.0]])
    normal = np.zeros((2 * length, 2 * length))
    block = np.hstack([-transition, np.eye(2)])                     # (2, 4)
    local = block.T @ step_inv @ block
    for j in range(length - 1):
        normal[2 * j:2 * j + 4, 2 * j:2 * j + 4] += local
    return normal
