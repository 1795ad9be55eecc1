"""Particles tracked through a time-resolved recording of one camera (docs/design.md
§7.3): :func:`track`.

Each frame is reconstructed (:func:`plenocl.reconstruct`'s chain), its volume's peaks
are fitted to the frame's raw image (:class:`plenocl.piv.imagefit.ImageFit`), the
particles of consecutive frames are linked (:func:`plenocl.ptv.link`; the first step
predicted by the correlation of the first two volumes) and every track is smoothed
(:func:`smooth_tracks`: a constant-velocity state-space smoother weighted by the fit's
variances, with its neighbours' depth velocity as a prior).
:func:`bin_tracks` turns tracks into an Eulerian field on interrogation windows.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..grid import Grid
from ..optics.rawimage import check_exposure, check_image
from ..options import is_integer, is_number, whole_counts, with_keywords
from ..peaks import find_particles, merge_close
from ..piv import PIVSettings, piv3d
from ..piv.imagefit import ImageFit, ImageFitSettings
from ..piv.jointfit import JointImageFit
from ..piv.refinement import (
    FITTED_POSITION_SIGMA,
    SEARCH,
    FocalZone,
    ParticlePairs,
    predicted,
    window_means,
)
from ..piv.validation import normalized_median_test, replace_outliers
from ..ptv import Tracks, link, neighbour_velocity, smooth, smooth_states
from ..reconstruction import ProjectionOperator, ReconstructionSettings, run_reconstruction
from ..vectorfield import PIVResult

#: The tracker's own method (merging, linking, smoothing, the binned field), recorded in
#: every tracking run's key with the methods it calls (:mod:`plenocl.batch.tracking`): a
#: rerun tracks again instead of keeping tracks an earlier tracker made. Change it
#: whenever :func:`track` or :func:`bin_tracks` makes other tracks or fields from the
#: same frames and settings (rounding included).
METHOD = ("fitted particles merged, linked from the first step's correlation, smoothed "
          "by the constant-velocity state-space smoother with the neighbours' depth "
          "velocity prior; fields from the refinement's window means (2026-12-01)")
#: Standard deviation (x, y, z voxels) of a volume's peak without the image fit: the
#: reconstruction draws particles up to about a voxel towards the focal plane.
PEAK_SIGMA_VOXELS = (0.1, 0.1, 1.0)
#: Fitted particles of one frame closer than this ``(x, y, z)`` voxels are one particle
#: seen twice (docs/design.md §7.3): about 0.7 of the paper optics' lateral and depth
#: resolution (one microlens, 8.6 voxels).
MERGE = (0.7, 0.7, 6.0)
#: Below this share of a step's particles linked, the step is reported (a warning).
LINKED_FLOOR = 0.2


@dataclass(frozen=True)
class TrackSettings:
    """Every option of :func:`track`.

    Attributes
    ----------
    reconstruction
        Each frame's reconstruction (:class:`~plenocl.reconstruction.ReconstructionSettings`;
        by default :func:`plenocl.reconstruct`'s).
    image_fit
        The fit of each volume's peaks to its raw image
        (:class:`~plenocl.piv.imagefit.ImageFitSettings`); ``None``: the peaks as they
        are, with :data:`PEAK_SIGMA_VOXELS` as their uncertainty.
    piv
        The correlation of the first two volumes that predicts the first step.
    threshold
        A peak counts as a particle above this fraction of its volume's bright level:
        the brightest peaks' level once the brightest 0.5 % are set aside
        (:func:`plenocl.peaks.find_particles` with ``reference="robust"``), so that a
        few spurious bright voxels of a densely seeded frame do not hide its particles.
    search
        Largest distance ``(x, y, z)`` voxels between a predicted position and its
        partner in the next frame.
    gap
        Frames a track may miss (a particle the reconstruction lost) and continue.
    window
        Frames of each local polynomial fit along a track (odd, >= 3): their velocities
        make the neighbours' prior (docs/design.md §7.3).
    degree
        The local polynomials' degree (0-3; 1, a straight line over ``window`` frames,
        measured). The tracks' positions, velocities and accelerations come from the
        state-space smoother whatever the degree.
    refits
        Times every tracked particle is fitted to its raw image again, starting from its
        smoothed track, and the tracks smoothed again (needs ``image_fit``).
    min_length
        Tracks seen in fewer frames are left out (>= 2).
    acceleration
        The state-space smoother's acceleration noise (voxels per frame², per axis): the
        standard deviation of a particle's change of velocity over one frame.
    merge
        Fitted particles of one frame within this ellipsoid ``(x, y, z)`` voxels of a
        brighter one are that particle seen twice (two peaks of its depth-elongated
        image), merged into it; ``(0, 0, 0)``: none merged.
    neighbours
        Tracks whose local linear velocity field is each track's depth velocity prior
        (more than 4; 0: none). Near the focal plane a particle's own images barely
        measure its depth, and the prior carries it there (docs/design.md §7.3).
    """

    reconstruction: ReconstructionSettings = field(default_factory=ReconstructionSettings)
    image_fit: ImageFitSettings | None = field(default_factory=ImageFitSettings)
    piv: PIVSettings = field(default_factory=PIVSettings)
    threshold: float = 0.1
    search: tuple[float, float, float] = SEARCH
    gap: int = 1
    window: int = 7
    degree: int = 1
    refits: int = 1
    min_length: int = 4
    acceleration: float = 0.05
    neighbours: int = 12
    merge: tuple[float, float, float] = MERGE

    def __post_init__(self) -> None:
        if isinstance(self.image_fit, bool):
            object.__setattr__(self, "image_fit", ImageFitSettings() if self.image_fit else None)
        whole_counts(self, ("min_length", "gap", "refits", "window", "degree", "neighbours"))
        self._check_distances()
        if not 0 < self.threshold < 1:
            raise ValueError(f"TrackSettings.threshold must lie between 0 and 1 (a fraction "
                             f"of the volume's bright level), got {self.threshold}")
        if not is_integer(self.min_length) or self.min_length < 2:
            raise ValueError(f"TrackSettings.min_length must be an integer >= 2 (frames), "
                             f"got {self.min_length!r}")
        for name in ("gap", "refits"):
            value = getattr(self, name)
            if not is_integer(value) or value < 0:
                raise ValueError(f"TrackSettings.{name} must be an integer >= 0, got {value!r}")
        if not (is_integer(self.window) and is_integer(self.degree)) or self.window < 3 \
                or self.window % 2 == 0 or self.degree not in (0, 1, 2, 3):
            raise ValueError(f"TrackSettings.window must be an odd number of frames >= 3 and "
                             f"degree 0-3, got window={self.window}, degree={self.degree}")
        self._check_smoother()

    def _check_distances(self) -> None:
        """The search range and the merge radius as three floats, or refused."""
        object.__setattr__(self, "search", _three_distances(
            "search", self.search, "three positive distances (x, y, z voxels)", 0.0))
        object.__setattr__(self, "merge", _three_distances(
            "merge", self.merge, "three distances >= 0 (x, y, z voxels; 0 merges nothing)",
            None))

    def _check_smoother(self) -> None:
        """Refuse a state-space smoother that cannot run, and a velocity prior that
        could never be formed."""
        if not (is_number(self.acceleration) and np.isfinite(self.acceleration)
                and self.acceleration > 0):
            raise ValueError(f"TrackSettings.acceleration must be a positive number (voxels "
                             f"per frame squared), got {self.acceleration!r}")
        n = self.neighbours
        if not is_integer(n) or not (n == 0 or n > 4):
            raise ValueError(f"TrackSettings.neighbours must be 0 (no velocity prior) or an "
                             f"integer above 4 (a local linear field), got {n!r}")
        if n and self.degree == 0:
            raise ValueError(f"TrackSettings.degree = 0 gives the local fits no velocity, so "
                             f"the neighbours' depth prior (neighbours = {n}) would have none "
                             "to take: give degree 1-3, or neighbours = 0 to track without "
                             "the prior")


def _three_distances(name: str, value, what: str, above: float | None
                     ) -> tuple[float, float, float]:
    """``value`` as three finite floats, each above ``above`` (``None``: at least 0),
    or refused naming ``TrackSettings.<name>`` and ``what`` it must be."""
    values = np.ravel(np.asarray(value, dtype=object)) if value is not None else []
    ok = len(values) == 3 and all(is_number(v) and np.isfinite(v) for v in values)
    if ok:
        values = tuple(float(v) for v in values)
        ok = all(v > above if above is not None else v >= 0 for v in values)
    if not ok:
        raise ValueError(f"TrackSettings.{name} must be {what}, got {value!r}")
    return values


@dataclass
class FrameParticles:
    """One frame's particles: positions ``(N, 3)`` mm and voxel indices, their standard
    deviations ``(N, 3)`` mm and intensities ``(N,)``; the median and noise the
    reconstruction removed from each camera's frame (``None`` when it removed none); the
    peaks the fit to the raw images dropped
    (:class:`~plenocl.piv.imagefit.FittedParticles`)."""

    positions: np.ndarray
    index: np.ndarray
    sigma: np.ndarray
    intensities: np.ndarray
    background: list[tuple[float, float]] | None = None
    dropped: int = 0


def track(frames, projector: ProjectionOperator | list, dt: float,
          settings: TrackSettings | None = None, *,
          progress: Callable[[int, int], None] | None = None, **options) -> Tracks:
    """Track the particles of a time-resolved recording.

    Parameters
    ----------
    frames
        The raw images, one per frame at a constant interval (a sequence of
        ``(rows, cols)`` arrays of the projector's camera, or one ``(frames, rows,
        cols)`` array), at least ``settings.min_length`` of them. Several cameras: one
        such sequence per camera, frame ``k`` of each taken at the same instant.
    projector
        A :class:`plenocl.Projector` (reused for every frame); several cameras: a list
        of them, one per camera, on one world grid and queue (docs/design.md §6.7): each
        frame is one joint reconstruction, its particles are fitted to every camera's
        image at once (:class:`plenocl.piv.jointfit.JointImageFit`), and no focal zone
        weighs the neighbours' depth prior (the cameras see depth).
    dt
        The time between frames (velocities are mm per unit of ``dt``).
    settings
        :class:`TrackSettings` (``None``: the defaults); its fields may be given as
        keywords instead.
    progress
        Called as ``progress(done, total)`` after each frame's particles and each frame's
        refit (``total``: the frames times one plus the refits), e.g. to draw a bar.

    Returns
    -------
    plenocl.ptv.Tracks
        The tracks seen in at least ``settings.min_length`` frames; ``dropped`` counts
        the particles the fits to the raw images dropped (a fit that left the grid or
        was not finite, docs/design.md §7.2), which the tracks miss.
    """
    settings = with_keywords(TrackSettings, settings, options, "track")
    if progress is not None and not callable(progress):
        raise TypeError(f"progress must be a callable progress(done, total), got {progress!r}")
    recording = Recording(frames, projector, settings.min_length)
    dt = _check_dt(dt)
    refits = settings.refits if settings.image_fit is not None else 0
    steps = _Steps(progress, len(recording.frames) * (1 + refits))
    particles, first_step = _frame_particles(recording, settings, steps)
    table = link([p.index for p in particles], settings.search, first_step, settings.gap)
    _warn_if_unlinked(table)
    table = table[(table >= 0).sum(axis=1) >= settings.min_length]
    tracks = smooth_tracks(*_gather(table, particles), dt, projector, settings)
    dropped = sum(part.dropped for part in particles)
    for _ in range(refits):
        tracks, lost = _refit(tracks, recording, particles, settings, steps)
        dropped += lost
    if dropped:  # a refit's dropped particle may leave its track too short
        tracks = tracks.longer_than(settings.min_length)
    return dataclasses.replace(tracks, dropped=dropped)


class _Steps:
    """The progress of :func:`track`: counts its steps and reports them."""

    def __init__(self, progress: Callable[[int, int], None] | None, total: int) -> None:
        self.progress, self.total, self.done = progress, total, 0

    def advance(self) -> None:
        """One more step done."""
        self.done += 1
        if self.progress is not None:
            self.progress(self.done, self.total)


def _refit(tracks: Tracks, recording: Recording, particles: list[FrameParticles],
           settings: TrackSettings, steps: _Steps) -> tuple[Tracks, int]:
    """Every tracked particle fitted to its frame again from its smoothed position, and
    the tracks smoothed again; and the particles the fits dropped (NaN: the track misses
    that frame)."""
    measured, sigma = np.full_like(tracks.measured, np.nan), np.full_like(tracks.measured, np.nan)
    intensity = np.full_like(tracks.intensities, np.nan)
    dropped = 0
    for k, part in enumerate(particles):
        rows = np.all(np.isfinite(tracks.measured[:, k]), axis=1)
        if rows.any():
            fitted = recording.image_fit(k, part.background, settings.image_fit).fit(
                0, tracks.positions[rows, k])
            measured[rows, k], sigma[rows, k] = fitted.positions, fitted.sigma
            intensity[rows, k] = fitted.intensities
            dropped += fitted.dropped
        steps.advance()
    return (smooth_tracks(measured, sigma, intensity, tracks.dt, recording.operator,
                          settings), dropped)


def smooth_tracks(measured: np.ndarray, sigma: np.ndarray, intensity: np.ndarray, dt: float,
                  projector: ProjectionOperator | list,
                  settings: TrackSettings | None = None
                  ) -> Tracks:
    """Tracks from their measured positions, smoothed as :func:`track` smooths them
    (docs/design.md §7.3).

    With ``settings.neighbours``, local polynomial fits along each track
    (``settings.window``, ``.degree``) give first velocities, and the neighbouring
    tracks' local linear field of those velocities is each track's depth velocity
    prior (:func:`plenocl.ptv.neighbour_velocity`, each neighbour weighted by its
    variance plus the focal zone's systematic depth term,
    :meth:`~plenocl.piv.refinement.FocalZone.ambiguity`);
    the constant-velocity state-space smoother (:func:`plenocl.ptv.smooth_states`,
    acceleration noise ``settings.acceleration`` voxels per frame²) then gives the
    positions, velocities and accelerations (the velocities' central differences).

    Parameters
    ----------
    measured, sigma
        Positions ``(n_tracks, n_frames, 3)`` mm and their standard deviations, NaN
        where a track has no particle.
    intensity
        ``(n_tracks, n_frames)``.
    dt
        The time between frames.
    projector
        The recording's projector (its camera and grid: the focal zone and the voxel);
        several cameras' list of them (their world grid; no focal zone).
    settings
        :class:`TrackSettings` (``None``: the defaults).

    Returns
    -------
    plenocl.ptv.Tracks
        Velocities per unit of ``dt``; ``measured``, ``measured_sigma`` and the
        intensities as given.
    """
    settings = settings or TrackSettings()
    projectors = list(projector) if isinstance(projector, (list, tuple)) else [projector]
    grid = projectors[0].grid
    voxel = np.asarray(grid.spacing[::-1])
    prior = prior_sigma = None
    if settings.neighbours:
        camera = projectors[0].camera
        focus = FocalZone.along_grid(camera, grid) if len(projectors) == 1 else None
        prior, prior_sigma = _depth_prior(measured, sigma, grid, focus, settings)
    fit = smooth_states(measured, sigma, settings.acceleration * voxel, prior, prior_sigma)
    return Tracks(fit.positions, measured, sigma, intensity, fit.velocities / dt,
                  fit.accelerations / dt**2, fit.position_sigma, fit.velocity_sigma / dt,
                  fit.acceleration_sigma / dt**2, dt)


def _depth_prior(measured: np.ndarray, sigma: np.ndarray, grid: Grid,
                 focus: FocalZone | None, settings: TrackSettings
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Each track's depth velocity (per frame) from its neighbours' local linear field
    of the local lines' velocities, each neighbour weighted by its line's variance plus
    the focal zone's systematic depth term (a neighbour near the focal plane counts
    little; ``focus`` ``None``: none); no lateral prior (NaN): laterally a track's own
    frames decide."""
    poly = smooth(measured, sigma, 1.0, settings.window, settings.degree)
    voxel = np.asarray(grid.spacing[::-1])
    depth = grid.to_index(np.nan_to_num(poly.positions).reshape(-1, 3))[:, 2]
    bias = 0.0 if focus is None else focus.ambiguity(depth) * voxel[2]
    own = np.hypot(poly.velocity_sigma[..., 2:],
                   np.reshape(bias, poly.positions.shape[:2] + (1,)) if focus is not None else 0.0)
    z, z_sigma = neighbour_velocity(poly.positions, poly.velocities[..., 2:], own, voxel,
                                    settings.neighbours)
    if np.isnan(z).all() and np.isfinite(poly.velocities[..., 2]).any():
        most = int(np.isfinite(poly.velocities[..., 2]).sum(axis=0).max())
        warnings.warn(f"the neighbours' depth prior was formed in no frame: it needs more "
                      f"than neighbours = {settings.neighbours} tracks with a velocity in a "
                      f"frame, and the most in any frame is {most}; lower neighbours "
                      "([tracking] neighbours, TrackSettings) or set it to 0 to track "
                      "without the prior", stacklevel=3)
    prior = np.full(poly.velocities.shape, np.nan)
    prior_sigma = np.full(poly.velocities.shape, np.nan)
    prior[..., 2:], prior_sigma[..., 2:] = z, z_sigma
    return prior, prior_sigma


def _frame_particles(recording: Recording, settings: TrackSettings, steps: _Steps):
    """Every frame's particles, and the first step's predictor (the correlation of the
    first two volumes, in voxel indices)."""
    particles, volumes = [], []
    for k in range(len(recording.frames)):
        vol, info = run_reconstruction(recording.images(k), recording.operator,
                                       settings.reconstruction)
        particles.append(_particles(recording, k, vol, info, settings))
        steps.advance()
        if len(volumes) < 2:
            volumes.append(vol)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the window-count notes of a field used once
        field_01 = piv3d(volumes[0], volumes[1], settings.piv, queue=recording.queue)

    def first_step(points: np.ndarray) -> np.ndarray:
        return predicted(field_01, points + predicted(field_01, points) / 2)

    return particles, first_step


def _particles(recording: Recording, k: int, vol: np.ndarray, info,
               settings: TrackSettings) -> FrameParticles:
    """Frame ``k``'s volume's peaks, fitted to its raw images when ``settings.image_fit``."""
    grid = recording.grid
    peaks, _ = find_particles(vol, settings.threshold, reference="robust")
    voxel = np.asarray(grid.spacing[::-1])
    if settings.image_fit is None or not len(peaks):
        sigma = np.broadcast_to(np.asarray(PEAK_SIGMA_VOXELS) * voxel, peaks.shape)
        return FrameParticles(grid.from_index(peaks), peaks, sigma.copy(),
                              np.ones(len(peaks)))
    known = recording.backgrounds(info)
    fitted = recording.image_fit(k, known, settings.image_fit).fit(0, grid.from_index(peaks))
    ok = fitted.kept
    positions, sigma = fitted.positions[ok], fitted.sigma[ok]
    index = grid.to_index(positions)
    keep, intensities = merge_close(index, fitted.intensities[ok], settings.merge)
    return FrameParticles(positions[keep], index[keep], sigma[keep], intensities[keep],
                          known, fitted.dropped)


def _gather(table: np.ndarray, particles: list[FrameParticles]):
    """The linked particles as track arrays (NaN where absent)."""
    n, f = table.shape
    measured, sigma = np.full((n, f, 3), np.nan), np.full((n, f, 3), np.nan)
    intensity = np.full((n, f), np.nan)
    for k, part in enumerate(particles):
        rows = table[:, k] >= 0
        measured[rows, k] = part.positions[table[rows, k]]
        sigma[rows, k] = part.sigma[table[rows, k]]
        intensity[rows, k] = part.intensities[table[rows, k]]
    return measured, sigma, intensity


class Recording:
    """The frames of one camera's recording or of several cameras' (docs/design.md
    §6.7), checked, with what each frame reconstructs from and is fitted to.

    Parameters
    ----------
    frames
        :func:`track`'s frames (several cameras: one sequence per camera).
    projector
        :func:`track`'s projector, or several cameras' list of them.
    min_length
        The fewest frames a recording may have.
    """

    def __init__(self, frames, projector, min_length: int) -> None:
        self.several = isinstance(projector, (list, tuple))
        self.projectors = list(projector) if self.several else [projector]
        if not self.several:
            self.frames = [[f] for f in _check_frames(frames, min_length)]
        else:
            self.frames = _camera_frames(frames, self.projectors, min_length)
        self.operator = projector
        self.grid, self.queue = self.projectors[0].grid, self.projectors[0].queue
        self._check_content()

    def _check_content(self) -> None:
        """Every frame's pixels checked before the first is reconstructed (numeric,
        finite, the sensor's shape, not blank), each error naming its frame: one bad frame
        would otherwise fail the recording after every frame before it was done."""
        for k, images in enumerate(self.frames):
            for c, (image, proj) in enumerate(zip(images, self.projectors), start=1):
                name = f"frame {k}" + (f" of camera {c}" if self.several else "")
                check_exposure(check_image(image, proj.camera, name=name, copy=False), name,
                               saturation=False)

    def images(self, k: int):
        """Frame ``k``'s raw image; several cameras': the list of them."""
        return list(self.frames[k]) if self.several else self.frames[k][0]

    def backgrounds(self, info) -> list | None:
        """Each camera's ``(median, noise)`` its reconstruction of a frame removed
        (``info``: its :class:`plenocl.reconstruction.ReconstructionInfo`), or ``None``
        when none was removed."""
        infos = info.cameras if self.several else [info]
        if any(i.background is None for i in infos):
            return None
        return [(i.background, i.noise) for i in infos]

    def image_fit(self, k: int, backgrounds: list | None, settings: ImageFitSettings):
        """The fit of particles to frame ``k``'s raw images (each camera's
        ``backgrounds`` as its reconstruction found them; ``None``: estimated)."""
        if self.several:
            return JointImageFit([p.camera for p in self.projectors], self.grid,
                                 [[raw] for raw in self.frames[k]], settings, queue=self.queue,
                                 backgrounds=None if backgrounds is None
                                 else [[bg] for bg in backgrounds])
        return ImageFit(self.projectors[0].camera, self.grid, self.frames[k], settings,
                        queue=self.queue, backgrounds=backgrounds)


def _camera_frames(frames, projectors: list, min_length: int) -> list[tuple]:
    """Several cameras' frames as one tuple per frame (camera by camera), refused when
    the cameras' counts differ or a camera's frames are too few or of different shapes."""
    per_camera = list(frames)
    if len(per_camera) != len(projectors) or not projectors:
        raise ValueError(f"several cameras need one sequence of frames per projector: got "
                         f"{len(per_camera)} sequence(s) for {len(projectors)} projector(s)")
    checked = [_check_frames(f, min_length) for f in per_camera]
    counts = [len(f) for f in checked]
    for c, count in enumerate(counts[1:], start=2):
        if count != counts[0]:
            raise ValueError(f"camera {c} has {count} frames but camera 1 has {counts[0]}: "
                             "frame k of every camera must be taken at the same instant; "
                             "give every camera the same frames")
    return list(zip(*checked, strict=True))


def _check_frames(frames, min_length: int) -> list:
    """The frames as a list, refused when too few or of different shapes."""
    if isinstance(frames, np.ndarray) and frames.ndim == 2:
        raise ValueError(f"track takes a recording, a sequence of at least {min_length} "
                         f"frames (a list of 2-D images or a (frames, rows, cols) array), "
                         f"got one 2-D image {frames.shape[::-1]} (cols x rows)")
    frames = list(frames)  # a (frames, rows, cols) array gives its frames
    if len(frames) < min_length:
        raise ValueError(f"tracking needs at least {min_length} frames (min_length), got "
                         f"{len(frames)}; give more frames or a smaller min_length (>= 2)")
    shapes = [np.shape(f) for f in frames]
    for k, shape in enumerate(shapes):
        if shape != shapes[0]:
            raise ValueError(f"frame {k} is {shape[::-1] if len(shape) == 2 else shape} "
                             f"(cols x rows) but frame 0 is {shapes[0][::-1]}: every frame "
                             "of a recording must come from the same sensor region")
    return frames


def _check_dt(dt) -> float:
    if not is_number(dt):
        raise ValueError(f"dt (the time between frames) must be a positive number, got {dt!r}")
    value = float(dt)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"dt (the time between frames) must be a positive number, got {dt!r}")
    return value


