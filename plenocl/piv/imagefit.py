"""Particle positions refined against the raw image (docs/design.md §7.2).

A reconstructed volume places a particle within about 0.1-0.2 voxel laterally but only
within 1-1.5 voxels in depth at the paper's optics: MLEM spreads a particle's light
along its depth-elongated footprint and draws it towards the focal plane. The raw image
holds more: an out-of-focus particle lights a disk of microlenses whose size and the
spot in each lens give its depth. Here every peak of a volume starts a fit of its
position and intensity to the raw image, with the camera's exact rays
(:class:`plenocl.optics.raybundle.RayBundle`): Gauss-Newton steps on all particles at
once (each one against the image minus every other particle's current image),
Levenberg-Marquardt damped in each particle's line-of-sight frame (as on the axis, where
the uncertain depth does not lean), with the volume's position as a Gaussian prior
(:data:`PRIOR_VOXELS`). Where the image says little, in the camera's focal zone where
a particle lights one lens, the prior keeps the volume's position; far from it the
image decides. Each pixel's noise is the residual's own scatter over the particle's
lit pixels (never below the camera's noise), so a particle crowded by others or by
ghosts leans on its prior.

One bad particle never ends a fit: each step is bounded (:data:`MAX_STEP_VOXELS`), and a
particle that starts or steps outside the grid and its margin (:data:`GRID_MARGIN_VOXELS`),
or whose sums, step or intensity are not finite, is dropped (its rows NaN,
:attr:`FittedParticles.kept` false) while the others go on without it.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..opencl.threads import thread_count
from ..optics.rawimage import (
    ScaledImage,
    check_image,
    checked_background,
    scaled_background_free,
)
from ..optics.raybundle import Patches, RayBundle
from ..optics.sightline import line_of_sight, sight_frames
from ..options import is_integer, whole_counts
from .devicebundle import DeviceRayBundle
from .fitsums import HOST_CHUNK, DeviceFitSums

#: The fit's method, recorded with every batch field (through
#: :data:`plenocl.piv.refinement.METHOD`) and every tracking run
#: (:mod:`plenocl.batch.tracking`), so that a rerun does not keep positions an earlier fit
#: made. Change it whenever the fit makes other positions or covariances from the same
#: settings (rounding included: a kept field then differs from a fresh one).
METHOD = ("Gauss-Newton with the prior, the Levenberg-Marquardt damping and the step bound "
          "in each line of sight's frame (2026-11-29, issue 45); the posterior covariance "
          "of each normal matrix scaled to a unit diagonal (2026-12-01); a thick lens's lines "
          "of sight through its entrance pupil (2026-12-01 evening); each particle's damping "
          "floor and inverse its own, not its launch's (2026-12-02); the turns to and from "
          "the frames as batched products (2026-12-04)")
#: Uncertainty ``(x, y, z)`` voxels of a peak's position in a reconstructed volume at the
#: paper's optics (``benchmarks/accuracy.py``; docs/design.md §7.1): the fit's prior.
PRIOR_VOXELS = (0.15, 0.15, 1.3)
#: Largest step of one iteration ``(x, y, z)`` voxels.
MAX_STEP_VOXELS = (0.5, 0.5, 1.0)
#: How far ``(x, y, z)`` voxels beyond the grid's outer faces a fitted particle may lie:
#: the farthest the default 4 bounded steps carry a particle that starts inside. Real
#: particles leaving the volume are fitted up to 3 voxels beyond its depth faces (the
#: paper's optics, ``benchmarks/tracking.py``'s series); farther out a fit has diverged.
GRID_MARGIN_VOXELS = (2.0, 2.0, 4.0)


@dataclass(frozen=True)
class ImageFitSettings:
    """Options of the image-space particle fit.

    Attributes
    ----------
    rays
        Aperture samples per particle (:class:`plenocl.optics.raybundle.RayBundle`).
    blur_px
        The optics' blur on the sensor (Gaussian standard deviation, pixels).
    iterations
        Gauss-Newton iterations.
    damping
        Levenberg-Marquardt damping (fraction of each normal matrix's diagonal).
    chunk
        Particles rendered at once (bounds memory). ``None``: the device's
        (:func:`plenocl.piv.fitsums.fit_chunk`: 128 on a CPU device and
        on the host, every particle a GPU's 256 MB of ray scratch holds); the fit is the
        same for any chunk.
    """

    rays: int = 200
    blur_px: float = 0.8
    iterations: int = 4
    damping: float = 0.1
    chunk: int | None = None

    def __post_init__(self) -> None:
        whole_counts(self, ("rays", "iterations", "chunk"))
        for name, low in (("rays", 16), ("iterations", 0), ("chunk", 1)):
            value = getattr(self, name)
            if value is None and name == "chunk":
                continue
            if not is_integer(value) or value < low:
                raise ValueError(f"ImageFitSettings.{name} must be an integer >= {low}, "
                                 f"got {value!r}")
        for name in ("blur_px", "damping"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"ImageFitSettings.{name} must be a positive number, "
                                 f"got {value!r}")


@dataclass(frozen=True)
class FittedParticles:
    """Fitted positions ``(N, 3)`` object-space mm, intensities ``(N,)`` (image units)
    and the posterior standard deviation of each position ``(N, 3)`` mm, one row per
    particle given to :meth:`ImageFit.fit`.

    Attributes
    ----------
    kept
        ``(N,)``: false for a particle the fit dropped (it started or stepped beyond
        the grid's margin, :meth:`ImageFit.inside`, or its fit was not finite); its
        rows are NaN.
    covariance
        ``(N, 3, 3)`` mm²: the posterior covariance of each position, whose diagonal
        ``sigma`` is the root of. Off the axis one camera's uncertainty leans with the
        line of sight, so x and y share the depth's; what a particle's position is known
        to across its line is the covariance seen in the line's frame. ``None``: not
        given (``sigma`` alone).
    """

    positions: np.ndarray
    intensities: np.ndarray
    sigma: np.ndarray
    kept: np.ndarray
    covariance: np.ndarray | None = None

    @property
    def dropped(self) -> int:
        """The number of particles the fit dropped."""
        return int(np.count_nonzero(~self.kept))


class RefinedPeaks(NamedTuple):
    """Peaks refined against their raw images: ``positions`` ``(N, 3)`` fractional voxel
    indices ``(x, y, z)``, their posterior standard deviations ``sigma`` ``(N, 3)``
    voxels (:attr:`FittedParticles.sigma` on the grid) and covariances ``covariance``
    ``(N, 3, 3)`` voxels² (:attr:`FittedParticles.covariance`; ``None`` where the fit
    gave none); NaN rows for the peaks the fit dropped."""

    positions: np.ndarray
    sigma: np.ndarray
    covariance: np.ndarray | None = None


def refined_peaks(fit, grid, index: int, peaks: np.ndarray) -> RefinedPeaks:
    """``fit``'s (:class:`ImageFit` or several cameras' joint fit) refinement of the
    peaks ``(N, 3)`` fractional voxel indices of exposure ``index`` on ``grid``."""
    peaks = np.asarray(peaks, float).reshape(-1, 3)
    if not len(peaks):
        return RefinedPeaks(peaks.copy(), peaks.copy(), np.zeros((0, 3, 3)))
    fitted = fit.fit(index, grid.from_index(peaks))
    spacing = np.asarray(grid.spacing[::-1], float)  # (x, y, z) mm per voxel
    cov = (None if fitted.covariance is None
           else fitted.covariance / (spacing[:, None] * spacing[None, :]))
    return RefinedPeaks(grid.to_index(fitted.positions), fitted.sigma / spacing, cov)


class ImageFit:
    """The raw images of a pair and the rays of their camera, to refine the peaks of the
    reconstructed volumes.

    Parameters
    ----------
    camera
        The (calibrated) camera of the images.
    grid
        The volumes' grid (voxel indices to mm).
    images
        The raw images, one per exposure (``(rows, cols)`` of the camera's sensor).
    settings
        :class:`ImageFitSettings`; ``None``: the defaults.
    queue
        An OpenCL queue (the pipeline's projector's): the particles are rendered on its
        device (:class:`plenocl.piv.devicebundle.DeviceRayBundle`, float32); ``None``:
        on the host (:class:`RayBundle`, NumPy, float64).
    host_sums
        With a ``queue``: sum the normal equations, the model image and the residual on
        the host (NumPy, the rows brought back) instead of on the device
        (:class:`plenocl.piv.fitsums.DeviceFitSums`, float32); the previous path,
        kept for comparison.
    backgrounds
        The median and noise of each image when already known (the reconstructions'
        ``ReconstructionInfo.background`` and ``.noise``, from the same raw images
        without a pixel mask): subtracted as they are instead of computing the medians
        again. ``None``: computed here.
    background_free
        Per image, that image with its background already removed as here
        (:class:`plenocl.optics.rawimage.ScaledImage`: ``max(image - median, 0)``
        divided by its brightest pixel, the median of ``backgrounds``; a
        reconstruction's ``ReconstructionInfo.background_free``, the image its solver
        read), taken as it is instead of removing the background again, and where it
        has a device copy on ``queue``'s context, read there instead of uploading the
        image; ``None`` (or a ``None`` entry): removed here. Needs ``backgrounds`` (its
        noise).

    Notes
    -----
    Every route gives the fit the same image to the bit: removed here or by the
    reconstruction, it is :func:`plenocl.optics.rawimage.scaled_background_free`'s
    float32 values, which the sums read times the scale.
    """

    def __init__(self, camera, grid, images, settings: ImageFitSettings | None = None,
                 queue=None, host_sums: bool = False, backgrounds=None,
                 background_free=None):
        self.settings = ImageFitSettings() if settings is None else settings
        self.bundle = RayBundle.of(camera, self.settings.rays, self.settings.blur_px)
        self.renderer = self.bundle if queue is None else DeviceRayBundle(self.bundle, queue)
        self.sums = (None if queue is None or host_sums
                     else DeviceFitSums(self.renderer, self.settings.chunk))
        self.grid = grid
        self.images, self._device_images, self._host_images = [], {}, {}
        knowns = _backgrounds(backgrounds, len(images))
        frees = [None] * len(images) if background_free is None else list(background_free)
        for raw, known, free in zip(images, knowns, frees, strict=True):
            img, noise = _background_free(raw, camera, known, free)
            self.images.append((img, max(noise, 1e-12)))

    def refine(self, index: int, peaks: np.ndarray) -> np.ndarray:
        """Peaks ``(N, 3)`` fractional voxel indices ``(ix, iy, iz)`` of exposure
        ``index``'s volume refined against its raw image; NaN rows for the peaks the fit
        dropped (:attr:`FittedParticles.kept`)."""
        return refined_peaks(self, self.grid, index, peaks).positions

    def refine_pair(self, peaks_a: np.ndarray, peaks_b: np.ndarray
                    ) -> tuple[RefinedPeaks, RefinedPeaks]:
        """Both exposures' peaks refined, with their uncertainties
        (:class:`RefinedPeaks`), the two fits on two threads where the process may use
        two cores (NumPy releases the interpreter in its array loops)."""
        if thread_count() < 2:
            return (refined_peaks(self, self.grid, 0, peaks_a),
                    refined_peaks(self, self.grid, 1, peaks_b))
        b = _second_thread().submit(refined_peaks, self, self.grid, 1, peaks_b)
        try:
            a = refined_peaks(self, self.grid, 0, peaks_a)
        finally:
            wait([b])  # nothing of this pair runs on after it returns or raises
        return a, b.result()

    def fit(self, index: int, positions: np.ndarray) -> FittedParticles:
        """Fit particles starting at object-space ``positions`` ``(N, 3)`` mm to exposure
        ``index``'s image; the intensities start from a linear least-squares fit.

        A particle that starts or steps where :meth:`inside` refuses (beyond the grid's
        margin, or not finite), or whose fit is not finite, is dropped: NaN rows,
        ``kept`` false (see the module notes); the others are fitted without it."""
        return fit_where_inside(positions, self.inside,
                                lambda start: self._iterate(index, start))

    def inside(self, positions: np.ndarray) -> np.ndarray:
        """Which object-space ``positions`` ``(N, 3)`` mm the fit keeps: finite, inside
        the grid or within :data:`GRID_MARGIN_VOXELS` of its outer faces, and in front
        of the main lens's focal length (where the camera forms an image)."""
        pts = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        out = np.all(np.isfinite(pts), axis=1)
        index = self.grid.to_index(np.where(out[:, None], pts, 0.0))
        margin = np.asarray(GRID_MARGIN_VOXELS)
        high = np.asarray(self.grid.shape[::-1]) - 0.5 + margin  # (x, y, z)
        out &= np.all((index >= -0.5 - margin) & (index <= high), axis=1)
        camera = self.bundle.camera
        return out & (pts[:, 2] > camera.focal_length_mm - camera.object_distance_mm)

    def _iterate(self, index: int, start: np.ndarray):
        """The Gauss-Newton iterations from ``start`` (inside the grid): positions,
        intensities, posterior covariances and which particles are still in the fit (the
        others' rows hold where they were dropped)."""
        noise = self.images[index][1]
        prior = self._prior_mm()
        frames = sight_frames(line_of_sight(self.bundle.camera, start))
        p, cov = start.copy(), prior_covariance(frames, prior)
        device = self.sums is not None and self.sums.fits(
            self.bundle.patches(self.bundle.camera.image_points(p)))
        data = None if device else self._host_image(index)
        intensity = (self._device_start(index, p) if device
                     else self._start_intensity(data, p))
        live = np.isfinite(intensity)
        for _ in range(self.settings.iterations):
            rows = np.flatnonzero(live)
            if not len(rows):
                break
            if device:
                sums = self._device_sums(index, noise, p[rows], intensity[rows])
            else:
                sums = self._host_sums(data, noise, p[rows], intensity[rows])
            step, intensity_step, c = self._solve(*sums, p[rows] - start[rows], prior,
                                                  frames[rows])
            p[rows] += step
            intensity[rows] = np.maximum(intensity[rows] + intensity_step, 0.0)
            cov[rows] = c
            live[rows] = (self.inside(p[rows]) & np.isfinite(intensity[rows])
                          & np.all(np.isfinite(c), axis=(1, 2)))
        return p, intensity, cov, live

    def _on_device(self, p: np.ndarray) -> bool:
        """Whether the sums of particles at ``p`` run on the device (a queue, device
        sums, and their rows fit one buffer)."""
        return self.sums is not None and self.sums.fits(
            self.bundle.patches(self.bundle.camera.image_points(p)))

    def start_intensities(self, index: int, p: np.ndarray) -> np.ndarray:
        """Each particle's intensity at object-space ``p`` ``(n, 3)`` mm by linear least
        squares against exposure ``index``'s image alone (the fit's start)."""
        if self._on_device(p):
            return self._device_start(index, p)
        return self._start_intensity(self._host_image(index), p)

    def normal_equations(self, index: int, p: np.ndarray, intensity: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every particle's Gauss-Newton sums at ``p`` ``(n, 3)`` mm and ``intensity``
        against exposure ``index``'s image (each against the image minus all the others):
        ``J^T J`` ``(n, 4, 4)`` and ``J^T r`` ``(n, 4)`` over (x, y, z mm, intensity),
        and the residual's scatter ``(n,)``, not yet divided by it (what several
        cameras' joint fit adds up, :mod:`plenocl.piv.jointfit`)."""
        noise = self.images[index][1]
        if self._on_device(p):
            return self._device_sums(index, noise, p, intensity)
        return self._host_sums(self._host_image(index), noise, p, intensity)

    def prior_mm(self) -> np.ndarray:
        """The prior's standard deviations ``(lateral, lateral, along)`` mm."""
        return self._prior_mm()

    def _prior_mm(self) -> np.ndarray:
        dz, dy, dx = self.grid.spacing
        return np.asarray(PRIOR_VOXELS) * np.array([dx, dy, dz])

    @property
    def _host_chunk(self) -> int:
        """Particles a host step takes at once: the settings' chunk, else
        :data:`plenocl.piv.fitsums.HOST_CHUNK` (the device's sums take
        :func:`plenocl.piv.fitsums.fit_chunk`'s)."""
        return self.settings.chunk or HOST_CHUNK

    def _chunks(self, n: int):
        return chunk_slices(n, self._host_chunk)

    def _render(self, p: np.ndarray, intensity: np.ndarray, derivatives: bool = True):
        """Image points, patches, and the particle, sensor pixel and rendered rows of
        every patch element the particles reach (the rest are zero)."""
        pts = self.bundle.camera.image_points(p)
        patches = self.bundle.patches(pts)
        elements, rows = self.renderer.render(pts, intensity, patches, derivatives)
        pid, pixel = patches.pixels(self.bundle.camera.pixels[0], elements)
        return pts, patches, pid, pixel, rows

    def _start_intensity(self, data: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Each particle's intensity by linear least squares against the image alone."""
        out = np.empty(len(p))
        for part in self._chunks(len(p)):
            n = part.stop - part.start
            _, _, pid, pixel, rows = self._render(p[part], np.ones(n), derivatives=False)
            unit = rows[0]  # the image of unit intensity: d image / d intensity
            out[part] = np.bincount(pid, unit * data[pixel], minlength=n) / np.maximum(
                np.bincount(pid, unit**2, minlength=n), 1e-30)
        return np.maximum(out, 0.0)

    def _device_start(self, index: int, p: np.ndarray) -> np.ndarray:
        """:meth:`_start_intensity` with the sums on the device."""
        pts = self.bundle.camera.image_points(p)
        data, data_scale = self._device_image(index)
        sums = self.sums.unit_sums(data, pts, self.bundle.patches(pts), data_scale)
        return np.maximum(sums[:, 0] / np.maximum(sums[:, 1], 1e-30), 0.0)

    def _host_image(self, index: int) -> np.ndarray:
        """Exposure ``index``'s background-free image as float64 (made once, for the
        host's sums only: the device takes the float32 image as it is)."""
        if index not in self._host_images:
            self._host_images[index] = self.images[index][0].image().ravel()
        return self._host_images[index]

    def _device_image(self, index: int) -> tuple:
        """Exposure ``index``'s scaled image on the device and its scale: the copy it
        came with where that is on this device's context, else uploaded once."""
        if index not in self._device_images:
            img = self.images[index][0]
            dev = img.on_device
            if dev is None or dev.context != self.renderer.queue.context:
                dev = self.sums.upload(img.values)
            self._device_images[index] = (dev, img.scale)
        return self._device_images[index]

    def _device_sums(self, index: int, noise: float, p: np.ndarray, intensity: np.ndarray):
        """:meth:`_host_sums` with the rendering, the model image and the sums on the
        device (:class:`DeviceFitSums`)."""
        pts = self.bundle.camera.image_points(p)
        data, data_scale = self._device_image(index)
        sums = self.sums.normal_sums(data, pts, intensity, self.bundle.patches(pts),
                                     _to_object(self.bundle.camera, p, pts), data_scale)
        upper = np.triu_indices(4)
        normal = np.zeros((len(p), 4, 4))
        normal[:, upper[0], upper[1]] = normal[:, upper[1], upper[0]] = sums[:, :10]
        mean_sq = sums[:, 15] / np.maximum(sums[:, 14], 1.0)
        return normal, sums[:, 10:14].copy(), np.maximum(np.sqrt(mean_sq), noise)

    def _host_sums(self, data: np.ndarray, noise: float, p: np.ndarray,
                   intensity: np.ndarray):
        """Every particle's ``J^T J`` ``(n, 4, 4)``, ``J^T r`` ``(n, 4)`` (position columns
        in object coordinates) and residual scatter ``(n,)`` at ``p``, against the image
        of all particles, rendered chunk by chunk and summed on the host."""
        n = len(p)
        renders = [self._render(p[part], intensity[part]) for part in self._chunks(n)]
        # one sensor-sized sum per step (not one per chunk); the same order of additions
        model = np.bincount(np.concatenate([r[3] for r in renders]),
                            np.concatenate([r[4][0] for r in renders]), minlength=data.size)
        normal, rhs, scatter = np.zeros((n, 4, 4)), np.zeros((n, 4)), np.zeros(n)
        for part, (pts, patches, pid, pixel, rows) in zip(self._chunks(n), renders,
                                                          strict=True):
            residual = data[pixel] - model[pixel]
            normal[part], rhs[part] = _normal_equations(
                rows, residual, pid, _to_object(self.bundle.camera, p[part], pts),
                part.stop - part.start)
            scatter[part] = _residual_noise(rows[0], residual, pid, patches, noise)
        return normal, rhs, scatter

    def _solve(self, normal, rhs, scatter, offset, prior, frames):
        """One damped Gauss-Newton step of every particle (position mm, intensity) and
        the posterior covariance ``(n, 3, 3)`` of each position, from the sums at ``p``
        (:meth:`_host_sums`, each divided by its residual's scatter here) and ``offset =
        p - start``: :func:`sight_steps`."""
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            normal = normal / scatter[:, None, None] ** 2
            rhs = rhs / scatter[:, None] ** 2
        return sight_steps(normal, rhs, offset, prior, frames, self.settings.damping,
                           self._host_chunk)


def sight_steps(normal: np.ndarray, rhs: np.ndarray, offset: np.ndarray,
                prior: np.ndarray, frames: np.ndarray, damping: float, chunk: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt steps of every particle, solved in its line-of-sight frame.

    Parameters
    ----------
    normal, rhs
        ``J^T J`` ``(n, 4, 4)`` and ``J^T r`` ``(n, 4)`` over (x, y, z mm, intensity),
        already weighed by the noise.
    offset
        ``p - start`` ``(n, 3)`` mm: where each particle is from its prior's centre.
    prior
        The prior's standard deviations ``(lateral, lateral, along)`` mm.
    frames
        Each particle's line-of-sight frame ``(n, 3, 3)``
        (:func:`plenocl.optics.sightline.sight_frames`).
    damping
        Fraction of each normal matrix's diagonal added, in that frame.
    chunk
        Particles solved at once.

    Returns
    -------
    steps, intensity_steps, covariances
        Position steps ``(n, 3)`` mm in the grid's axes, bounded by
        :data:`MAX_STEP_VOXELS` in the frame; intensity steps ``(n,)``; each position's
        posterior covariance ``(n, 3, 3)`` mm². NaN where a particle's equations are
        not finite (the fit drops it; the others are left alone).

    Notes
    -----
    The prior, the damping and the bound all hold in the frame, so the step is the same
    for a particle off the axis as for one on it with the same equations turned: off
    the axis, where the uncertain depth leans with the line, damping by the grid's
    diagonal would slow the step along the line several times more than on the axis
    (docs/design.md §7.2).
    """
    n = len(offset)
    steps, covs = np.full((n, 4), np.nan), np.full((n, 3, 3), np.nan)
    normal, rhs = in_sight_frames(normal, rhs, frames)
    weights = 1.0 / np.asarray(prior, dtype=np.float64) ** 2
    normal[:, [0, 1, 2], [0, 1, 2]] += weights
    rhs[:, :3] -= weights * np.einsum("nji,nj->ni", frames, offset)
    good = np.all(np.isfinite(normal), axis=(1, 2)) & np.all(np.isfinite(rhs), axis=1)
    for part in chunk_slices(n, chunk):
        rows = np.arange(part.start, part.stop)[good[part]]
        if len(rows):
            covs[rows], steps[rows] = _solve_each(normal[rows], rhs[rows], damping)
    limit = np.asarray(MAX_STEP_VOXELS) * prior / np.asarray(PRIOR_VOXELS)
    local = np.clip(steps[:, :3], -limit, limit)
    covs = frames @ covs @ np.swapaxes(frames, 1, 2)  # batched, as in in_sight_frames
    return np.einsum("nij,nj->ni", frames, local), steps[:, 3], covs


def chunk_slices(n: int, size: int):
    """Slices of ``range(n)`` at most ``size`` long, in order."""
    return (slice(i, min(i + size, n)) for i in range(0, n, size))


def in_sight_frames(normal: np.ndarray, rhs: np.ndarray, frames: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations ``J^T J`` ``(n, 4, 4)`` and ``J^T r`` ``(n, 4)`` over (x, y, z,
    intensity) turned to unknowns (across, across, along the line of sight, intensity):
    ``T^T N T`` and ``T^T r`` with ``T = diag(R, 1)``, ``R = frames[k]`` ``(3, 3)``
    whose columns are the frame's axes (:func:`plenocl.optics.sightline.sight_frames`).
    A step ``s`` found there is ``R s`` in the grid's axes."""
    turn = np.zeros((len(frames), 4, 4))
    turn[:, :3, :3] = frames
    turn[:, 3, 3] = 1.0
    # batched products: 8.7x faster than a three-operand einsum (host_work.py)
    return (np.swapaxes(turn, 1, 2) @ normal @ turn, np.einsum("nji,nj->ni", turn, rhs))


def fit_where_inside(positions: np.ndarray, inside, iterate) -> FittedParticles:
    """A fit's :class:`FittedParticles` from ``positions`` ``(N, 3)`` mm: ``iterate``
    (start -> positions, intensities, posterior covariances ``(n, 3, 3)``, still in) runs
    on the positions ``inside`` keeps; the others, and those it drops, get NaN rows and
    ``kept`` false (one camera's fit and several cameras' share it)."""
    start = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(start)
    p = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    intensity = np.full(n, np.nan)
    kept = inside(start)
    if kept.any():
        p[kept], intensity[kept], cov[kept], still = iterate(start[kept])
        kept[np.flatnonzero(kept)[~still]] = False
    p[~kept], intensity[~kept], cov[~kept] = np.nan, np.nan, np.nan
    return FittedParticles(p, intensity, standard_deviations(cov), kept, cov)


def standard_deviations(covariance: np.ndarray) -> np.ndarray:
    """The standard deviations ``(n, 3)`` of covariances ``(n, 3, 3)``: their diagonals'
    roots (NaN rows stay NaN)."""
    return np.sqrt(np.abs(np.diagonal(covariance, axis1=1, axis2=2)))


def prior_covariance(frames: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """The covariance ``(n, 3, 3)`` of a prior with standard deviations ``prior``
    ``(lateral, lateral, along)`` in each particle's line-of-sight frame ``frames``
    ``(n, 3, 3)`` (:func:`plenocl.optics.sightline.sight_frames`): ``R diag(prior²) R^T``,
    what a particle the fit has not moved is known to."""
    return (frames * np.asarray(prior, float) ** 2) @ np.swapaxes(frames, 1, 2)


#: Per calling thread, the thread that fits a pair's second exposure (:func:`_second_thread`).
_SECOND = threading.local()


def _second_thread() -> ThreadPoolExecutor:
    """The calling thread's own helper thread for :meth:`ImageFit.refine_pair`, kept from
    pair to pair, so that its kernels are fetched once (kernel objects are per thread:
    :func:`plenocl.opencl.program.fetch_kernels`); it ends with the calling thread."""
    pool = getattr(_SECOND, "pool", None)
    if pool is None:
        pool = _SECOND.pool = ThreadPoolExecutor(1, thread_name_prefix="plenocl-fit")
    return pool


def _background_free(raw, camera, known, free) -> tuple[ScaledImage, float]:
    """An image without its background and its noise: ``free`` as it is (checked
    against the camera; its noise ``known``'s), else removed from ``raw``
    (:func:`plenocl.optics.rawimage.scaled_background_free`)."""
    if free is None:
        return scaled_background_free(check_image(raw, camera, copy=False), known)
    cols, rows = camera.pixels
    device = getattr(free, "on_device", None)
    if (known is None or not isinstance(free, ScaledImage) or free.shape != (rows, cols)
            or free.dtype != np.float32 or not 0 < free.scale < np.inf
            or (device is not None and (device.shape != free.shape
                                        or device.dtype != np.float32))):
        raise ValueError(f"ImageFit's background_free images must be ScaledImage of float32 "
                         f"({rows}, {cols}) values (and device copy) and a positive scale, "
                         f"with their (median, "
                         f"noise) in backgrounds (a reconstruction's info.background_free "
                         f"and .background, .noise); got {type(free).__name__} "
                         f"{getattr(free, 'dtype', '')} {getattr(free, 'shape', '')}"
                         f"{' without a background' if known is None else ''}")
    return free, checked_background(known)[1]


def _backgrounds(backgrounds, n: int) -> list:
    """:class:`ImageFit`'s ``backgrounds`` as one ``(median, noise)`` or ``None`` per
    image, refused when their number differs from the images'."""
    if backgrounds is None:
        return [None] * n
    out = list(backgrounds)
    if len(out) != n:
        raise ValueError(f"ImageFit got {len(out)} backgrounds for {n} images: give one "
                         "(median, noise) per image, or None to compute them")
    return out


def _to_object(camera, p: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``d (X', Y', d') / d (x, y, z)`` ``(P, 3, 3)`` by central differences."""
    h = 1e-4
    jac = np.empty((len(p), 3, 3))
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h
        jac[:, :, k] = (camera.image_points(p + dp) - camera.image_points(p - dp)) / (2 * h)
    return jac


def _normal_equations(rows: np.ndarray, residual: np.ndarray, pid: np.ndarray,
                      jac: np.ndarray, n: int):
    """``J^T J`` ``(n, 4, 4)`` and ``J^T r`` ``(n, 4)`` per particle, with the position
    columns turned from image-point to object coordinates."""
    cols = [sum(rows[1 + k] * jac[pid, k, j] for k in range(3)) for j in range(3)]
    cols.append(rows[4])
    normal, rhs = np.zeros((n, 4, 4)), np.zeros((n, 4))
    for i in range(4):
        rhs[:, i] = np.bincount(pid, cols[i] * residual, minlength=n)
        for j in range(i, 4):
            normal[:, i, j] = normal[:, j, i] = np.bincount(pid, cols[i] * cols[j], minlength=n)
    return normal, rhs


def _residual_noise(value: np.ndarray, residual: np.ndarray, pid: np.ndarray,
                    patches: Patches, noise: float) -> np.ndarray:
    """Per particle: the residual's RMS over its lit pixels (its own image above 1 % of
    its brightest pixel), at least the camera's ``noise``."""
    n = len(patches.width)
    peak = _peaks(value, pid, n)
    lit = value > 0.01 * peak[pid]
    count = np.bincount(pid[lit], minlength=n)
    mean_sq = np.bincount(pid[lit], residual[lit] ** 2, minlength=n) / np.maximum(count, 1)
    return np.maximum(np.sqrt(mean_sq), noise)


def _peaks(value: np.ndarray, pid: np.ndarray, n: int) -> np.ndarray:
    """Each particle's largest ``value`` (0 without elements). The elements come in patch
    order, so ``pid`` is sorted and one ``maximum.reduceat`` over its runs does it
    (``np.maximum.at``, its unsorted form, was a tenth of the fit's time)."""
    peak = np.zeros(n)
    if not len(pid):
        return peak
    if np.any(pid[1:] < pid[:-1]):
        np.maximum.at(peak, pid, value)
        return peak
    starts = np.flatnonzero(np.concatenate([[True], pid[1:] != pid[:-1]]))
    peak[pid[starts]] = np.maximum.reduceat(value, starts)
    return peak


def _solve_each(normal: np.ndarray, rhs: np.ndarray, damping: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """The posterior covariances ``(n, 3, 3)`` and :func:`_damped_solve`'s steps
    ``(n, 4)`` of finite normal equations, all at once; where NumPy's stacked solvers
    refuse (one singular or unconverged matrix refuses the stack), particle by particle,
    NaN for those that fail alone."""
    try:
        return posterior_covariance(normal), _damped_solve(normal, rhs, damping)
    except np.linalg.LinAlgError:
        cov, steps = np.full((len(normal), 3, 3), np.nan), np.full((len(normal), 4), np.nan)
        for k in range(len(normal)):
            try:
                cov[k] = posterior_covariance(normal[k:k + 1])[0]
                steps[k] = _damped_solve(normal[k:k + 1], rhs[k:k + 1], damping)[0]
            except np.linalg.LinAlgError:
                cov[k] = np.nan
                continue
        return cov, steps


def posterior_covariance(normal: np.ndarray) -> np.ndarray:
    """The position block ``(n, 3, 3)`` of the inverse of normal matrices ``(n, k, k)``
    (the first three unknowns the position), made exactly symmetric.

    Each matrix is scaled to a unit diagonal, inverted and scaled back: a fit's axes
    (millimetres, counts) span many orders of magnitude (condition numbers of 1e8-1e12 on
    the paper pair's fits, under 1e3 once scaled), which the scaling takes out, so the
    inverse is closer than the pseudo-inverse's (``N X - I`` within 4e-11 against 1.6e-8
    there) and several times faster. A matrix whose diagonal is not all finite and
    normal (above the smallest normal float: a particle lighting no pixel has an unseen
    intensity, a zero) or whose scaled inverse is not finite (one exactly singular
    matrix, alone: the others of its stack keep theirs) takes the pseudo-inverse
    (``numpy.linalg.pinv``), which raises ``LinAlgError`` where it cannot converge (a
    NaN diagonal). The fit passes finite matrices alone (docs/design.md §7.2)."""
    diag = np.diagonal(normal, axis1=1, axis2=2)
    scalable = np.all(np.isfinite(diag) & (diag >= np.finfo(np.float64).tiny), axis=1)
    inverse = np.empty(normal.shape)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        root = np.sqrt(diag[scalable])
        outer = root[:, :, None] * root[:, None, :]
        inverse[scalable] = _each_inverse(normal[scalable] / outer) / outer
    scalable &= np.all(np.isfinite(inverse), axis=(1, 2))
    if not scalable.all():
        inverse[~scalable] = np.linalg.pinv(normal[~scalable])
    cov = inverse[:, :3, :3]
    return (cov + np.swapaxes(cov, 1, 2)) / 2


def _each_inverse(matrices: np.ndarray) -> np.ndarray:
    """The inverses of ``matrices`` ``(n, k, k)``, NaN for those exactly singular: one
    such matrix no longer sends the whole stack to the pseudo-inverse (a particle's
    covariance then depended on the others inverted with it)."""
    try:
        return np.linalg.inv(matrices)
    except np.linalg.LinAlgError:
        out = np.full(matrices.shape, np.nan)
        for k, matrix in enumerate(matrices):
            try:
                out[k] = np.linalg.inv(matrix)
            except np.linalg.LinAlgError:
                continue
        return out


def _damped_solve(normal: np.ndarray, rhs: np.ndarray, damping: float) -> np.ndarray:
    """Levenberg-Marquardt steps ``(n, 4)`` for normal matrices ``(n, 4, 4)``, each
    particle's alone: its damping's floor is its own largest diagonal's (it was the
    stack's, so a particle's step depended on the others solved with it: a batch's field
    moved by 0.22 voxel with the fit's particles per launch)."""
    diag = np.diagonal(normal, axis1=1, axis2=2)
    top = diag.max(axis=1, keepdims=True, initial=1.0)  # each particle its own
    scale = np.maximum(diag, 1e-12 * top + 1e-300)
    damped = normal + np.einsum("pi,ij->pij", damping * scale, np.eye(4))
    damped[:, 3, 3] = np.maximum(damped[:, 3, 3], 1e-300)
    return np.linalg.solve(damped, rhs[..., None])[..., 0]
