"""A track's velocity as its neighbours see it (docs/design.md §7.3).

Near a plenoptic camera's focal plane a particle's image barely changes with depth, so
its own frames say little about its depth velocity. Its neighbours, in a flow that is
smooth at the scale of the particles' spacing, say more. At every frame each track's
``neighbours`` nearest other tracks (in voxel units) fit a local linear velocity field
``v(x) = a + B (x - x₀)`` by weighted least squares (each neighbour weighted by the
inverse variance of its own velocity); the field's value at the track, ``a``, is the
prior, and its variance is the fit's, scaled up by the fit's reduced chi-square where
the neighbours scatter more than their variances say (a flow that is not linear there:
turbulence, or a neighbour's error). The track's own velocity is left out of its
prior.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Coefficients of the local linear field (value and three gradients).
_COEFFICIENTS = 4
#: A local fit whose normal matrix is worse conditioned than this (neighbours in a
#: plane or on a line) gives no prior.
CONDITION_LIMIT = 1e10


def neighbour_velocity(positions: np.ndarray, velocities: np.ndarray,
                       velocity_sigma: np.ndarray, scale: np.ndarray, neighbours: int = 12
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Every track's velocity from its neighbours' local linear field, per frame and
    component.

    Parameters
    ----------
    positions
        ``(n_tracks, n_frames, 3)``, NaN where a track has no particle.
    velocities, velocity_sigma
        ``(n_tracks, n_frames, m)``: the velocity components to predict (e.g. depth
        alone, ``m = 1``) and their standard deviations (the neighbours' weights), NaN
        where a track has no velocity.
    scale
        The length of one voxel per axis ``(3,)`` (positions are measured in voxels for
        the neighbour search and the field's gradients).
    neighbours
        Tracks in each local fit (more than 4).

    Returns
    -------
    prior, prior_sigma
        The field's value at each track and its standard deviation, the shape of
        ``velocities``; NaN where a frame has too few tracks with velocities or the
        neighbours do not span a volume.
    """
    if not _is_count(neighbours) or neighbours <= _COEFFICIENTS:
        raise ValueError(f"the velocity prior needs more than {_COEFFICIENTS} neighbours, "
                         f"got {neighbours!r}")
    prior = np.full(velocities.shape, np.nan)
    prior_sigma = np.full(velocities.shape, np.nan)
    for j in range(velocities.shape[1]):
        have = np.flatnonzero(np.all(np.isfinite(positions[:, j]), axis=1)
                              & np.all(np.isfinite(velocities[:, j])
                                       & (velocity_sigma[:, j] > 0), axis=1))
        if len(have) > neighbours:
            where = positions[have, j] / np.asarray(scale, float)
            prior[have, j], prior_sigma[have, j] = _local_fields(
                where, velocities[have, j], velocity_sigma[have, j], int(neighbours))
    return prior, prior_sigma


def _is_count(value) -> bool:
    """A whole number (not a bool)."""
    return (isinstance(value, (int, np.integer, float, np.floating))
            and not isinstance(value, bool) and np.isfinite(value) and value == int(value))


def _nearest_others(where: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` nearest other points of every point ``(n, k)``: the point itself is
    left out by its index (not by its rank, which a tied neighbour may share)."""
    _, nearest = cKDTree(where).query(where, k + 1)
    own = nearest == np.arange(len(where))[:, None]
    own[~own.any(axis=1), -1] = True  # the point is not among them: drop the farthest
    return nearest[~own].reshape(len(where), k)


def _local_fields(where: np.ndarray, velocity: np.ndarray, sigma: np.ndarray, k: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The local linear fields of ``k`` nearest neighbours at every point (``(n, m)``
    each): their value at the point and its standard deviation (NaN where the
    neighbours lie in a plane or a line)."""
    nearest = _nearest_others(where, k)
    offset = where[nearest] - where[:, None, :]                      # (n, k, 3)
    design = np.concatenate([np.ones(offset.shape[:2] + (1,)), offset], axis=2)
    weight = 1.0 / sigma[nearest] ** 2                               # (n, k, m)
    normal = np.einsum("nki,nka,nkj->naij", design, weight, design)  # (n, m, 4, 4)
    flat = np.linalg.cond(normal) > CONDITION_LIMIT
    normal[flat] = np.eye(_COEFFICIENTS)
    cov = np.linalg.inv(normal)
    coef = np.einsum("naij,naj->nai", cov,
                     np.einsum("nki,nka->nai", design, weight * velocity[nearest]))
    fitted = np.einsum("nki,nai->nka", design, coef)
    chi2 = np.sum(weight * (velocity[nearest] - fitted) ** 2, axis=1) / (k - _COEFFICIENTS)
    sd = np.sqrt(cov[..., 0, 0] * np.maximum(chi2, 1.0))
    return np.where(flat, np.nan, coef[..., 0]), np.where(flat, np.nan, sd)
