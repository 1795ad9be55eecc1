"""NumPy twin of :func:`plenocl.ptv.smooth_states` (particles tracked through time,
docs/design.md §7.3): the constant-velocity state-space smoother as a dense
least-squares problem written row by row, one track and axis at a time; the batched
production code is tested against it (``tests/test_track_smoothers.py``)."""

from __future__ import annotations

import numpy as np


def smooth_states_reference(measured: np.ndarray, sigma: np.ndarray, acceleration,
                            prior: np.ndarray | None = None,
                            prior_sigma: np.ndarray | None = None
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`plenocl.ptv.smooth_states` one track and axis at a time, as a dense
    least-squares problem written row by row (without its Birge scaling): positions,
    velocities, accelerations (the velocities' central differences, one-sided at the
    track's ends) and their standard deviations, NaN where a track has no particle."""
    q = np.broadcast_to(np.asarray(acceleration, float), (3,))
    out = [np.full(measured.shape, np.nan) for _ in range(6)]
    step = np.linalg.cholesky(np.linalg.inv(np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]]))).T
    for i in range(measured.shape[0]):
        seen = np.flatnonzero(np.all(np.isfinite(measured[i]), axis=1))
        if len(seen) < 2:
            continue
        span = np.arange(seen[0], seen[-1] + 1)
        for axis in range(3):
            rows, rhs = [], []
            for j, frame in enumerate(span):
                _row(rows, rhs, 2 * j, len(span), measured[i, frame, axis],
                     sigma[i, frame, axis])
                if prior is not None:
                    _row(rows, rhs, 2 * j + 1, len(span), prior[i, frame, axis],
                         prior_sigma[i, frame, axis])
            for j in range(len(span) - 1):  # x_{j+1} - F x_j ~ N(0, q² Q)
                d = np.zeros((2, 2 * len(span)))
                d[0, 2 * j:2 * j + 4] = [-1, -1, 1, 0]
                d[1, 2 * j:2 * j + 4] = [0, -1, 0, 1]
                rows.extend(step @ d / q[axis])
                rhs.extend([0.0, 0.0])
            a, b = np.array(rows), np.array(rhs)
            cov = np.linalg.inv(a.T @ a)
            x = cov @ a.T @ b
            accel, accel_sd = _differences(x[1::2], cov[1::2, 1::2])
            keep = np.isfinite(measured[i, span, axis])
            for k, values in enumerate((x[0::2], x[1::2], accel, np.sqrt(np.diag(cov)[0::2]),
                                        np.sqrt(np.diag(cov)[1::2]), accel_sd)):
                out[k][i, span[keep], axis] = values[keep]
    return tuple(out)


def _differences(v: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of ``v`` (one-sided at its ends) and their standard
    deviations from ``v``'s covariance ``cov``."""
    accel, sd = np.empty(len(v)), np.empty(len(v))
    for j in range(len(v)):
        lo, hi = max(j - 1, 0), min(j + 1, len(v) - 1)
        c = np.zeros(len(v))
        c[hi], c[lo] = 1.0 / (hi - lo), -1.0 / (hi - lo)
        accel[j], sd[j] = c @ v, np.sqrt(c @ cov @ c)
    return accel, sd


def _row(rows: list, rhs: list, column: int, length: int, value: float, sd: float) -> None:
    """One measurement row ``(x[column] - value) / sd`` (none where either is missing)."""
    if np.isfinite(value) and np.isfinite(sd) and sd > 0:
        row = np.zeros(2 * length)
        row[column] = 1.0 / sd
        rows.append(row)
        rhs.append(value / sd)
