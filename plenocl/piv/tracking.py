"""Particle refinement of a correlation field (docs/design.md §7.1): the particles of the
two reconstructed volumes, matched with the correlation's displacement as predictor,
averaged per interrogation window.

A reconstructed volume places each particle within about 0.1 voxel laterally, but the
correlation of whole windows also sees every ghost and the particles' irregular,
depth-elongated shapes, and it reads the displacement about three times less precisely
(``benchmarks/accuracy.py``). Here each peak of the first volume (local maxima above
``threshold`` of the volume's maximum, 3-point Gaussian sub-voxel positions) is sent
along the predicted displacement and paired with the nearest peak of the second volume
within ``search`` voxels (x, y, z); only mutual nearest neighbours are kept (a ghost
rarely has a partner both ways). Each window of the correlation's final grid then takes
the mean displacement of the pairs whose midpoints lie in it, each first moved to the
window's centre along the local displacement gradient (a least-squares linear fit to the
pairs in the window grown to twice its size, where it holds at least
:data:`GRADIENT_PAIRS`; otherwise none), after leaving out pairs farther than ``search``
from the window's median. Without that step, a gradient across a sparse window would
bias its mean by where its few particles happen to lie. The vector's uncertainty
(:func:`window_estimate`) adds in quadrature the half-width of the mean's 68.3 %
confidence interval (the standard error times Student's t quantile for the pairs it
holds: 1.32 for 3 pairs, 1.05 for 11), the systematic depth error of pairs in the
camera's focal zone (:class:`FocalZone`), which err together, and the particles'
reconstructed depth position carried through the local gradient. Windows with fewer
than ``min_pairs`` pairs keep the correlation's vector. The refined field is validated
like the correlation's last pass (normalised median test, outliers replaced): a cluster
of failed windows at a face of the volume can survive the correlation's test and the
refinement, which follows it.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial import cKDTree

from ..peaks import find_particles
from ..vectorfield import PIVResult
from .validation import normalized_median_test, replace_outliers

if TYPE_CHECKING:
    from collections.abc import Iterator

    from ..camera import Camera
    from ..grid import Grid
    from .imagefit import ImageFit

#: Match tolerance (x, y, z voxels): depth is about three times less certain.
SEARCH = (1.0, 1.0, 3.0)
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


@dataclass(frozen=True)
class ParticlePairs:
    """Matched particles: midpoints ``(N, 3)`` and displacements ``(N, 3)``, both as
    ``(x, y, z)`` voxels; ``dropped``: the peaks the fit to the raw images dropped
    (:class:`plenocl.piv.imagefit.FittedParticles`), left out before pairing again."""

    midpoints: np.ndarray
    displacements: np.ndarray
    dropped: int = 0


def predicted(field: PIVResult, points: np.ndarray) -> np.ndarray:
    """The displacement ``(N, 3)`` ``(dx, dy, dz)`` of a :class:`PIVResult` at ``points``
    ``(N, 3)`` ``(x, y, z)``: trilinear between window centres, the nearest value beyond
    them; masked (NaN) vectors count as 0."""
    axes = (field.z, field.y, field.x)
    zyx = np.clip(points[:, ::-1], [a[0] for a in axes], [a[-1] for a in axes])
    comps = []
    for c in (field.u, field.v, field.w):
        comps.append(RegularGridInterpolator(axes, np.nan_to_num(c), bounds_error=False)(zyx))
    return np.column_stack(comps)


def pair_particles(vol_a: np.ndarray, vol_b: np.ndarray, field: PIVResult,
                   threshold: float = 0.1, search=SEARCH,
                   fit: ImageFit | None = None) -> ParticlePairs:
    """Mutual nearest-neighbour pairs of the two volumes' peaks along ``field``; with
    ``fit``, the paired peaks are refined against their raw images and paired again
    (the peaks the fit dropped left out, and counted)."""
    pa, _ = find_particles(vol_a, threshold)
    pb, _ = find_particles(vol_b, threshold)
    ia, ib = mutual_pairs(pa, pb, field, search)
    dropped = 0
    if fit is not None and len(ia):
        pa[ia], pb[ib] = fit.refine_pair(pa[ia], pb[ib])
        kept_a, kept_b = (np.all(np.isfinite(p), axis=1) for p in (pa, pb))
        dropped = int(np.count_nonzero(~kept_a) + np.count_nonzero(~kept_b))
        pa, pb = pa[kept_a], pb[kept_b]
        ia, ib = mutual_pairs(pa, pb, field, search)
    disp = pb[ib] - pa[ia]
    return ParticlePairs(pa[ia] + disp / 2, disp, dropped)


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


def near_median(d: np.ndarray, search=SEARCH) -> np.ndarray:
    """Which displacements ``d`` ``(n, 3)`` lie within ``search`` (x, y, z voxels) of
    their median, per component: the pairs a window or a gradient fit keeps."""
    if not len(d):
        return np.zeros(0, bool)
    return np.all(np.abs(d - np.median(d, axis=0)) <= search, axis=1)


def local_gradient(pairs: ParticlePairs, near: list[int], centre: np.ndarray,
                   search=SEARCH) -> np.ndarray:
    """The displacement gradient ``(3, 3)`` (component, x/y/z) fitted by least squares to
    the pairs ``near`` (those within ``search`` of their median), or zeros with fewer
    than :data:`GRADIENT_PAIRS` of them."""
    d = pairs.displacements[near]
    keep = near_median(d, search)
    if np.count_nonzero(keep) < GRADIENT_PAIRS:
        return np.zeros((3, 3))
    offsets = pairs.midpoints[near][keep] - centre
    design = np.column_stack([np.ones(len(offsets)), offsets])
    coef, *_ = np.linalg.lstsq(design, d[keep], rcond=None)
    return coef[1:].T


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

    def ambiguity(self, z: np.ndarray) -> np.ndarray:
        """A pair's systematic depth uncertainty (voxels) at depth index ``z``:
        :data:`FOCAL_SYSTEMATIC` times the resolution at the plane, falling linearly to
        0 at twice the resolution, where the blur spans two microlenses and the
        parallax is read in every case."""
        reach = np.clip(1.0 - np.abs(np.asarray(z, float) - self.plane)
                        / (2.0 * self.resolution), 0.0, None)
        return FOCAL_SYSTEMATIC * self.resolution * reach


@functools.cache
def t_quantile(dof: int) -> float:
    """Student's t quantile at :data:`ONE_SIGMA` for ``dof`` degrees of freedom, computed
    once per count (SciPy's quantile costs about 0.1 ms a call; a paper-size field has
    about 10,000 windows and a few dozen distinct counts)."""
    return float(stats.t.ppf(ONE_SIGMA, dof))


def window_estimate(d: np.ndarray, depth: np.ndarray, grad: np.ndarray,
                    focus: FocalZone | None, position_sigma=POSITION_SIGMA
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The displacement ``(3,)`` of one window from its pairs' displacements ``d``
    ``(n, 3)`` (already moved to the window's centre) at depth indices ``depth``, and
    its standard uncertainty.

    The displacement is the pairs' mean. Its uncertainty adds in quadrature the random
    part (the standard error times Student's t quantile for ``n`` pairs), the focal
    zone's systematic depth part (the mean of the pairs' :meth:`FocalZone.ambiguity`:
    the pairs near the focal plane err together, so it does not shrink with their
    number; 0 without ``focus``), and the particles' positions (``position_sigma``,
    x, y, z voxels: :data:`POSITION_SIGMA` as the volume places them,
    :data:`FITTED_POSITION_SIGMA` fitted to the images) carried through the local
    displacement gradient ``grad`` ``(3, 3)``.
    """
    n = len(d)
    random = d.std(axis=0, ddof=1) / np.sqrt(n) * t_quantile(n - 1)
    systematic = np.zeros(3)
    if focus is not None:
        systematic[2] = focus.ambiguity(depth).mean()
    position = np.sqrt(((grad * np.asarray(position_sigma)) ** 2).sum(axis=1))
    return d.mean(axis=0), np.sqrt(random ** 2 + systematic ** 2 + position ** 2)


