"""Tracks smoothed by a constant-velocity state-space model (docs/design.md §7.3).

Along a track, each frame ``j`` has a state: a position ``p_j`` and a velocity ``v_j``
per axis. From one frame to the next the particle moves with its velocity while the
velocity changes by a random acceleration of standard deviation ``q`` (white noise in
continuous time: the state's step has the covariance ``q² [[1/3, 1/2], [1/2, 1]]`` per
frame). Each frame's fitted position measures ``p_j`` with its variance, and an
optional prior (e.g. what the neighbouring tracks say, :mod:`.neighbours`) measures
``v_j``. The states are the weighted least-squares solution of all these at once (the
Rauch-Tung-Striebel smoother's answer), their variances the diagonal of the inverse
normal matrix.

The normal matrix is block tridiagonal in the frames (2 x 2 blocks), so every track and
axis is solved at once by block elimination over the frames and the variances come
from the same factors (the selected inverse): time and memory grow with tracks x
frames, not with the cube of a long track's length. Frames outside a track's span, with
nothing measured, only extend its trajectory and change nothing within the span.

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
STEP_COVARIANCE = np.array([[1.0 / 3.0, 1.0 / 2.0], [1.0 / 2.0, 1.0]])
#: The state's transition over one frame.
TRANSITION = np.array([[1.0, 1.0], [0.0, 1.0]])


@dataclass(frozen=True)
class StateFit:
    """What :func:`smooth_states` gives, each ``(n_tracks, n_frames, 3)`` and NaN where
    the track has no particle: positions, velocities (per frame) and accelerations (per
    frame², the velocities' central differences, one-sided at a track's ends) and their
    standard deviations; ``birge`` ``(3,)``, the factor per axis by which those
    deviations were scaled up (the fit's pooled reduced chi-square's root, at least 1)."""

    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray
    position_sigma: np.ndarray
    velocity_sigma: np.ndarray
    acceleration_sigma: np.ndarray
    birge: np.ndarray


def smooth_states(measured: np.ndarray, sigma: np.ndarray, acceleration: float | np.ndarray,
                  prior: np.ndarray | None = None, prior_sigma: np.ndarray | None = None
                  ) -> StateFit:
    """Every track's constant-velocity smoothing.

    Parameters
    ----------
    measured
        Positions ``(n_tracks, n_frames, 3)``, NaN where a track has no particle.
    sigma
        Their standard deviations, the same shape; a frame counts where its position
        and deviation are finite and the deviation positive on every axis.
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
        Velocities in position units per frame (divide by the frame interval); NaN for
        tracks with fewer than two frames. Where the residuals of all tracks together
        scatter more than the given deviations and ``q`` say (the pooled reduced
        chi-square per axis above 1: deviations stated too small, or a flow that
        accelerates more than ``q``), the standard deviations are scaled up by its
        square root (Birge's ratio).
    """
    q = np.broadcast_to(np.asarray(acceleration, float), (3,))
    if not np.all(np.isfinite(q) & (q > 0)):
        raise ValueError(f"the acceleration noise must be positive, got {acceleration!r}")
    w, m = _weights(measured, sigma)
    present = np.all(w > 0, axis=2)
    pw, pm = _weights(prior, prior_sigma) if prior is not None else (np.zeros_like(w),) * 2
    span = _within_span(present)
    pw = np.where(span[..., None], pw, 0.0)  # a prior only where measured
    rows = np.flatnonzero(present.sum(axis=1) >= 2)
    out = [np.full(measured.shape, np.nan) for _ in range(6)]
    birge = np.ones(3)
    if len(rows):
        states, cov, chi2 = _solve(w[rows], m[rows], pw[rows], pm[rows], q)
        dof = np.sum((w[rows] > 0) + (pw[rows] > 0), axis=1) - 2     # (n, 3)
        birge = np.sqrt(np.maximum(chi2.sum(axis=0) / np.maximum(dof.sum(axis=0), 1), 1.0))
        accel, accel_var = _accelerations(states[..., 1], cov, span[rows])
        for k, values in enumerate((states[..., 0], states[..., 1], accel,
                                    np.sqrt(cov[0][..., 0, 0]), np.sqrt(cov[0][..., 1, 1]),
                                    np.sqrt(accel_var))):
            out[k][rows] = np.where(present[rows, :, None], values * (birge if k > 2 else 1),
                                    np.nan)
    return StateFit(*out, birge)


def _accelerations(velocity: np.ndarray, cov: tuple, span: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Accelerations ``(n, frames, 3)`` per frame² as the smoothed velocities' central
    differences (one-sided at a track's first and last frame) and their variances,
    from the states' covariances (``cov``: the diagonal blocks and those one and two
    frames apart)."""
    diagonal, lag1, lag2 = (c[..., 1, 1] for c in cov)
    nan = np.full(velocity[:, :1].shape, np.nan)
    central = np.concatenate([nan, (velocity[:, 2:] - velocity[:, :-2]) / 2, nan], axis=1)
    central_var = np.concatenate(
        [nan, (diagonal[:, 2:] + diagonal[:, :-2] - 2 * lag2) / 4, nan], axis=1)
    step = velocity[:, 1:] - velocity[:, :-1]
    step_var = diagonal[:, 1:] + diagonal[:, :-1] - 2 * lag1
    forward = np.concatenate([step, nan], axis=1)
    forward_var = np.concatenate([step_var, nan], axis=1)
    backward = np.concatenate([nan, step], axis=1)
    backward_var = np.concatenate([nan, step_var], axis=1)
    inside = np.zeros_like(span)
    inside[:, 1:-1] = span[:, :-2] & span[:, 2:]
    first = span & ~np.concatenate([np.zeros_like(span[:, :1]), span[:, :-1]], axis=1)
    inside, first = inside[..., None], first[..., None]
    accel = np.where(inside, central, np.where(first, forward, backward))
    var = np.where(inside, central_var, np.where(first, forward_var, backward_var))
    return accel, np.maximum(var, 0.0)


def _within_span(present: np.ndarray) -> np.ndarray:
    """Frames from each track's first measured frame to its last."""
    return (np.cumsum(present, axis=1) > 0) & (np.cumsum(present[:, ::-1], axis=1) > 0)[:, ::-1]


def _weights(values: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse variances (0 where a value or its deviation is missing) and the values
    (0 there)."""
    ok = np.isfinite(values) & np.isfinite(sigma) & (sigma > 0)
    return (np.where(ok, 1.0 / np.where(ok, sigma, 1.0) ** 2, 0.0),
            np.where(ok, values, 0.0))


def _solve(w: np.ndarray, m: np.ndarray, pw: np.ndarray, pm: np.ndarray, q: np.ndarray
           ) -> tuple[np.ndarray, tuple, np.ndarray]:
    """The least-squares states of tracks ``(n, frames, 3)`` (position and velocity
    weights and values): states ``(n, frames, 3, 2)``, their covariance blocks (see
    :func:`_selected_inverse`), and the chi-square per track and axis ``(n, 3)``."""
    diagonal, upper = _blocks(w, pw, q)                  # (n, F, 3, 2, 2), (n, F-1, 3, 2, 2)
    rhs = np.stack([w * m, pw * pm], axis=-1)            # (n, F, 3, 2)
    pivots, forward = _eliminate(diagonal, upper, rhs)
    states = _substitute(pivots, upper, forward)
    cov = _selected_inverse(pivots, upper)
    chi2 = np.sum(w * m**2 + pw * pm**2, axis=1) - np.einsum("nfak,nfak->na", states, rhs)
    return states, cov, np.maximum(chi2, 0.0)


def _blocks(w: np.ndarray, pw: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normal matrix's diagonal and upper 2 x 2 blocks: each step's ``Dᵀ Q⁻¹ D``
    (``D = [-F, I]`` the residual ``x_{j+1} - F x_j``) plus the measurements."""
    n, frames, _ = w.shape
    step = np.linalg.inv(STEP_COVARIANCE)[None] / (q**2)[:, None, None]  # (3, 2, 2)
    before = np.einsum("ji,ajk,kl->ail", TRANSITION, step, TRANSITION)   # Fᵀ Q⁻¹ F
    diagonal = np.zeros((n, frames, 3, 2, 2))
    diagonal[:, :-1] += before
    diagonal[:, 1:] += step
    diagonal[..., 0, 0] += w
    diagonal[..., 1, 1] += pw
    upper = np.broadcast_to(-np.einsum("ji,ajk->aik", TRANSITION, step),
                            (n, frames - 1, 3, 2, 2))                    # -Fᵀ Q⁻¹
    return diagonal, upper


def _eliminate(diagonal: np.ndarray, upper: np.ndarray, rhs: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Block forward elimination: the pivots' inverses ``D_j⁻¹`` and the eliminated
    right-hand sides."""
    inverse = np.empty_like(diagonal)
    forward = np.empty_like(rhs)
    inverse[:, 0], forward[:, 0] = np.linalg.inv(diagonal[:, 0]), rhs[:, 0]
    for j in range(1, diagonal.shape[1]):
        lower = np.swapaxes(upper[:, j - 1], -1, -2) @ inverse[:, j - 1]  # Bᵀ D⁻¹
        inverse[:, j] = np.linalg.inv(diagonal[:, j] - lower @ upper[:, j - 1])
        forward[:, j] = rhs[:, j] - np.einsum("naij,naj->nai", lower, forward[:, j - 1])
    return inverse, forward


def _substitute(inverse: np.ndarray, upper: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Block back substitution: the states."""
    states = np.empty_like(forward)
    states[:, -1] = np.einsum("naij,naj->nai", inverse[:, -1], forward[:, -1])
    for j in range(forward.shape[1] - 2, -1, -1):
        rest = forward[:, j] - np.einsum("naij,naj->nai", upper[:, j], states[:, j + 1])
        states[:, j] = np.einsum("naij,naj->nai", inverse[:, j], rest)
    return states


def _selected_inverse(inverse: np.ndarray, upper: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blocks of the normal matrix's inverse (the states' covariances) on its
    diagonal and one and two frames off it, from the elimination's factors:
    ``Σ_j = D_j⁻¹ + G_j Σ_{j+1} G_jᵀ`` and ``Σ_{j,j+k} = -G_j Σ_{j+1,j+k}`` with
    ``G_j = D_j⁻¹ B_j``; ``(n, frames [- 1, - 2], 3, 2, 2)``."""
    frames = inverse.shape[1]
    cov = np.empty_like(inverse)
    lag1 = np.empty_like(inverse[:, :-1])
    lag2 = np.empty_like(inverse[:, :max(frames - 2, 0)])
    cov[:, -1] = inverse[:, -1]
    for j in range(frames - 2, -1, -1):
        gain = inverse[:, j] @ upper[:, j]
        lag1[:, j] = -gain @ cov[:, j + 1]
        if j + 2 < frames:
            lag2[:, j] = -gain @ lag1[:, j + 1]
        cov[:, j] = inverse[:, j] + gain @ cov[:, j + 1] @ np.swapaxes(gain, -1, -2)
    return cov, lag1, lag2
