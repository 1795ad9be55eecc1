"""Particle refinement of a correlation field (docs/design.md §7.1, §7.4): the particles
of the two reconstructed volumes, matched with the correlation's displacement as
predictor, averaged per interrogation window.

A reconstructed volume places each particle within about 0.1 voxel laterally, but the
correlation of whole windows also sees every ghost and the particles' irregular,
depth-elongated shapes, and it reads the displacement about three times less precisely
(``benchmarks/accuracy.py``). Here each volume's particles are its peaks above
``threshold`` of a robust peak level (:func:`volume_particles`); with the camera's lines
of sight (:class:`SightLines`) the peaks of one particle stretched along its line are
merged and centred on the ridge they sit on. Each particle of the first volume is sent
along the predicted displacement and paired with the nearest of the second volume
within ``search`` voxels (x, y, z); only mutual nearest neighbours are kept (a ghost
rarely has a partner both ways). The predictor is the correlation refined once by these
pairs (:func:`repredicted`): where the correlation errs beyond the search its windows
would find no pairs. Each window of the correlation's final grid then takes the mean
displacement of the pairs whose midpoints lie in it, each first moved to the window's
centre along the local displacement gradient (a least-squares linear fit to the pairs in
the window grown to twice its size, weighted as the means are, where it holds at least
:data:`GRADIENT_PAIRS`; otherwise none), after leaving out pairs farther than ``search``
from the window's median (:func:`near_median`; optionally also those beyond ``spread``
robust standard deviations, :data:`ROBUST_SPREAD`). Without the gradient step, a
gradient across a sparse window would bias its mean by where its few particles happen to
lie. With the fit to the raw images, the mean weighs each pair by the inverse of its
displacement's variance, the two particles' posterior variances from their fits plus
:data:`WEIGHT_FLOOR` squared (:func:`pair_weights`): a particle in the focal zone lights
one microlens and its fit knows its lateral position to 0.15 voxel (its prior), against
0.01-0.03 elsewhere; elsewhere the pairs' errors follow their fits' uncertainties, there
they err more (0.25 voxel at the paper's full size; docs/design.md §7.1, and for the
gradient's weights §7.4 item 9). With the camera's :class:`FocalZone`, the depth
component comes from the pairs that see depth (:func:`seen_depth`; interpolated in depth
across the blind zone at the focal plane) in a box :data:`DEPTH_SUPPORT` times the
window, and with its lines of sight every pair is then moved along its line to that
depth, so that the lateral motion is read across the lines (:func:`seen_means`,
:meth:`SightLines.along_sight`).
The vector's uncertainty (:func:`window_estimate`) adds in quadrature the half-width of
the mean's 68.3 % confidence interval (the standard error times Student's t quantile for
the pairs it holds: 1.32 for 3 pairs, 1.05 for 11), the systematic depth error of pairs
in the camera's focal zone, which err together, and the particles' reconstructed depth
position carried through the local gradient. Windows with fewer than ``min_pairs`` pairs
keep the predictor's vector. The refined field is validated like the correlation's last
pass (normalised median test, outliers replaced): a cluster of failed windows at a face
of the volume can survive the correlation's test and the refinement, which follows it.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pyopencl.array as cl_array
from scipy import stats
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial import cKDTree

from ..opencl.arrays import device_copies, upload
from ..opencl.volume import DeviceVolume, host_volume
from ..optics.sightline import line_of_sight, sight_frames
from ..peaks import find_particles, merge_along_lines
from ..vectorfield import PIVResult
from .devicemeans import (
    ILL_POSED,
    DeviceWindowMeans,
    PairsOnDevice,
    WindowCentres,
    WindowLists,
)
from .imagefit import METHOD as FIT_METHOD
from .imagefit import PRIOR_VOXELS, standard_deviations
from .pairoutliers import FLOOR as PAIR_SCATTER
from .pairoutliers import MAD_SIGMA, neighbour_outliers
from .pairoutliers import THRESHOLD as OUTLIER_THRESHOLD
from .tube import DeviceTubeSums, host_tube_sums
from .validation import normalized_median_test, replace_outliers

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

    from ..camera import Camera
    from ..grid import Grid
    from .imagefit import ImageFit

#: The particle refinement's method, recorded with every batch field
#: (:func:`plenocl.batch.record.run_record`): a batch rerun re-correlates the pairs whose
#: fields an earlier method made from the same settings. Change it whenever the
#: refinement makes a different field from the same settings (rounding included).
METHOD = ("lines of sight, seen depth in the predictor and over twice the window, every "
          "pair along its line with its covariance, fit-weighted window means "
          "(2026-11-29 evening); pairs tested against their neighbours, sparse windows "
          "from twice their box, the moves along the lines extended linearly beyond the "
          "window centres "
          "(2026-11-29 night); the local gradients weighted as the means (2026-11-30); "
          "a blind window without a seeing one in its column from its seeing pairs "
          "(2026-12-01); "
          "a particle's peaks merged within the whole cylinder around its line, their "
          "centre summed in index order (2026-12-04); "
          f"the fit: {FIT_METHOD}")
#: Match tolerance (x, y, z voxels): depth is about three times less certain.
SEARCH = (1.0, 1.0, 3.0)
#: The robust rule (:func:`near_median`, ``spread=ROBUST_SPREAD``): a window keeps the
#: pairs whose displacement (moved to its centre) lies within this many robust standard
#: deviations (1.4826 times the median absolute deviation) of the window's median, per
#: component. It left out the one pair in a hundred whose fit to the raw images ends
#: 0.3-0.5 voxel off, but in a sheared, turbulent window it also trims the flow's own
#: spread (the paper-size demo 7.4 -> 8.5 % of U∞); the fit-weighted means
#: (:func:`pair_weights`) do better on both, so it is no longer the default
#: (docs/design.md §7.1; ``benchmarks/robust_means.py``).
ROBUST_SPREAD = 3.0
#: The default ``spread``: ``None``, a window keeps every pair within ``search`` of its
#: median, and weighs them by their fits' uncertainties (:func:`pair_weights`).
SPREAD: float | None = None
#: Added in quadrature to a pair's fitted uncertainty (x, y, z voxels) for its weight
#: (:func:`pair_weights`): the scatter of the best-fitted pairs' displacements at the
#: paper's optics (0.016-0.022 voxel laterally where the fits claim 0.009-0.015), so
#: that no pair outweighs the others by more than its fit can show. On
#: ``benchmarks/robust_means.py``'s one-camera scenes no floor gives 0.014 / 0.184 voxel,
#: this one 0.016 / 0.188 and twice it 0.017 / 0.192; the small demo 7.0 % of U∞ with
#: each.
WEIGHT_FLOOR = (PAIR_SCATTER, PAIR_SCATTER, 0.1)  # lateral: the neighbour test's floor
#: The robust rule never leaves out a pair within this distance (x, y, z voxels) of the median:
#: about twice the scatter of fitted particles' displacements at the paper's optics
#: (median 0.011, 90th percentile 0.034 voxel laterally), so that a window whose pairs
#: agree closely keeps its ordinary spread.
KEEP_FLOOR = (0.1, 0.1, 0.3)
#: Fewest pairs in the doubled window for a displacement-gradient fit (12 unknowns).
GRADIENT_PAIRS = 12
#: The upper quantile of a one-sigma (68.3 %) two-sided interval.
ONE_SIGMA = 0.8413447460685429
#: Standard uncertainty (x, y, z voxels) of a reconstructed particle's position that
#: its pair partner shares: at the paper's optics the reconstruction draws particles
#: 0.5-1 voxel towards the focal plane (docs/design.md §7.1), laterally it is unbiased.
POSITION_SIGMA = (0.0, 0.0, 1.0)
#: The same for particles fitted to the raw images (docs/design.md §7.2): the draw
#: towards the focal plane falls from 0.5-0.9 to below 0.1 voxel beyond 2 mm of the plane.
FITTED_POSITION_SIGMA = (0.0, 0.0, 0.3)
#: A focal-plane pair's systematic depth uncertainty as a fraction of the camera's depth
#: resolution (0.75 voxel at the paper's optics): calibrated on reconstructed scenes so that
#: about 68 % of the depth errors of windows within 2 mm of the focal plane lie within
#: one sigma (docs/design.md §7.1).
FOCAL_SYSTEMATIC = 0.087
#: Within this many depth resolutions of the focal plane a pair's depth displacement is
#: not used (:meth:`FocalZone.sees_depth`): both exposures' particles there are drawn to
#: the same depth, their ``dz`` 1.0-1.4 voxel short of a 1.7-voxel motion at the paper's
#: optics, and a window that holds a few of them inherits it. Measured at the paper's
#: full size (``benchmarks/field_size.py``): 1.0 leaves windows at 0.45 voxel RMS in
#: depth, 1.5 at 0.31; docs/design.md §7.4.
DEPTH_BLIND = 1.5
#: The depth component's support, in windows (docs/design.md §7.1 "Choice: one camera's
#: depth over twice the window"): with the camera's focal zone, each window's depth is the
#: mean of the seeing pairs in a box this many times its window about its centre, each
#: moved to the centre along the local gradient, and every pair is then moved along its
#: line of sight to that depth before the lateral means. One camera places a particle
#: 10-20 times less precisely along its line of sight than across it, so a window's depth
#: holds most of its error, and off the axis, where the line leans, that error also moves
#: the lateral components (``r / s_o`` of it). At the paper's optics (three scenes each,
#: ``benchmarks/field_size.py``'s chain), lateral / depth voxel for 1, 1.5 and 2: the whole
#: sensor 0.020 / 0.187, 0.015 / 0.108, 0.015 / 0.082; 96 x 64 lenses 0.012 / 0.175,
#: 0.011 / 0.096, 0.011 / 0.074; the small demo's boundary layer 7.0, 6.9, 6.7 % of U∞.
DEPTH_SUPPORT = 2.0
#: The box (in windows) from which a window left with fewer than ``min_pairs`` pairs
#: takes its lateral means (:func:`sparse_filled`; 1.5 and 2 gave the same vectors on
#: the paper's full sensor under the rotation, 20-30 windows of 10,500 per scene).
SPARSE_SUPPORT = 2.0


@dataclass(frozen=True)
class ParticlePairs:
    """Matched particles: midpoints ``(N, 3)`` and displacements ``(N, 3)``, both as
    ``(x, y, z)`` voxels; ``dropped``: the peaks the fit to the raw images dropped
    (:class:`plenocl.piv.imagefit.FittedParticles`), left out before pairing again."""

    midpoints: np.ndarray
    displacements: np.ndarray
    dropped: int = 0
    #: ``(N, 3)`` each displacement's standard uncertainty (x, y, z voxels) from its two
    #: particles' fits (:class:`plenocl.piv.imagefit.RefinedPeaks`; a peak paired but
    #: not fitted: :data:`plenocl.piv.imagefit.PRIOR_VOXELS`); ``None``: not fitted, the
    #: window means weigh every pair alike.
    sigma: np.ndarray | None = None
    #: ``(N, 3, 3)`` each displacement's covariance (voxels², the two fits' added),
    #: whose diagonal ``sigma`` is the root of; ``None``: not known. Off the axis one
    #: camera's uncertainty leans with the line of sight: moving a pair along its line
    #: (:meth:`SightLines.along_sight`) leaves it what is known across the line.
    covariance: np.ndarray | None = None

    def subset(self, rows: np.ndarray) -> ParticlePairs:
        """The pairs ``rows`` (a mask or indices), their uncertainties with them."""
        return dataclasses.replace(
            self, midpoints=self.midpoints[rows], displacements=self.displacements[rows],
            sigma=None if self.sigma is None else self.sigma[rows],
            covariance=None if self.covariance is None else self.covariance[rows])

    def alike(self) -> ParticlePairs:
        """The same pairs without their uncertainties: every window mean, also after a
        move along the lines of sight, weighs them alike."""
        return dataclasses.replace(self, sigma=None, covariance=None)


def predicted(field: PIVResult, points: np.ndarray, extrapolate: bool = False
              ) -> np.ndarray:
    """The displacement ``(N, 3)`` ``(dx, dy, dz)`` of a :class:`PIVResult` at ``points``
    ``(N, 3)`` ``(x, y, z)``: trilinear between window centres; beyond them the nearest
    value, or with ``extrapolate`` the outermost cells' linear trend (a linear motion
    stays exact up to the volume's faces: under the error budget's rotation the nearest
    value misses 0.7 voxel of depth motion at a face, which off the axis leans into the
    lateral components); masked (NaN) vectors count as 0."""
    axes = (field.z, field.y, field.x)
    zyx = np.asarray(points, float)[:, ::-1]
    if not extrapolate:
        zyx = np.clip(zyx, [a[0] for a in axes], [a[-1] for a in axes])
    values = np.stack([np.nan_to_num(c) for c in (field.u, field.v, field.w)], axis=-1)
    # one interpolator for the three components: the cells found once, the same bits
    look = RegularGridInterpolator(axes, values, bounds_error=False, fill_value=None)
    return look(zyx)


def pair_particles(vol_a: np.ndarray, vol_b: np.ndarray, field: PIVResult,
                   threshold: float = 0.1, search=SEARCH,
                   fit: ImageFit | None = None, sight: SightLines | None = None
                   ) -> ParticlePairs:
    """Mutual nearest-neighbour pairs of the two volumes' peaks along ``field``; with
    ``sight``, each particle's peaks along its line of sight merged first
    (:meth:`SightLines.merge`); with ``fit``, the paired peaks are refined against their
    raw images and paired again (the peaks the fit dropped left out, and counted)."""
    pa, pb = (volume_particles(v, threshold, sight) for v in (vol_a, vol_b))
    return pair_peaks(pa, pb, field, search, fit)


def pair_peaks(pa: np.ndarray, pb: np.ndarray, field: PIVResult, search=SEARCH,
               fit: ImageFit | None = None) -> ParticlePairs:
    """:func:`pair_particles` of the two volumes' particles ``pa``, ``pb`` ``(N, 3)``
    ``(x, y, z)`` voxels (copied, not changed)."""
    pa, pb = np.array(pa, float), np.array(pb, float)
    ia, ib = mutual_pairs(pa, pb, field, search)
    if fit is None or not len(ia):
        disp = pb[ib] - pa[ia]
        return ParticlePairs(pa[ia] + disp / 2, disp)
    prior = np.diag(np.asarray(PRIOR_VOXELS, float) ** 2)
    ca, cb = (np.tile(prior, (len(p), 1, 1)) for p in (pa, pb))
    ra, rb = fit.refine_pair(pa[ia], pb[ib])
    pa[ia], pb[ib] = ra.positions, rb.positions
    known = ra.covariance is not None and rb.covariance is not None
    if known:
        ca[ia], cb[ib] = ra.covariance, rb.covariance
    else:  # a fit that gives its sigmas alone
        ca[ia], cb[ib] = (_diagonal(r.sigma) for r in (ra, rb))
    kept_a, kept_b = (np.all(np.isfinite(p), axis=1) for p in (pa, pb))
    dropped = int(np.count_nonzero(~kept_a) + np.count_nonzero(~kept_b))
    pa, pb, ca, cb = pa[kept_a], pb[kept_b], ca[kept_a], cb[kept_b]
    ia, ib = mutual_pairs(pa, pb, field, search)
    disp, cov = pb[ib] - pa[ia], ca[ia] + cb[ib]
    return ParticlePairs(pa[ia] + disp / 2, disp, dropped, standard_deviations(cov),
                         cov if known else None)


def _diagonal(sigma: np.ndarray) -> np.ndarray:
    """Covariances ``(n, 3, 3)`` with the variances ``sigma**2`` ``(n, 3)`` alone."""
    return np.einsum("ni,ij->nij", np.asarray(sigma, float) ** 2, np.eye(3))


def volume_particles(vol: np.ndarray, threshold: float = 0.1,
                     sight: SightLines | None = None, maxima: Callable | None = None,
                     on_device=None) -> np.ndarray:
    """A volume's particles ``(N, 3)`` ``(x, y, z)`` voxels, brightest first: its peaks
    above ``threshold`` of the robust peak level (:func:`plenocl.peaks.find_particles`
    with ``reference="robust"``: a high quantile of the peaks, which does not grow with
    the volume as its maximum does; at the paper's full size the maximum kept 80-83 % of
    the particles, the quantile 84-92 %, against 88 % on a 96 x 64 camera); with
    ``sight``, the peaks along one line of sight merged (:meth:`SightLines.merge`) and
    centred on their ridge (:meth:`SightLines.centres`). ``maxima``: where the local
    maxima are found (:func:`plenocl.peaks.find_particles`' ``maxima``; ``None``: the
    host). Where both run on one device, the volume goes to it once
    (:func:`shared_upload`); ``on_device``: the volume's float32 device copy (the same
    values), which each of them on its context reads instead (a
    :class:`plenocl.opencl.volume.DeviceVolume`'s own array by default)."""
    for_maxima, for_sums = device_reads(vol, maxima, sight, on_device)
    if for_maxima is not None:
        maxima = _maxima_on(maxima, for_maxima)
    peaks, values = find_particles(vol, threshold, reference="robust", maxima=maxima)
    if sight is None:
        return peaks
    peaks = sight.merge(peaks, values)[0]
    for _ in range(CENTRE_PASSES):
        peaks = sight.centres(host_volume(vol) if for_sums is None else for_sums, peaks)
    return peaks


def device_reads(vol: np.ndarray, maxima, sight: SightLines | None, on_device=None
                 ) -> tuple:
    """The device volumes :func:`volume_particles`' local maxima and tube sums read
    (``None``: the host volume, uploaded by each as it needs): ``on_device`` for each on
    its context; without it, one upload for both where both run on one device
    (:func:`shared_upload`)."""
    if on_device is None and isinstance(vol, DeviceVolume):
        on_device = vol.array
    if on_device is None:
        on_device = shared_upload(vol, maxima, sight)
        if on_device is None:
            return None, None
    return tuple(on_device if q is not None and q.context == on_device.context else None
                 for q in _queues(maxima, sight))


def _queues(maxima, sight: SightLines | None) -> tuple:
    """The queues of :func:`volume_particles`' local maxima and tube sums (``None``: the
    host's)."""
    return (getattr(maxima, "queue", None),
            None if sight is None else getattr(sight.sums, "queue", None))


def _maxima_on(maxima: Callable, shared: cl_array.Array) -> Callable:
    """``maxima`` run on the device copy ``shared``, whatever volume it is given."""
    return lambda _vol, floor, reach: maxima(shared, floor, reach)


def shared_upload(vol: np.ndarray, maxima, sight: SightLines | None
                  ) -> cl_array.Array | None:
    """One float32 device copy of ``vol`` for both the local maxima and the tube sums
    of :func:`volume_particles`, where both run on one device (``maxima`` and
    ``sight.sums`` with a ``queue`` of one context; each would upload it, the sums once
    per centring pass); ``None`` otherwise."""
    queues = _queues(maxima, sight)
    if any(q is None for q in queues) or queues[0].context != queues[1].context:
        return None
    return upload(queues[0], np.asarray(vol, np.float32))


def mutual_pairs(pa: np.ndarray, pb: np.ndarray, field: PIVResult, search=SEARCH
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``pa`` and ``pb`` (voxel positions ``(N, 3)``) of the peaks that are
    each other's nearest neighbour within ``search`` after moving along ``field``."""
    if not len(pa) or not len(pb):
        return np.zeros(0, int), np.zeros(0, int)
    scale = 1.0 / np.asarray(search, float)
    # the field is the displacement at mid-time: look it up half a step along
    fwd = pa + predicted(field, pa + predicted(field, pa) / 2)
    back = pb - predicted(field, pb - predicted(field, pb) / 2)
    dist_a, to_b = cKDTree(pb * scale).query(fwd * scale, distance_upper_bound=1.0)
    dist_b, to_a = cKDTree(pa * scale).query(back * scale, distance_upper_bound=1.0)
    ia = np.flatnonzero(np.isfinite(dist_a))
    ia = ia[np.isfinite(dist_b[to_b[ia]]) & (to_a[to_b[ia]] == ia)]
    return ia, to_b[ia]


def near_median(d: np.ndarray, search=SEARCH, spread: float | None = SPREAD) -> np.ndarray:
    """Which displacements ``d`` ``(n, 3)`` lie near their median, per component: within
    ``search`` (x, y, z voxels) and within ``spread`` robust standard deviations (1.4826
    times the median absolute deviation; never nearer than :data:`KEEP_FLOOR`): the
    pairs a window or a gradient fit keeps. ``spread=None``: ``search`` alone."""
    if not len(d):
        return np.zeros(0, bool)
    off = np.abs(d - np.median(d, axis=0))
    reach = np.asarray(search, float)
    if spread is not None:
        robust = spread * MAD_SIGMA * np.median(off, axis=0)
        reach = np.minimum(reach, np.maximum(robust, KEEP_FLOOR))
    return np.all(off <= reach, axis=1)


def local_gradient(pairs: ParticlePairs, near: list[int], centre: np.ndarray,
                   search=SEARCH, spread: float | None = SPREAD) -> np.ndarray:
    """The displacement gradient ``(3, 3)`` (component, x/y/z) fitted by least squares to
    the pairs ``near`` (those :func:`near_median` keeps), each component's weighted as
    the window means weigh it (:func:`pair_weights`; alike without uncertainties), or
    zeros with fewer than :data:`GRADIENT_PAIRS` of them.

    Weighted, a pair whose fit knows it to 0.25 voxel (a focal-zone particle, placed to
    a lens) no longer tilts the gradient that moves the well-fitted pairs to the
    window's centre (docs/design.md §7.4 item 9)."""
    d = pairs.displacements[near]
    keep = near_median(d, search, spread)
    if np.count_nonzero(keep) < GRADIENT_PAIRS:
        return np.zeros((3, 3))
    offsets = pairs.midpoints[near][keep] - centre
    design = np.column_stack([np.ones(len(offsets)), offsets])
    weight = pair_weights(pairs, np.asarray(near)[keep])
    if weight is None:
        coef, *_ = np.linalg.lstsq(design, d[keep], rcond=None)
        return coef[1:].T
    root = np.sqrt(weight)
    return np.stack([np.linalg.lstsq(design * root[:, c, None], d[keep, c] * root[:, c],
                                     rcond=None)[0][1:] for c in range(3)])


@dataclass(frozen=True)
class FocalZone:
    """Where the camera cannot see depth: the nominal focal plane's depth index
    ``plane`` and the camera's depth resolution ``resolution`` (both in voxels of the
    volume; :attr:`plenocl.Camera.depth_resolution_mm`). Within ``resolution`` of the
    plane a particle's blur stays inside one microlens (docs/design.md §2), so its
    reconstructed depth, and a pair's depth displacement, is not measured: both
    exposures' particles are drawn to the same depth (docs/design.md §7.1)."""

    plane: float
    resolution: float

    @classmethod
    def of(cls, camera: Camera, grid: Grid) -> FocalZone:
        """The focal zone of ``camera`` on ``grid`` (depth from ``grid.z``, which puts
        the nominal focal plane at z = 0)."""
        dz = grid.spacing[0]
        return cls(plane=-grid.z[0] / dz - 0.5, resolution=camera.depth_resolution_mm / dz)

    @classmethod
    def along_grid(cls, camera: Camera, grid: Grid) -> FocalZone | None:
        """:meth:`of` where the focal zone lies along the grid's z (a camera without a
        pose), else ``None``: a posed camera's focal plane is tilted or moved in the
        world grid (docs/design.md §5.5), so no depth index tells it."""
        return cls.of(camera, grid) if camera.pose is None else None

    def sees_depth(self, z: np.ndarray) -> np.ndarray:
        """Whether the camera measures depth at depth index ``z``: farther from the plane
        than :data:`DEPTH_BLIND` resolutions (docs/design.md §7.4)."""
        return np.abs(np.asarray(z, float) - self.plane) >= DEPTH_BLIND * self.resolution

    def ambiguity(self, z: np.ndarray) -> np.ndarray:
        """A pair's systematic depth uncertainty (voxels) at depth index ``z``:
        :data:`FOCAL_SYSTEMATIC` times the resolution at the plane, falling linearly to
        0 at twice the resolution, where the blur spans two microlenses and the
        parallax is read in every case."""
        reach = np.clip(1.0 - np.abs(np.asarray(z, float) - self.plane)
                        / (2.0 * self.resolution), 0.0, None)
        return FOCAL_SYSTEMATIC * self.resolution * reach


#: How far across its line of sight (voxels, lateral) a peak may lie from a brighter one
#: for :class:`SightLines` to take it as the same particle: the duplicates of a
#: reconstructed particle lie within 0.15 voxel of one line (docs/design.md §7.4).
SIGHT_ACROSS = 1.0
#: The tube around a particle's line of sight whose intensity centroid places it along
#: the line (:meth:`SightLines.centres`): its radius (lateral voxels) and the passes (each
#: centred on the last). At the paper's full size the pairs' depth error falls from 1.14
#: (the merged peaks) to 0.95 voxel RMS (``benchmarks/field_size.py``).
TUBE_RADIUS = 2.0
CENTRE_PASSES = 2
#: Samples along the tube per depth resolution each way (about one per depth voxel).
TUBE_STEPS = 8


@dataclass(frozen=True)
class SightLines:
    """Where a volume's peaks are one particle stretched along its line of sight
    (:mod:`plenocl.optics.sightline`): peaks within the camera's depth resolution of a
    brighter one along that line, and within :data:`SIGHT_ACROSS` lateral voxel of it,
    are merged into it (:func:`plenocl.peaks.merge_along_lines`).

    Attributes
    ----------
    camera, grid
        The camera (its lines of sight and depth resolution) and the volumes' grid.
    """

    camera: Camera
    grid: Grid
    #: The tube sums of :meth:`centres` (:class:`plenocl.piv.tube.DeviceTubeSums` on a
    #: device; ``None``: SciPy on the host).
    sums: DeviceTubeSums | None = dataclasses.field(default=None, compare=False, repr=False)

    @classmethod
    def of(cls, camera: Camera, grid: Grid, queue=None) -> SightLines:
        """The lines of sight of ``camera`` through ``grid``; their tube sums on
        ``queue``'s device (``None``: on the host)."""
        return cls(camera, grid, None if queue is None else DeviceTubeSums(queue))

    def merge(self, peaks: np.ndarray, values: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """The peaks ``(N, 3)`` ``(x, y, z)`` voxels and their values, each particle's
        peaks along its line of sight merged into the brightest at their value-weighted
        mean position (brightest first, as :func:`plenocl.peaks.find_particles`)."""
        if len(peaks) < 2:
            return peaks, values
        mm = self.grid.from_index(peaks)
        across = SIGHT_ACROSS * float(np.mean(self.grid.spacing[1:]))
        keep, moved = merge_along_lines(mm, values, line_of_sight(self.camera, mm),
                                        self.camera.depth_resolution_mm, across)
        return self.grid.to_index(moved[keep]), values[keep]

    def unseen_along_sight(self, pairs: ParticlePairs, depth: PIVResult,
                           focus: FocalZone) -> ParticlePairs:
        """``pairs`` with the displacement of each pair the camera does not see in
        depth (:meth:`FocalZone.sees_depth`) moved along its line of sight to ``depth``
        (:meth:`along_sight`).

        Such a pair's two particles are placed at about the same depth along their
        lines of sight whatever their motion in depth, and off the axis that error
        leans into the lateral components too (``r / s_o`` of it: 0.2 voxel of a
        1.7-voxel motion 20 mm off the axis); the lateral motion across the line is
        measured, the motion along it is taken from the pairs that see depth."""
        return self.along_sight(pairs, depth, ~focus.sees_depth(pairs.midpoints[:, 2]))

    def along_sight(self, pairs: ParticlePairs, depth: PIVResult,
                    rows: np.ndarray | None = None) -> ParticlePairs:
        """``pairs`` with the displacement of the pairs ``rows`` (a boolean mask;
        ``None``: every pair) moved along its line of sight until its depth component is
        ``depth``'s ``w`` at its midpoint (:func:`predicted`): what the camera measures
        across the line is kept, the motion along it is ``depth``'s.

        With :attr:`ParticlePairs.covariance`, each moved pair's covariance becomes
        ``A C A^T`` for the move ``d -> A d + b`` (``A = I - l e_z^T / l_z``, ``l`` the
        line in voxels; ``depth`` taken as known), and ``sigma`` its diagonal's root:
        the lateral uncertainty left is the fit's across the line. Off the axis the
        fit's x and y share its depth's uncertainty through the line's lean (at 20-25 mm
        on the paper's optics, 2-3 times the across-line one); a window weighing moved
        pairs by that would weigh them by their depth."""
        rows = np.ones(len(pairs.midpoints), bool) if rows is None else np.asarray(rows)
        if not rows.any():
            return pairs
        mid, disp = pairs.midpoints[rows], pairs.displacements[rows].copy()
        mm = self.grid.from_index(mid)
        along = self.grid.to_index(mm + line_of_sight(self.camera, mm)) - mid  # voxels
        shift = predicted(depth, mid, extrapolate=True)[:, 2] - disp[:, 2]
        disp += along * (shift / along[:, 2])[:, None]
        out = pairs.displacements.copy()
        out[rows] = disp
        if pairs.covariance is None:
            return dataclasses.replace(pairs, displacements=out)
        move = np.eye(3) - np.einsum("ni,j->nij", along / along[:, 2:], np.eye(3)[2])
        cov = pairs.covariance.copy()
        cov[rows] = move @ cov[rows] @ np.swapaxes(move, 1, 2)
        return dataclasses.replace(pairs, displacements=out, sigma=standard_deviations(cov),
                                   covariance=cov)

    def centres(self, vol: np.ndarray, peaks: np.ndarray) -> np.ndarray:
        """The particles ``peaks`` ``(N, 3)`` ``(x, y, z)`` voxels moved along their lines
        of sight to the intensity centroid of ``vol`` (a host array, or a float32 device
        array on the tube sums' queue) in a tube around each line
        (:data:`TUBE_RADIUS` lateral voxels, as long as the camera's depth resolution each
        way; trilinear samples every half voxel across and :data:`TUBE_STEPS` per resolution
        along).

        A reconstructed particle's ridge along its line holds lobes that a peak sits on;
        its centroid is the ridge's centre. Only the position along the line moves: across
        it the peak's sub-voxel fit is the sharper estimate."""
        peaks = np.asarray(peaks, float).reshape(-1, 3)
        if not len(peaks):
            return peaks
        lines = line_of_sight(self.camera, self.grid.from_index(peaks))
        to_voxels = self.grid.index_jacobian() @ sight_frames(lines)  # local mm -> index
        sums = (self.sums or host_tube_sums)(vol, peaks, to_voxels, self.tube_offsets())
        lit = sums[:, 0] > 0
        along = np.where(lit, sums[:, 1] / np.where(lit, sums[:, 0], 1.0), 0.0)
        return peaks + to_voxels[:, :, 2] * along[:, None]  # along the line only

    def tube_offsets(self) -> np.ndarray:
        """``(S, 3)`` the tube's sample offsets ``(u, v, t)`` (mm) in a line's frame: every
        half lateral voxel across within :data:`TUBE_RADIUS`, :data:`TUBE_STEPS` per depth
        resolution along, one resolution each way."""
        lateral = float(np.mean(self.grid.spacing[1:]))
        g = np.arange(-TUBE_RADIUS, TUBE_RADIUS + 1e-9, 0.5) * lateral
        a = np.arange(-1.0, 1.0 + 1e-9, 1.0 / TUBE_STEPS) * self.camera.depth_resolution_mm
        u, v, t = np.meshgrid(g, g, a, indexing="ij")
        inside = u**2 + v**2 <= (TUBE_RADIUS * lateral) ** 2
        return np.stack([u[inside], v[inside], t[inside]], axis=1)


@functools.cache
def t_quantile(dof: int) -> float:
    """Student's t quantile at :data:`ONE_SIGMA` for ``dof`` degrees of freedom, computed
    once per count (SciPy's quantile costs about 0.1 ms a call; a paper-size field has
    about 10,000 windows and a few dozen distinct counts)."""
    return float(stats.t.ppf(ONE_SIGMA, dof))


def window_estimate(d: np.ndarray, depth: np.ndarray, grad: np.ndarray,
                    focus: FocalZone | None, position_sigma=POSITION_SIGMA,
                    weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The displacement ``(3,)`` of one window from its pairs' displacements ``d``
    ``(n, 3)`` (already moved to the window's centre) at depth indices ``depth``, and
    its standard uncertainty.

    The displacement is the pairs' mean, weighted per component by ``weight`` ``(n, 3)``
    (:func:`pair_weights`; ``None``: alike). Its uncertainty adds in quadrature the
    random part (the weighted standard error, the spread about the mean over the
    effective number of pairs ``(sum w)^2 / sum w^2``, times Student's t quantile for
    ``n`` pairs), the focal
    zone's systematic depth part (the mean of the pairs' :meth:`FocalZone.ambiguity`:
    the pairs near the focal plane err together, so it does not shrink with their
    number; 0 without ``focus``), and the particles' positions (``position_sigma``,
    x, y, z voxels: :data:`POSITION_SIGMA` as the volume places them,
    :data:`FITTED_POSITION_SIGMA` fitted to the images) carried through the local
    displacement gradient ``grad`` ``(3, 3)``.
    """
    n = len(d)
    w = np.ones_like(d) if weight is None else weight
    mean = np.average(d, axis=0, weights=w)
    n_eff = w.sum(axis=0) ** 2 / (w ** 2).sum(axis=0)
    spread = np.average((d - mean) ** 2, axis=0, weights=w) * n_eff / (n_eff - 1)
    random = np.sqrt(spread / n_eff) * t_quantile(n - 1)
    systematic = np.zeros(3)
    if focus is not None:
        systematic[2] = focus.ambiguity(depth).mean()
    position = np.sqrt(((grad * np.asarray(position_sigma)) ** 2).sum(axis=1))
    return mean, np.sqrt(random ** 2 + systematic ** 2 + position ** 2)


#: Smallest ratio of the least to the largest eigenvalue of a window's centred offsets'
#: scatter for which :func:`_fit_gradients` solves the normal equations (their error,
#: about the squared condition number times the rounding, stays below 1e-12 of the
#: gradient); flatter spreads of pairs go to ``np.linalg.lstsq`` as in
#: :func:`local_gradient`.
WELL_POSED = 1e-4


def window_means(pairs: ParticlePairs, field: PIVResult, min_pairs: int = 3, search=SEARCH,
                 focus: FocalZone | None = None, position_sigma=POSITION_SIGMA,
                 spread: float | None = SPREAD, support: float = 1.0,
                 windows: np.ndarray | None = None, *, device_means: DeviceWindowMeans | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window of ``field``'s grid: the displacement of its pairs at the window's
    centre ``(3, nz, ny, nx)`` (NaN where fewer than ``min_pairs`` pairs remain; see
    :func:`window_estimate`), its uncertainty, and the pair counts.

    ``support``: the pairs taken from a box this many times the window about its centre
    (the gradient's twice that), each moved to the centre along the gradient. (A box
    shifted inwards at the volume's faces, to hold as many pairs as one inside, changed
    the whole sensor's vectors by under 0.002 voxel: not kept.) ``windows``: a boolean
    ``(nz, ny, nx)``, the windows wanted (the others NaN, count 0); each window's
    result is the same as without it (``None``: all).

    At ``support`` 1, the same as
    :func:`plenocl.reference.refinement.window_means_reference`, the per-window loop over
    :func:`local_gradient`, :func:`near_median` and :func:`window_estimate`, computed for
    all windows holding the same number of pairs at once: about 5 times faster at the
    paper's size (11,220 windows, 5,000 pairs; ``benchmarks/window_means.py``), the
    same counts, means and uncertainties within a few 1e-15 voxel.

    ``device_means``: the gradients and estimates on that OpenCL device
    (:class:`plenocl.piv.devicemeans.DeviceWindowMeans`, one work-item per window in
    double precision: the same pairs kept, the results the host's to rounding); ``None``:
    on the host.
    """
    shape = field.u.shape
    if windows is not None:
        windows = _checked_windows(windows, shape)
    mean, error = np.full((2, 3, *shape), np.nan)
    count = np.zeros(shape, int)
    if not len(pairs.midpoints):
        return mean, error, count
    half = np.asarray(field.window[::-1], float) / 2  # (x, y, z)
    box = half * support
    centre_axes = (field.x, field.y, field.z)
    wanted = None if windows is None else windows.reshape(-1)
    if device_means is None:
        points, axes = pairs.midpoints / box, [c / b for c, b in zip(centre_axes, box)]
        centres = _grid_centres(field)
        win, member = _box_members(points, axes, 1.0, wanted)
        busy = np.bincount(win, minlength=count.size) >= min_pairs
        near_win, near = _box_members(points, axes, 2.0, busy)
        inside = busy[win]
        grad = _local_gradients(pairs, near_win, near, centres, search, spread)
        n, m, e = _window_estimates(pairs, win[inside], member[inside], centres, grad,
                                    min_pairs, search, focus, position_sigma, spread)
    else:
        dev = _device_pairs(device_means, pairs, focus)
        on_device = device_means.device_centres(centre_axes)
        ranges = [device_means.box_ranges(dev, box, on_device, r) for r in (1.0, 2.0)]
        inside, _ = device_means.box_lists(  # the busy windows' own pairs
            ranges[0], shape, np.ones(count.size, bool) if wanted is None else wanted,
            least=min_pairs, counted=False)
        near, _ = device_means.box_lists(ranges[1], shape, inside.mask, counted=False)
        busy = np.zeros(count.size, bool)
        busy[inside.win] = True
        n, m, e = _device_estimates(device_means, dev, pairs, near, inside, on_device,
                                    min_pairs, search, position_sigma, spread)
    count.reshape(-1)[busy] = n[busy]
    use = busy & (n >= max(min_pairs, 1))
    mean.reshape(3, -1)[:, use], error.reshape(3, -1)[:, use] = m[use].T, e[use].T
    return mean, error, count


def _device_pairs(means: DeviceWindowMeans, pairs: ParticlePairs,
                  focus: FocalZone | None) -> PairsOnDevice:
    """``pairs`` on ``means``' device: midpoints, displacements, weights and the focal
    zone's depth ambiguity (``None`` without one)."""
    every = np.arange(len(pairs.midpoints))
    amb = None if focus is None else focus.ambiguity(pairs.midpoints[:, 2])
    return means.pairs(pairs.midpoints, pairs.displacements, pair_weights(pairs, every), amb)


def _device_estimates(means: DeviceWindowMeans, dev: PairsOnDevice, pairs: ParticlePairs,
                      near: WindowLists, inside: WindowLists, on_device: WindowCentres,
                      min_pairs: int, search, position_sigma, spread: float | None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_local_gradients` over the doubled boxes' pairs ``near``, then
    :func:`_window_estimates` over the boxes' pairs ``inside``, on ``means``' device
    (``pairs`` there as ``dev``); the gradients too flat for its normal equations fitted
    here (:func:`local_gradient`); ``on_device``: the field's window centres there."""
    status, device_grad = means.device_gradients(
        dev, near, on_device, search, spread, KEEP_FLOOR, GRADIENT_PAIRS, WELL_POSED)
    flat = np.flatnonzero(status[near.win] == ILL_POSED)
    if len(flat):  # rare: the gradients come to the host only then
        grad = device_grad.get().reshape(-1, 3, 3)
        for k in flat:
            w = near.win[k]
            grad[w] = local_gradient(pairs, near.members(k), on_device.centre(w), search,
                                     spread)
        means.set_gradients(device_grad, grad)
    t = np.array([np.nan] + [t_quantile(k - 1) for k in range(1, inside.largest() + 1)])
    return means.estimates(dev, inside, on_device, device_grad, search, spread, KEEP_FLOOR,
                           max(min_pairs, 1), t, position_sigma)


def _checked_windows(windows, shape: tuple[int, ...]) -> np.ndarray:
    """``windows`` as the boolean ``(nz, ny, nx)`` of the field's grid ``shape``, or a
    ValueError that names the shape wanted."""
    w = np.asarray(windows)
    if w.shape != tuple(shape) or w.dtype != bool:
        raise ValueError(f"windows must be a boolean array of the field's grid shape "
                         f"{tuple(shape)} (nz, ny, nx), one flag per window; got "
                         f"{w.dtype} of shape {w.shape}")
    return w


def _grid_centres(field: PIVResult) -> np.ndarray:
    """The window centres ``(nz * ny * nx, 3)`` ``(x, y, z)`` of ``field``, in
    ``np.ndindex`` order."""
    z, y, x = np.meshgrid(field.z, field.y, field.x, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def _axis_range(p: np.ndarray, c: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Along one axis: for each point ``p`` ``(n,)``, the first of the sorted centres
    ``c`` within ``radius`` of it and the first after them (the test ``|p - c| <=
    radius`` that :class:`scipy.spatial.cKDTree` makes, which holds on a run of
    centres)."""
    lo = np.searchsorted(c, p - radius) - 1  # one candidate to spare each side
    k = int((np.searchsorted(c, p + radius, side="right") - lo).max()) + 1
    idx = lo[:, None] + np.arange(k)
    ok = (idx >= 0) & (idx < len(c))
    ok &= np.abs(p[:, None] - c[idx.clip(0, len(c) - 1)]) <= radius
    first = idx[np.arange(len(p)), ok.argmax(axis=1)]
    return first, first + np.count_nonzero(ok, axis=1)


def _box_members(points: np.ndarray, axes: list[np.ndarray], radius: float,
                 wanted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The points ``(n, 3)`` ``(x, y, z)`` within ``radius`` per axis of each centre of
    the grid ``axes`` (x, y, z): flat (window, point) index pairs, by window (``np.ndindex``
    order of ``(nz, ny, nx)``), then point; what ``cKDTree.query_ball_point(...,
    p=np.inf)`` returns for every centre, one row of windows at a time. ``wanted``: a
    boolean per window (flat), the only windows listed (``None``: all)."""
    (x0, x1), (y0, y1), (z0, z1) = (_axis_range(points[:, a], axes[a], radius)
                                    for a in range(3))
    nx, ny, nz = (len(a) for a in axes)
    want = np.ones((nz, ny, nx), bool) if wanted is None else wanted.reshape(nz, ny, nx)
    rows = want.any(axis=2)
    windows, members = [np.zeros(0, int)], [np.zeros(0, int)]
    for kz in np.flatnonzero(rows.any(axis=1)):
        in_z = np.flatnonzero((z0 <= kz) & (kz < z1))
        for ky in np.flatnonzero(rows[kz]):
            p = in_z[(y0[in_z] <= ky) & (ky < y1[in_z])]
            kx = np.flatnonzero(want[kz, ky])[:, None]
            i, j = np.nonzero((x0[p] <= kx) & (kx < x1[p]))  # by window, then point
            windows.append((kz * ny + ky) * nx + kx[i, 0])
            members.append(p[j])
    return np.concatenate(windows), np.concatenate(members)


def _by_count(window: np.ndarray, size: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Group the entries of the sorted window indices ``window``: for each number of
    entries ``n`` a window holds, those windows ``(g,)`` and their entries ``(g, n)``."""
    count = np.bincount(window, minlength=size)
    start = np.cumsum(count) - count
    for n in np.unique(count[count > 0]):
        which = np.flatnonzero(count == n)
        yield which, start[which, None] + np.arange(n)


def _near_medians(d: np.ndarray, search=SEARCH, spread: float | None = SPREAD) -> np.ndarray:
    """:func:`near_median` of each of ``g`` windows at once: ``d`` ``(g, n, 3)`` gives
    ``(g, n)``."""
    off = np.abs(d - np.median(d, axis=1, keepdims=True))
    reach = np.asarray(search, float)
    if spread is not None:
        robust = spread * MAD_SIGMA * np.median(off, axis=1, keepdims=True)
        reach = np.minimum(reach, np.maximum(robust, KEEP_FLOOR))
    return np.all(off <= reach, axis=2)


def _local_gradients(pairs: ParticlePairs, window: np.ndarray, near: np.ndarray,
                     centres: np.ndarray, search=SEARCH, spread: float | None = SPREAD
                     ) -> np.ndarray:
    """:func:`local_gradient` of every window ``(W, 3, 3)`` (zeros where it fits none),
    from the pairs ``near`` each doubled window holds (flat, sorted by ``window``)."""
    grad = np.zeros((len(centres), 3, 3))
    both = np.hstack([pairs.midpoints, pairs.displacements])
    for which, rows in _by_count(window, len(centres)):
        pos = both[near[rows]]  # (g, n, 6): midpoint, displacement
        keep = _near_medians(pos[..., 3:], search, spread)
        fit = np.count_nonzero(keep, axis=1) >= GRADIENT_PAIRS
        if fit.any():
            pos = pos[fit]
            pos[..., :3] -= centres[which[fit], None]
            grad[which[fit]] = _fit_gradients(pos, keep[fit],
                                              pair_weights(pairs, near[rows[fit]]))
    return grad


def _fit_gradients(pos: np.ndarray, keep: np.ndarray, weight: np.ndarray | None = None
                   ) -> np.ndarray:
    """The least-squares gradients ``(g, 3, 3)`` of the displacements over the offsets
    from each window's centre, ``pos`` ``(g, n, 6)`` (offset, displacement), on the rows
    ``keep`` ``(g, n)``, each component weighted by ``weight`` ``(g, n, 3)`` (``None``:
    alike): :func:`local_gradient`'s, by :func:`_weighted_gradients`."""
    if weight is None:
        return _weighted_gradients(pos[..., :3], pos[..., 3:], keep.astype(float))
    grad = np.empty((len(pos), 3, 3))
    for c in range(3):
        grad[:, c:c + 1] = _weighted_gradients(pos[..., :3], pos[..., 3 + c:4 + c],
                                               keep * weight[..., c])
    return grad


def _weighted_gradients(offset: np.ndarray, values: np.ndarray, w: np.ndarray
                        ) -> np.ndarray:
    """The gradients ``(g, k, 3)`` of ``values`` ``(g, n, k)`` over ``offset`` ``(g, n,
    3)`` by least squares weighted by ``w`` ``(g, n)`` (0: left out): the normal
    equations of both centred on their weighted means (the same full-rank solution as
    ``np.linalg.lstsq`` on ``[1, offset]``); a scatter flatter than :data:`WELL_POSED`
    goes to that ``lstsq`` (its minimum-norm solution where the pairs do not span the
    three axes)."""
    total = w.sum(axis=1)[:, None, None]
    x = offset - np.sum(w[..., None] * offset, axis=1, keepdims=True) / total
    y = values - np.sum(w[..., None] * values, axis=1, keepdims=True) / total
    moments = (w[..., None] * x).transpose(0, 2, 1) @ np.concatenate([x, y], axis=2)
    lam, vec = np.linalg.eigh(moments[..., :3])
    with np.errstate(divide="ignore", invalid="ignore"):
        coef = vec @ ((vec.transpose(0, 2, 1) @ moments[..., 3:]) / lam[..., None])
    grad = coef.transpose(0, 2, 1)
    for g in np.flatnonzero(~(lam[:, 0] > WELL_POSED * lam[:, -1])):
        rows = w[g] > 0
        root = np.sqrt(w[g, rows])[:, None]
        design = np.column_stack([np.ones(np.count_nonzero(rows)), offset[g, rows]])
        grad[g] = np.linalg.lstsq(design * root, values[g, rows] * root,
                                  rcond=None)[0][1:].T
    return grad


def _window_estimates(pairs: ParticlePairs, window: np.ndarray, inside: np.ndarray,
                      centres: np.ndarray, grad: np.ndarray, min_pairs: int, search=SEARCH,
                      focus: FocalZone | None = None, position_sigma=POSITION_SIGMA,
                      spread: float | None = SPREAD
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window: the pairs kept ``(W,)`` and, where at least ``min_pairs`` (and 1),
    :func:`window_estimate`'s mean and uncertainty ``(W, 3)`` (NaN elsewhere) of the
    pairs ``inside`` it (flat, sorted by ``window``), moved to its centre along ``grad``."""
    count = np.zeros(len(centres), int)
    mean, error = np.full((2, len(centres), 3), np.nan)
    for which, rows in _by_count(window, len(centres)):
        mid = pairs.midpoints[inside[rows]]
        offsets = mid - centres[which, None]
        d = pairs.displacements[inside[rows]] - offsets @ grad[which].transpose(0, 2, 1)
        keep = _near_medians(d, search, spread)
        count[which] = np.count_nonzero(keep, axis=1)
        use = count[which] >= max(min_pairs, 1)
        weight = pair_weights(pairs, inside[rows[use]])  # (g, n, 3) or None
        mean[which[use]], error[which[use]] = _estimates(
            d[use], mid[use, :, 2], keep[use], grad[which[use]], focus, position_sigma,
            weight)
    return count, mean, error


def pair_weights(pairs: ParticlePairs, rows: np.ndarray) -> np.ndarray | None:
    """The window means' weights of the pairs ``rows`` (any shape): the inverse of each
    displacement's variance with :data:`WEIGHT_FLOOR` added, ``rows.shape + (3,)``;
    ``None`` where the pairs carry no uncertainty (every pair alike)."""
    if pairs.sigma is None:
        return None
    return 1.0 / (pairs.sigma[rows] ** 2 + np.asarray(WEIGHT_FLOOR) ** 2)


def _estimates(d: np.ndarray, depth: np.ndarray, keep: np.ndarray, grad: np.ndarray,
               focus: FocalZone | None, position_sigma=POSITION_SIGMA,
               weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`window_estimate` of ``g`` windows at once, each of the pairs ``keep``
    ``(g, n)`` of ``d`` ``(g, n, 3)`` at depths ``depth`` ``(g, n)``, weighted by
    ``weight`` ``(g, n, 3)`` (``None``: alike): ``(g, 3)`` each."""
    n = np.count_nonzero(keep, axis=1)
    w = np.where(keep[..., None], 1.0 if weight is None else weight, 0.0)
    total = w.sum(axis=1)
    mean = np.sum(w * d, axis=1) / total
    n_eff = total ** 2 / np.sum(w ** 2, axis=1)  # n when alike
    with np.errstate(divide="ignore", invalid="ignore"):
        spread = np.sum(w * (d - mean[:, None]) ** 2, axis=1) / total * n_eff / (n_eff - 1)
    t = np.array([t_quantile(int(k) - 1) for k in n])
    random = np.sqrt(spread / n_eff) * t[:, None]
    systematic = np.zeros_like(mean)
    if focus is not None:
        systematic[:, 2] = np.sum(focus.ambiguity(depth), axis=1, where=keep) / n
    position = np.sqrt(((grad * np.asarray(position_sigma)) ** 2).sum(axis=2))
    return mean, np.sqrt(random ** 2 + systematic ** 2 + position ** 2)


def repredicted(field: PIVResult, pa: np.ndarray, pb: np.ndarray, min_pairs: int = 3,
                search=SEARCH, focus: FocalZone | None = None,
                spread: float | None = SPREAD, sight: SightLines | None = None, *,
                device_means: DeviceWindowMeans | None = None) -> PIVResult:
    """``field`` refined by the volumes' particles ``pa``, ``pb`` as they are (paired
    along ``field``; :func:`with_window_means`): the predictor of the pairing that the
    fit to the raw images follows, and the field of the windows it leaves without
    pairs. Where a correlation errs by more than the search range (off the axis its
    depth error reaches 3-4 voxels in places, ``benchmarks/field_size.py``) its windows
    find no pairs along it, and would keep it; along this field they find them.

    With ``focus`` and ``sight`` the means are :func:`seen_means`' over the window
    itself: the depth from the pairs that see it (interpolated across the blind zone),
    the blind pairs moved along their lines to it. The correlation errs along the lines
    of sight (a lateral motion off the axis reads as depth there: 1.3-2 voxels at 20-25
    mm on the paper's optics), and the pairing picks, among a particle's peaks along its
    line, the one nearest the predictor; the blind zone's pairs, whose depth is the
    predictor's, kept that error in a predictor from all the window's pairs
    (docs/design.md §7.4 item 6). Over twice the window, as the final depth, the
    predictor misses a boundary layer's depth motion (the small demo 7.0 % of U∞ against
    6.7 %)."""
    pairs = pair_peaks(pa, pb, field, search)
    if focus is not None and sight is not None:
        mean, error, _ = seen_means(pairs, field, focus, sight, field.w, min_pairs, search,
                                    POSITION_SIGMA, spread, depth_support=1.0,
                                    device_means=device_means)
    else:
        mean, error, _ = window_means(pairs, field, min_pairs, search, focus, spread=spread,
                                      device_means=device_means)
    return with_window_means(field, mean, error)[0]


def with_window_means(field: PIVResult, mean: np.ndarray, error: np.ndarray
                      ) -> tuple[PIVResult, np.ndarray]:
    """``field`` with the windows where ``mean`` ``(3, nz, ny, nx)`` is finite replaced
    by it and ``error`` (their uncertainty), then validated as :func:`plenocl.piv3d`
    validates its last pass (normalised median test, outliers replaced by their
    neighbours' median, marked invalid, sigma NaN); and which windows took ``mean``."""
    use = np.isfinite(mean[0]) & ~field.masked
    vectors = np.stack([np.where(use, mean[n], getattr(field, c))
                        for n, c in enumerate("uvw")])
    outlier = normalized_median_test(vectors, ignore=field.masked)
    vectors = np.where(field.masked, vectors, replace_outliers(vectors, outlier | field.masked))
    valid = (field.valid | use) & ~outlier & ~field.masked
    comps = {c: vectors[n] for n, c in enumerate("uvw")}
    for n, c in enumerate("uvw"):
        sigma = getattr(field, f"sigma_{c}")
        sigma = np.full(field.u.shape, np.nan) if sigma is None else sigma
        comps[f"sigma_{c}"] = np.where(valid, np.where(use, error[n], sigma), np.nan)
    outlier = outlier | (field.outlier & ~use)
    return dataclasses.replace(field, **comps, valid=valid, outlier=outlier), use


def seen_means(pairs: ParticlePairs, field: PIVResult, focus: FocalZone,
               sight: SightLines | None = None, fallback_w: np.ndarray | None = None,
               min_pairs: int = 3, search=SEARCH, position_sigma=POSITION_SIGMA,
               spread: float | None = SPREAD, depth_support: float = DEPTH_SUPPORT,
               outliers: float | None = None, *, device_means: DeviceWindowMeans | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`window_means` with the depth seen by the camera: each window's depth from
    the pairs that see it in a box ``depth_support`` times the window
    (:func:`seen_depth` with that ``support``); with ``sight``, the lateral means then
    taken after moving the pairs along their lines of sight to that depth (every pair;
    with ``depth_support`` 1, the blind ones alone), ``fallback_w`` ``(nz, ny, nx)``
    (the predictor's) giving the depth where no window's is known.

    With ``sight``, the lateral means also leave out the moved pairs that lie more than
    ``outliers`` combined scales from their neighbours
    (:func:`plenocl.piv.pairoutliers.neighbour_outliers` along these means; ``None``:
    none left out), and a window left with fewer than ``min_pairs`` pairs takes them
    from a box :data:`SPARSE_SUPPORT` times its size (:func:`sparse_filled`).
    ``device_means``: where the window means run (:func:`window_means`)."""
    if sight is None:
        mean, error, count = window_means(pairs, field, min_pairs, search, focus,
                                          position_sigma, spread, device_means=device_means)
        mean[2], error[2] = seen_depth(pairs, field, focus, mean[2], error[2], min_pairs,
                                       search, position_sigma, spread, depth_support,
                                       device_means=device_means)
        return mean, error, count
    mean, error = np.full((2, 3, *field.u.shape), np.nan)  # lateral: the moved pairs'
    mean[2], error[2] = seen_depth(pairs, field, focus, None, None, min_pairs, search,
                                   position_sigma, spread, depth_support, device_means=device_means)
    known = np.isfinite(mean[2])
    depth = dataclasses.replace(field, w=np.where(known, mean[2], field.w if fallback_w is None
                                                  else fallback_w))
    pairs = (sight.unseen_along_sight(pairs, depth, focus) if depth_support == 1
             else sight.along_sight(pairs, depth))
    lateral, lateral_error, count = window_means(pairs, field, min_pairs, search, focus,
                                                 position_sigma, spread, device_means=device_means)
    if outliers is not None:
        trend = dataclasses.replace(depth, **{c: np.where(np.isfinite(lateral[n]), lateral[n],
                                                          getattr(field, c))
                                              for n, c in enumerate("uv")})
        pairs = pairs.subset(~neighbour_outliers(pairs.midpoints, pairs.displacements,
                                                 pairs.sigma, trend, threshold=outliers))
        lateral, lateral_error, count = window_means(pairs, field, min_pairs, search, focus,
                                                     position_sigma, spread,
                                                     device_means=device_means)
    lateral, lateral_error, count = sparse_filled(
        (lateral, lateral_error, count), known, pairs, field, min_pairs, search, focus,
        position_sigma, spread, device_means=device_means)
    mean[:2], error[:2] = lateral[:2], lateral_error[:2]
    return mean, error, count


def sparse_filled(means: tuple[np.ndarray, np.ndarray, np.ndarray], known: np.ndarray,
                  pairs: ParticlePairs, field: PIVResult, min_pairs: int = 3,
                  search=SEARCH, focus: FocalZone | None = None,
                  position_sigma=POSITION_SIGMA, spread: float | None = SPREAD, *,
                  device_means: DeviceWindowMeans | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``means`` (:func:`window_means`' mean, uncertainty and counts) with each window
    that has none but whose depth is ``known`` ``(nz, ny, nx)`` given the means of the
    pairs in a box :data:`SPARSE_SUPPORT` times it (each moved to its centre along their
    gradient), where those hold ``min_pairs``: such a window kept the predictor's
    vector, and in the focal zone at the paper's full size that erred 0.2-0.37 voxel
    laterally where one well-fitted pair lay in it (docs/design.md §7.4 item 8)."""
    mean, error, count = means
    empty = ~np.isfinite(mean[0]) & known
    if not empty.any():
        return mean, error, count
    wide, wide_error, wide_count = window_means(pairs, field, min_pairs, search, focus,
                                                position_sigma, spread, SPARSE_SUPPORT,
                                                windows=empty, device_means=device_means)
    fill = empty & np.isfinite(wide[0])
    return (np.where(fill, wide, mean), np.where(fill, wide_error, error),
            np.where(fill, wide_count, count))


def seen_depth(pairs: ParticlePairs, field: PIVResult, focus: FocalZone,
               w: np.ndarray | None, sigma_w: np.ndarray | None, min_pairs: int = 3,
               search=SEARCH,
               position_sigma=POSITION_SIGMA, spread: float | None = SPREAD,
               support: float = 1.0, *, device_means: DeviceWindowMeans | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """The depth component of every window ``(nz, ny, nx)`` and its uncertainty from
    the pairs that see depth (:meth:`FocalZone.sees_depth`) alone.

    A window centred where the camera sees depth, with at least ``min_pairs`` such
    pairs, takes their mean (:func:`window_means`). A window centred in the blind zone
    takes the linear interpolation in depth between the nearest such windows above and
    below in its column (the nearest one at an end), with the interpolated uncertainty
    and half the two values' difference added in quadrature: its own seeing pairs lie at
    its faces, and carried to its centre along their gradient they missed the small
    demo's boundary layer by more (8.3 % of U∞ against 7.6 %). A blind window whose
    column has no window that sees depth (a volume hardly deeper than a window) takes its
    own seeing pairs' mean, and where no window sees depth warns (:func:`_warn_shallow`):
    all its pairs' mean read the depth motion 7 % low, the blind pairs' 42 %
    (docs/design.md §7.4). Others keep
    ``w`` and ``sigma_w`` (all their pairs' mean; ``None``: :func:`window_means` of all
    the pairs, computed for those windows alone). ``support``: the seeing pairs are
    taken from a box this many times the window (:func:`window_means`).
    """
    seeing = focus.sees_depth(pairs.midpoints[:, 2])
    blind = ~focus.sees_depth(field.z)[:, None, None]
    mean, error, _ = window_means(pairs.subset(seeing), field, min_pairs, search, focus,
                                  position_sigma, spread, support,
                                  windows=np.broadcast_to(~blind, field.u.shape),
                                  device_means=device_means)
    seen = np.where(blind, np.nan, mean[2])
    seen_sigma = np.where(blind, np.nan, error[2])
    fill, fill_sigma = depth_interpolation(seen, seen_sigma, field.z)
    if w is None:  # wanted in the blind zone and where the seeing pairs are too few
        every, every_error, _ = window_means(pairs, field, min_pairs, search, focus,
                                             position_sigma, spread,
                                             windows=~np.isfinite(seen), device_means=device_means)
        w, sigma_w = every[2], every_error[2]
    filled = blind & np.isfinite(w) & np.isfinite(fill)
    out = np.where(np.isfinite(seen), seen, np.where(filled, fill, w))
    out_sigma = np.where(np.isfinite(seen), seen_sigma, np.where(filled, fill_sigma, sigma_w))
    orphan = blind & ~np.isfinite(fill)  # a column without a window that sees depth
    if orphan.any():
        own, own_error, _ = window_means(pairs.subset(seeing), field, min_pairs, search,
                                         focus, position_sigma, spread, support,
                                         windows=orphan, device_means=device_means)
        take = orphan & np.isfinite(own[2])
        out, out_sigma = np.where(take, own[2], out), np.where(take, own_error[2], out_sigma)
        if blind.all():  # no depth of windows sees depth
            _warn_shallow(focus, field)
    return out, out_sigma


def _warn_shallow(focus: FocalZone, field: PIVResult) -> None:
    """Warn that every window lies in the blind zone (a volume hardly deeper than a
    window about the focal plane): their depth component comes from the few pairs they
    hold beyond the zone."""
    reach = DEPTH_BLIND * focus.resolution
    warnings.warn(
        f"every window's centre (z = {', '.join(f'{z:g}' for z in field.z)} voxels) lies "
        f"within the camera's blind zone about the focal plane ({reach:.1f} voxels either "
        "side, where it cannot place a particle in depth), so no window beyond it gives "
        "their depth motion: their depth "
        "displacements come from the few particles beyond the zone and read low (4-11 % "
        "in simulated scenes, against 1 % in a volume twice as deep). Where depth "
        "motion matters, reconstruct a deeper volume (plenocl grid --z; docs/design.md "
        "§7.4)", stacklevel=2)


def depth_interpolation(w: np.ndarray, sigma: np.ndarray, z: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Per column ``(y, x)`` of ``w`` ``(nz, ny, nx)`` (NaN: missing), the linear
    interpolation in ``z`` (ascending) between the finite values, constant beyond the
    first and last (:func:`numpy.interp`'s, to the bit), their uncertainty ``sigma``
    interpolated likewise (NaN taken as 0) with half the bracketing values' difference
    added in quadrature; NaN in a column without any. Every column at once: each row's
    nearest finite rows below and above it by running maxima and minima of their
    indices (a column at a time took 0.06 s a call at paper size)."""
    nz = len(z)
    fill, fill_sigma = np.full((2, *w.shape), np.nan)
    flat_w = w.reshape(nz, -1)
    cols = np.flatnonzero(np.isfinite(flat_w).any(axis=0))
    if not len(cols):
        return fill, fill_sigma
    values, ok = flat_w[:, cols], np.isfinite(flat_w[:, cols])
    sig = np.nan_to_num(sigma.reshape(nz, -1)[:, cols])
    rows = np.broadcast_to(np.arange(nz)[:, None], ok.shape)
    below = np.maximum.accumulate(np.where(ok, rows, -1), axis=0)  # finite row <= i
    above = np.minimum.accumulate(np.where(ok, rows, nz)[::-1], axis=0)[::-1]  # >= i
    lo, hi = np.where(below < 0, above, below), np.where(above >= nz, below, above)
    z = np.asarray(z, float)
    # the bracket's values (numpy.searchsorted's in the finite rows): the first finite
    # row at or above (else the last), and the finite row before that one (else itself)
    before = np.concatenate([np.full((1, len(cols)), -1), below[:-1]])  # finite row < i
    lower = _rows(before, hi)
    lower = np.where(lower < 0, hi, lower)
    spread = np.abs(_rows(values, hi) - _rows(values, lower)) / 2
    inside = lo != hi
    fill.reshape(nz, -1)[:, cols] = _interp(values, z, lo, hi, inside)
    fill_sigma.reshape(nz, -1)[:, cols] = np.hypot(_interp(sig, z, lo, hi, inside), spread)
    return fill, fill_sigma


def _rows(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``a[rows[i, c], c]``."""
    return np.take_along_axis(a, rows, axis=0)


def _interp(fp: np.ndarray, z: np.ndarray, lo: np.ndarray, hi: np.ndarray,
            inside: np.ndarray) -> np.ndarray:
    """:func:`numpy.interp`'s value at each row's depth ``z`` between rows ``lo`` and
    ``hi`` of each column (``fp[lo]`` where they are one row: at a finite row, or beyond
    the ends), by its formula ``slope (z - z_lo) + fp_lo``."""
    f_lo, f_hi, z_lo = _rows(fp, lo), _rows(fp, hi), z[lo]
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = (f_hi - f_lo) / (z[hi] - z_lo)
        return np.where(inside, slope * (z[:, None] - z_lo) + f_lo, f_lo)


def refine_with_particles(field: PIVResult, vol_a: np.ndarray, vol_b: np.ndarray,
                          threshold: float = 0.1, min_pairs: int = 3,
                          search=SEARCH, focus: FocalZone | None = None,
                          fit: ImageFit | None = None,
                          sight: SightLines | None = None,
                          maxima: Callable | None = None,
                          spread: float | None = SPREAD, weighted: bool = True,
                          depth_support: float = DEPTH_SUPPORT,
                          outliers: float | None = OUTLIER_THRESHOLD, *,
                          device_means: DeviceWindowMeans | None = None,
                          on_device: tuple | None = None) -> PIVResult:
    """``field`` with every window that holds at least ``min_pairs`` matched particle
    pairs replaced by their mean displacement at the window's centre and its uncertainty
    (``sigma_*``; see the module documentation).

    Vectors that were masked stay masked; windows with too few pairs keep the
    correlation's vector and uncertainty. The refined field is validated as
    :func:`plenocl.piv3d` validates its last pass (normalised median test, outliers
    replaced by their neighbours' median, marked invalid, sigma NaN). ``refinement``
    records the pairs found, the vectors refined, the outliers and the particles the
    fit to the raw images dropped (``dropped``: their fit left the grid or was not
    finite; docs/design.md §7.2). ``maxima``: where the volumes' local maxima are found
    (:func:`volume_particles`). ``spread``: the pairs each window keeps
    (:func:`near_median`; ``None``: all within ``search`` of the window's median).
    ``weighted``: the window means weigh the pairs by their fits' uncertainties
    (:func:`pair_weights`; ``False``: alike, the refinement before 2026-11-29).
    ``depth_support``: with ``focus``, the depth comes from the pairs in a box this many
    times each window (:data:`DEPTH_SUPPORT`; 1: the window itself), and with ``sight``
    every pair is then moved along its line of sight to that depth
    (:meth:`SightLines.along_sight`; 1: the blind pairs alone, the window means of
    2026-11-29 afternoon; the predictor's seen depth and the moved pairs' covariances
    of that evening stay). ``outliers``: with ``focus`` and ``sight``, the lateral
    means leave out the pairs this many combined scales from their neighbours
    (:func:`plenocl.piv.pairoutliers.neighbour_outliers`; ``None``: none, the
    refinement before 2026-11-29 night). ``device_means``: the window means on that device
    (:class:`plenocl.piv.devicemeans.DeviceWindowMeans`; ``None``: on the host).
    ``on_device``: the volumes' float32 device copies ``(dev_a, dev_b)`` (the same
    values; a reconstruction's ``info.volume_on_device``), which the local maxima and the
    tube sums on their context read instead of uploading the volumes
    (:func:`volume_particles`).
    """
    on_device = device_copies(on_device, np.shape(vol_a), who="refine_with_particles")
    if spread is not None and not spread > 0:
        raise ValueError(f"refine_with_particles got spread={spread}: give a positive "
                         f"number of robust standard deviations (ROBUST_SPREAD = "
                         f"{ROBUST_SPREAD:g}), or None for the search range alone")
    if not 1.0 <= depth_support < np.inf:
        raise ValueError(f"refine_with_particles got depth_support={depth_support}: give "
                         f"a finite number of windows, at least 1 (the window itself; "
                         f"DEPTH_SUPPORT = {DEPTH_SUPPORT:g})")
    if outliers is not None and not 0 < outliers < np.inf:
        raise ValueError(f"refine_with_particles got outliers={outliers}: give a positive "
                         f"number of combined scales from a pair's neighbours "
                         f"(OUTLIER_THRESHOLD = {OUTLIER_THRESHOLD:g}), or None to leave "
                         f"no pair out")
    pa, pb = (volume_particles(v, threshold, sight, maxima, dev)
              for v, dev in zip((vol_a, vol_b), on_device or (None, None), strict=True))
    predictor = repredicted(field, pa, pb, min_pairs, search, focus, spread, sight,
                            device_means=device_means)
    pairs = pair_peaks(pa, pb, predictor, search, fit)
    if not weighted:
        pairs = pairs.alike()
    position = POSITION_SIGMA if fit is None else FITTED_POSITION_SIGMA
    if focus is None:
        mean, error, count = window_means(pairs, field, min_pairs, search, None, position,
                                          spread, device_means=device_means)
    else:
        mean, error, count = seen_means(pairs, field, focus, sight, predictor.w, min_pairs,
                                        search, position, spread, depth_support, outliers,
                                        device_means=device_means)
    refined, use = with_window_means(predictor, mean, error)
    log = {"refinement": "particles", "pairs": len(pairs.midpoints),
           "vectors": int(use.sum()), "outliers": int(np.count_nonzero(refined.outlier)),
           "median_pairs": float(np.median(count[use])) if use.any() else 0.0,
           "dropped": pairs.dropped}
    return dataclasses.replace(refined, refinement=log)