#: Smallest ratio of the least to the largest eigenvalue of a window's centred offsets'
#: scatter for which :func:`_fit_gradients` solves the normal equations (their error,
#: about the squared condition number times the rounding, stays below 1e-12 of the
#: gradient); flatter spreads of pairs go to ``np.linalg.lstsq`` as in
#: :func:`local_gradient`.
WELL_POSED = 1e-4


def window_means(pairs: ParticlePairs, field: PIVResult, min_pairs: int = 3, search=SEARCH,
                 focus: FocalZone | None = None, position_sigma=POSITION_SIGMA
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window of ``field``'s grid: the displacement of its pairs at the window's
    centre ``(3, nz, ny, nx)`` (NaN where fewer than ``min_pairs`` pairs remain; see
    :func:`window_estimate`), its uncertainty, and the pair counts.

    The same as :func:`plenocl.reference.tracking.window_means_reference`, the
    per-window loop over
    :func:`local_gradient`, :func:`near_median` and :func:`window_estimate`, computed for
    all windows holding the same number of pairs at once: about 5 times faster at the
    paper's size (11,220 windows, 5,000 pairs; ``benchmarks/window_means.py``), the
    same counts, means and uncertainties within a few 1e-15 voxel.
    """
    shape = field.u.shape
    mean, error = np.full((2, 3, *shape), np.nan)
    count = np.zeros(shape, int)
    if not len(pairs.midpoints):
        return mean, error, count
    half = np.asarray(field.window[::-1], float) / 2  # (x, y, z)
    points = pairs.midpoints / half
    axes = [a / h for a, h in zip((field.x, field.y, field.z), half)]
    centres = _grid_centres(field)
    win, member = _box_members(points, axes, 1.0)
    busy = np.bincount(win, minlength=count.size) >= min_pairs
    near_win, near = _box_members(points, axes, 2.0)
    grad = _local_gradients(pairs, near_win[busy[near_win]], near[busy[near_win]],
                            centres, search)
    inside = busy[win]
    n, m, e = _window_estimates(pairs, win[inside], member[inside], centres, grad,
                                min_pairs, search, focus, position_sigma)
    count.reshape(-1)[busy] = n[busy]
    use = busy & (n >= max(min_pairs, 1))
    mean.reshape(3, -1)[:, use], error.reshape(3, -1)[:, use] = m[use].T, e[use].T
    return mean, error, count


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


def _box_members(points: np.ndarray, axes: list[np.ndarray], radius: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The points ``(n, 3)`` ``(x, y, z)`` within ``radius`` per axis of each centre of
    the grid ``axes`` (x, y, z): flat (window, point) index pairs, by window (``np.ndindex``
    order of ``(nz, ny, nx)``), then point; what ``cKDTree.query_ball_point(...,
    p=np.inf)`` returns for every centre, one row of windows at a time."""
    (x0, x1), (y0, y1), (z0, z1) = (_axis_range(points[:, a], axes[a], radius)
                                    for a in range(3))
    nx, ny, nz = (len(a) for a in axes)
    kx = np.arange(nx)[:, None]
    windows, members = [], []
    for kz in range(nz):
        in_z = np.flatnonzero((z0 <= kz) & (kz < z1))
        for ky in range(ny):
            p = in_z[(y0[in_z] <= ky) & (ky < y1[in_z])]
            i, j = np.nonzero((x0[p] <= kx) & (kx < x1[p]))  # by window, then point
            windows.append((kz * ny + ky) * nx + i)
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


def _near_medians(d: np.ndarray, search=SEARCH) -> np.ndarray:
    """:func:`near_median` of each of ``g`` windows at once: ``d`` ``(g, n, 3)`` gives
    ``(g, n)``."""
    return np.all(np.abs(d - np.median(d, axis=1, keepdims=True)) <= search, axis=2)


def _local_gradients(pairs: ParticlePairs, window: np.ndarray, near: np.ndarray,
                     centres: np.ndarray, search=SEARCH) -> np.ndarray:
    """:func:`local_gradient` of every window ``(W, 3, 3)`` (zeros where it fits none),
    from the pairs ``near`` each doubled window holds (flat, sorted by ``window``)."""
    grad = np.zeros((len(centres), 3, 3))
    both = np.hstack([pairs.midpoints, pairs.displacements])
    for which, rows in _by_count(window, len(centres)):
        pos = both[near[rows]]  # (g, n, 6): midpoint, displacement
        keep = _near_medians(pos[..., 3:], search)
        fit = np.count_nonzero(keep, axis=1) >= GRADIENT_PAIRS
        if fit.any():
            pos = pos[fit]
            pos[..., :3] -= centres[which[fit], None]
            grad[which[fit]] = _fit_gradients(pos, keep[fit])
    return grad


def _fit_gradients(pos: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The least-squares gradients ``(g, 3, 3)`` of the displacements over the offsets
    from each window's centre, ``pos`` ``(g, n, 6)`` (offset, displacement), on the rows
    ``keep`` ``(g, n)``: the normal equations of both centred on their means (the same
    full-rank solution as :func:`local_gradient`'s ``np.linalg.lstsq`` on ``[1,
    offset]``); a scatter flatter than :data:`WELL_POSED` goes to that ``lstsq`` (its
    minimum-norm solution where the pairs do not span the three axes)."""
    w = keep[..., None]
    m = np.count_nonzero(keep, axis=1)
    centred = (pos - np.sum(pos, axis=1, where=w, keepdims=True) / m[:, None, None]) * w
    moments = centred[..., :3].transpose(0, 2, 1) @ centred  # (g, 3, 6)
    lam, vec = np.linalg.eigh(moments[..., :3])
    with np.errstate(divide="ignore", invalid="ignore"):
        coef = vec @ ((vec.transpose(0, 2, 1) @ moments[..., 3:]) / lam[..., None])
    grad = coef.transpose(0, 2, 1)
    for g in np.flatnonzero(~(lam[:, 0] > WELL_POSED * lam[:, -1])):
        design = np.column_stack([np.ones(m[g]), pos[g, keep[g], :3]])
        grad[g] = np.linalg.lstsq(design, pos[g, keep[g], 3:], rcond=None)[0][1:].T
    return grad


def _window_estimates(pairs: ParticlePairs, window: np.ndarray, inside: np.ndarray,
                      centres: np.ndarray, grad: np.ndarray, min_pairs: int, search=SEARCH,
                      focus: FocalZone | None = None, position_sigma=POSITION_SIGMA
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
        keep = _near_medians(d, search)
        count[which] = np.count_nonzero(keep, axis=1)
        use = count[which] >= max(min_pairs, 1)
        mean[which[use]], error[which[use]] = _estimates(
            d[use], mid[use, :, 2], keep[use], grad[which[use]], focus, position_sigma)
    return count, mean, error


def _estimates(d: np.ndarray, depth: np.ndarray, keep: np.ndarray, grad: np.ndarray,
               focus: FocalZone | None, position_sigma=POSITION_SIGMA
               ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`window_estimate` of ``g`` windows at once, each of the pairs ``keep``
    ``(g, n)`` of ``d`` ``(g, n, 3)`` at depths ``depth`` ``(g, n)``: ``(g, 3)`` each."""
    n = np.count_nonzero(keep, axis=1)
    w = keep[..., None]
    mean = np.sum(d, axis=1, where=w) / n[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        var = np.sum((d - mean[:, None]) ** 2, axis=1, where=w) / (n[:, None] - 1)
    t = np.array([t_quantile(int(k) - 1) for k in n])
    random = np.sqrt(var) / np.sqrt(n)[:, None] * t[:, None]
    systematic = np.zeros_like(mean)
    if focus is not None:
        systematic[:, 2] = np.sum(focus.ambiguity(depth), axis=1, where=keep) / n
    position = np.sqrt(((grad * np.asarray(position_sigma)) ** 2).sum(axis=2))
    return mean, np.sqrt(random ** 2 + systematic ** 2 + position ** 2)


def refine_with_particles(field: PIVResult, vol_a: np.ndarray, vol_b: np.ndarray,
                          threshold: float = 0.1, min_pairs: int = 3,
                          search=SEARCH, focus: FocalZone | None = None,
                          fit: ImageFit | None = None) -> PIVResult:
    """``field`` with every window that holds at least ``min_pairs`` matched particle
    pairs replaced by their mean displacement at the window's centre and its uncertainty
    (``sigma_*``; see the module documentation).

    Vectors that were masked stay masked; windows with too few pairs keep the
    correlation's vector and uncertainty. The refined field is validated as
    :func:`plenocl.piv3d` validates its last pass (normalised median test, outliers
    replaced by their neighbours' median, marked invalid, sigma NaN). ``refinement``
    records the pairs found, the vectors refined, the outliers and the particles the
    fit to the raw images dropped (``dropped``: their fit left the grid or was not
    finite; docs/design.md §7.2).
    """
    pairs = pair_particles(vol_a, vol_b, field, threshold, search, fit)
    position = POSITION_SIGMA if fit is None else FITTED_POSITION_SIGMA
    mean, error, count = window_means(pairs, field, min_pairs, search, focus, position)
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
    log = {"refinement": "particles", "pairs": len(pairs.midpoints),
           "vectors": int(use.sum()), "outliers": int(outlier.sum()),
           "median_pairs": float(np.median(count[use])) if use.any() else 0.0,
           "dropped": pairs.dropped}
    return dataclasses.replace(field, **comps, valid=valid, outlier=outlier,
                               refinement=log)
