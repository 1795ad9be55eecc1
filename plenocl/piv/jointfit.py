"""Particles fitted to several cameras' raw images at once (docs/design.md §7.2, §6.7;
issue 49).

Each camera's :class:`plenocl.piv.imagefit.ImageFit` gives every particle's Gauss-Newton
sums against its own image (:meth:`~plenocl.piv.imagefit.ImageFit.normal_equations`:
over the position in world mm and that camera's intensity). One particle has one
position and an intensity per camera (the cameras' gains and apertures need not agree),
so its normal equations are ``(3 + C) x (3 + C)``: the position block is the sum of the
cameras' blocks, each divided by its residual's scatter squared, and each intensity is
tied to the position by its own camera's cross terms. The prior on the volume's position
is isotropic, the single camera's along-the-line width in every direction (several
cameras see depth: no line of sight is the uncertain one), and so is the step bound.
Levenberg-Marquardt damped as the single camera's fit; a particle whose sums are not
finite, or that steps outside any camera's fit region, is dropped.
"""

from __future__ import annotations

import numpy as np

from .imagefit import (
    MAX_STEP_VOXELS,
    PRIOR_VOXELS,
    FittedParticles,
    ImageFit,
    ImageFitSettings,
    RefinedPeaks,
    fit_where_inside,
    posterior_covariance,
    refined_peaks,
)


class JointImageFit:
    """The raw images of a pair from several cameras, to refine the volumes' peaks.

    Parameters
    ----------
    cameras
        The (posed, calibrated) cameras.
    grid
        The volumes' world grid.
    images
        Per camera, its raw images of the exposures (``[[a_1, b_1], [a_2, b_2], ...]``).
    settings, queue
        As :class:`plenocl.piv.imagefit.ImageFit`'s (one for every camera).
    backgrounds
        Per camera, its images' ``(median, noise)`` or ``None``.
    """

    def __init__(self, cameras, grid, images, settings: ImageFitSettings | None = None,
                 queue=None, backgrounds=None) -> None:
        if len(images) != len(cameras):
            raise ValueError(f"one list of images per camera: {len(cameras)} cameras, "
                             f"{len(images)} lists")
        known = backgrounds if backgrounds is not None else [None] * len(cameras)
        self.fits = [ImageFit(cam, grid, raws, settings, queue=queue, backgrounds=bg)
                     for cam, raws, bg in zip(cameras, images, known, strict=True)]
        self.grid, self.settings = grid, self.fits[0].settings
        spacing = np.array(grid.spacing[::-1])
        self.prior = np.full(3, max(np.asarray(PRIOR_VOXELS) * spacing))
        self.max_step = np.full(3, max(np.asarray(MAX_STEP_VOXELS) * spacing))

    def refine(self, index: int, peaks: np.ndarray) -> np.ndarray:
        """:meth:`plenocl.piv.imagefit.ImageFit.refine` against every camera's image of
        exposure ``index``."""
        return refined_peaks(self, self.grid, index, peaks).positions

    def refine_pair(self, peaks_a: np.ndarray, peaks_b: np.ndarray
                    ) -> tuple[RefinedPeaks, RefinedPeaks]:
        """Both exposures' peaks refined, with their uncertainties
        (:class:`plenocl.piv.imagefit.RefinedPeaks`)."""
        return (refined_peaks(self, self.grid, 0, peaks_a),
                refined_peaks(self, self.grid, 1, peaks_b))

    def inside(self, positions: np.ndarray) -> np.ndarray:
        """Which positions every camera's fit keeps."""
        return np.logical_and.reduce([f.inside(positions) for f in self.fits])

    def fit(self, index: int, positions: np.ndarray) -> FittedParticles:
        """Fit particles starting at world ``positions`` ``(N, 3)`` mm to every camera's
        image of exposure ``index``; the intensities (their mean over the cameras) start
        from each camera's linear least squares. Dropped particles: NaN rows."""
        return fit_where_inside(positions, self.inside,
                                lambda start: self._iterate(index, start))

    def _iterate(self, index: int, start: np.ndarray):
        """The joint Gauss-Newton iterations from ``start``: positions, mean intensities,
        posterior covariances and which particles are still in the fit."""
        p = start.copy()
        cov = np.tile(np.diag(np.asarray(self.prior, float) ** 2), (len(start), 1, 1))
        intens = np.stack([f.start_intensities(index, p) for f in self.fits])
        live = np.all(np.isfinite(intens), axis=0)
        for _ in range(self.settings.iterations):
            rows = np.flatnonzero(live)
            if not len(rows):
                break
            normal, rhs = self._system(index, p[rows], intens[:, rows],
                                       p[rows] - start[rows])
            steps, c = _solve(normal, rhs, self.settings.damping)
            p[rows] += np.clip(steps[:, :3], -self.max_step, self.max_step)
            intens[:, rows] = np.maximum(intens[:, rows] + steps[:, 3:].T, 0.0)
            cov[rows] = c
            live[rows] = (self.inside(p[rows]) & np.all(np.isfinite(steps), axis=1)
                          & np.all(np.isfinite(c), axis=(1, 2)))
        return p, intens.mean(axis=0), cov, live

    def _system(self, index: int, p: np.ndarray, intens: np.ndarray, offset: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """The ``(n, 3 + C, 3 + C)`` normal equations and ``(n, 3 + C)`` right-hand sides
        of every camera's sums with the prior (module documentation)."""
        c_count, n = len(self.fits), len(p)
        normal, rhs = np.zeros((n, 3 + c_count, 3 + c_count)), np.zeros((n, 3 + c_count))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for c, fit in enumerate(self.fits):
                block, right, scatter = fit.normal_equations(index, p, intens[c])
                w = 1.0 / scatter ** 2
                normal[:, :3, :3] += block[:, :3, :3] * w[:, None, None]
                normal[:, :3, 3 + c] = block[:, :3, 3] * w[:, None]
                normal[:, 3 + c, :3] = block[:, 3, :3] * w[:, None]
                normal[:, 3 + c, 3 + c] = block[:, 3, 3] * w
                rhs[:, :3] += right[:, :3] * w[:, None]
                rhs[:, 3 + c] = right[:, 3] * w
        information = 1.0 / self.prior ** 2
        normal[:, [0, 1, 2], [0, 1, 2]] += information
        rhs[:, :3] -= offset * information
        return normal, rhs


def _solve(normal: np.ndarray, rhs: np.ndarray, damping: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt steps ``(n, k)`` and the positions' posterior covariances
    ``(n, 3, 3)``, all particles at once; where the stacked solve refuses (one singular
    system refuses the stack), particle by particle; NaN rows for particles whose system
    is not finite or singular."""
    n, k = rhs.shape
    steps, cov = np.full((n, k), np.nan), np.full((n, 3, 3), np.nan)
    good = np.flatnonzero(np.all(np.isfinite(normal), axis=(1, 2))
                          & np.all(np.isfinite(rhs), axis=1))
    diag = np.maximum(np.diagonal(normal[good], axis1=1, axis2=2), 1e-300)
    damped = normal[good] + np.einsum("pi,ij->pij", damping * diag, np.eye(k))
    try:
        steps[good] = np.linalg.solve(damped, rhs[good][..., None])[..., 0]
        cov[good] = posterior_covariance(normal[good])
    except np.linalg.LinAlgError:
        for j, i in enumerate(good):
            try:
                steps[i] = np.linalg.solve(damped[j], rhs[i])
                cov[i] = posterior_covariance(normal[i:i + 1])[0]
            except np.linalg.LinAlgError:
                continue
    return steps, cov