def _warn_if_unlinked(table: np.ndarray) -> None:
    """Warn about a step in which few particles found a partner."""
    for k in range(table.shape[1] - 1):
        here = table[:, k] >= 0
        if here.sum() >= 10:
            share = float((table[here, k + 1] >= 0).mean())
            if share < LINKED_FLOOR:
                warnings.warn(
                    f"only {share:.0%} of frame {k}'s particles found a partner in frame "
                    f"{k + 1}: the particles move farther than the search range, the "
                    "frames are not consecutive, or most of a frame's peaks are ghosts (a "
                    "dense seeding). Record at a shorter interval, check the frames' order, "
                    "widen search= (x, y, z voxels) or raise threshold= (docs/errors.md)",
                    stacklevel=3)


def bin_tracks(tracks: Tracks, grid: Grid, window=(16, 16, 16), step=None, frames=None,
               min_samples: int = 3, focus: FocalZone | None = None) -> PIVResult:
    """The tracks' Eulerian field: their steps per frame interval averaged in
    interrogation windows, as a :class:`plenocl.PIVResult` (docs/design.md §7.3).

    Each step of a track from frame ``k`` to ``k + 1`` (of its smoothed positions) is a
    sample at its midpoint, like a particle pair of the pair chain, and the windows
    average them as the pair chain's particle refinement does
    (:func:`plenocl.piv.refinement.window_means`, §7.1): samples farther than the search
    range from their window's median are left out, the rest moved to the window's centre
    along the local gradient, and the uncertainty is the standard error with Student's
    t (with ``focus``, the focal zone's systematic depth term too). Windows of
    ``window`` voxels ``(z, y, x)``, centres ``step`` apart (half a window by default),
    the first at ``(w - 1) / 2``, as :func:`plenocl.piv3d` lays them out; a window with
    fewer than ``min_samples`` samples holds no vector (NaN, not valid). The field is
    validated as a correlation's (normalised median test, outliers replaced).

    Parameters
    ----------
    tracks
        :class:`plenocl.Tracks` on ``grid``'s millimetres.
    grid
        The grid whose voxels are the field's units (the reconstruction's).
    window, step
        Window size and centre spacing, voxels.
    frames
        The frames whose steps count (a step from ``k`` to ``k + 1`` counts for ``k``);
        ``None``: every frame (a steady flow's mean field).
    min_samples
        Fewest samples for a vector.
    focus
        The camera's focal zone (:meth:`plenocl.piv.refinement.FocalZone.of`), for the
        systematic depth term of the uncertainty.
    """
    template = _windows(grid, window, step)
    samples = _steps(tracks, grid, frames)
    # every sample within the search range of its window's median, as before the pairs'
    # robust window means (a track's steps are already smoothed; not measured with them)
    mean, error, count = window_means(samples, template, min_samples, SEARCH, focus,
                                      FITTED_POSITION_SIGMA, spread=None)
    use = np.isfinite(mean[0])
    outlier = normalized_median_test(np.where(use, mean, 0.0), ignore=~use) & use
    vectors = np.where(use, replace_outliers(np.where(use, mean, 0.0), outlier | ~use), np.nan)
    valid = use & ~outlier
    sigma = np.where(valid, error, np.nan)
    return dataclasses.replace(
        template, u=vectors[0], v=vectors[1], w=vectors[2], valid=valid, outlier=outlier,
        masked=~use, sigma_u=sigma[0], sigma_v=sigma[1], sigma_w=sigma[2],
        refinement={"refinement": "tracks", "samples": len(samples.midpoints),
                    "vectors": int(valid.sum()), "outliers": int(outlier.sum()),
                    "median_samples": float(np.median(count[use])) if use.any() else 0.0})


