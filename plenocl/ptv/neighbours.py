"""A track's velocity as its neighbours see it (docs/design.md §7.3).

Near a plenoptic camera's focal plane a particle's image barely changes with depth, so
its own frames say little about its depth velocity. Its neighbours, in a flow that is
smooth at the scale of the particles' spacing, say more. At every frame each track's
``neighbours`` nearest other tracks (in voxel units) fit a local linear velocity field
``v(x) = a + B (x - x₀)`` by weighted least squares (each neighbour weighted by the
inverse variance of its own velocity); the field's value at the track, ``a``, is the
prior, and its variance is the fit's, scaled up by the fit's reduced chi-square where
the neighbours scatter more than their variances say (a flow that is not linear there:
turbulence, or a neighbour's error). The track's own velocity is left out of its prior.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Coefficients of the local linear field (value and three gradients).
_COEFFICIENTS = 4


def neighbour_velocity(positions: np.ndarray, velocities: np.ndarray,
                       velocity_sigma: np.ndarray, scale, neighbours: int = 12
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Every track's velocity from its neighbours' local linear field, per frame and
    axis.

    Parameters
    ----------
    positions, velocities, velocity_sigma
        ``(n_tracks, n_frames, 3)``, NaN where a track has no velocity.
    scale
        The length of one voxel per axis ``(3,)`` (positions are measured in voxels for
        the neighbour search and the field's gradients).
    neighbours
        Tracks in each local fit (more than 4).

    Returns
    -------
    prior, prior_sigma
        The field's value at each track and its standard deviation, the shape of
        ``velocities``; NaN where a frame has too few tracks with velocities.
    """
    if int(neighbours) != neighbours or neighbours <= _COEFFICIENTS:
        raise ValueError(f"the velocity prior needs more than {_COEFFICIENTS} neighbours, "
                         f"got {neighbours!r}")
    prior = np.full(velocities.shape, np.nan)
    prior_sigma = np.full(velocities.shape, np.nan)
    for j in range(velocities.shape[1]):
        have = np.flatnonzero(np.all(np.isfinite(velocities[:, j])
                                     & np.isfinite(positions[:, j])
                                     & (velocity_sigma[:, j] > 0), axis=1))
        if len(have) > neighbours:
            where = positions[have, j] / np.asarray(scale, float)
            value, sd = _local_fields(where, velocities[have, j], velocity_sigma[have, j],
                                      int(neighbours))
            prior[have, j], prior_sigma[have, j] = value, sd
    return prior, prior_sigma


def _local_fields(where: np.ndarray, velocity: np.ndarray, sigma: np.ndarray, k: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The local linear fields of ``k`` nearest neighbours at every point (``(n, 3)``
    each): their value at the point and its standard deviation."""
    _, nearest = cKDTree(where).query(where, k + 1)
    nearest = nearest[:, 1:]                                         # the point itself out
    offset = where[nearest] - where[:, None, :]                      # (n, k, 3)
    design = np.concatenate([np.ones(offset.shape[:2] + (1,)), offset], axis=2)
    weight = 1.0 / sigma[nearest] ** 2                               # (n, k, 3)
    normal = np.einsum("nki,nka,nkj->naij", design, weight, design)  # (n, 3, 4, 4)
    rhs = np.einsum("nki,nka->nai", design, weight * velocity[nearest])
    cov = np.linalg.pinv(normal)
    coef = np.einsum("naij,naj->nai", cov, rhs)
    fitted = np.einsum("nki,nai->nka", design, coef)
    chi2 = np.sum(weight * (velocity[nearest] - fitted) ** 2, axis=1) / (k - _COEFFICIENTS)
    return coef[..., 0], np.sqrt(cov[..., 0, 0] * np.maximum(chi2, 1.0))