def _windows(grid: Grid, window, step) -> PIVResult:
    """An empty field on ``grid``'s windows of ``window`` voxels ``step`` apart."""
    window = np.broadcast_to(np.asarray(window, int), 3)
    step = window // 2 if step is None else np.broadcast_to(np.asarray(step, int), 3)
    if np.any(window < 1) or np.any(step < 1) or np.any(window > np.asarray(grid.shape)):
        raise ValueError(f"bin_tracks: window {tuple(window)} and step {tuple(step)} (z, y, x "
                         f"voxels) must be positive and fit the grid {grid.shape}")
    counts = tuple((np.asarray(grid.shape) - window) // step + 1)
    z, y, x = ((w - 1) / 2 + s * np.arange(c) for w, s, c in zip(window, step, counts))
    empty = np.full(counts, np.nan)
    flags = np.zeros(counts, bool)
    return PIVResult(x, y, z, empty, empty.copy(), empty.copy(), flags, empty.copy(),
                     flags.copy(), flags.copy(), tuple(int(w) for w in window))


def _steps(tracks: Tracks, grid: Grid, frames) -> ParticlePairs:
    """The tracks' steps from each chosen frame to the next as particle pairs (voxel
    indices ``(x, y, z)``)."""
    n, f, _ = tracks.positions.shape
    chosen = np.arange(f - 1) if frames is None else np.atleast_1d(frames)
    chosen = chosen[(chosen >= 0) & (chosen < f - 1)]
    start = tracks.positions[:, chosen].reshape(-1, 3)
    end = tracks.positions[:, chosen + 1].reshape(-1, 3)
    ok = np.all(np.isfinite(start) & np.isfinite(end), axis=1)
    a, b = grid.to_index(start[ok]), grid.to_index(end[ok])
    return ParticlePairs((a + b) / 2, b - a)
