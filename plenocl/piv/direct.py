"""Direct (non-FFT) correlation of every window at the 63 lags around zero.

After the first pass the volumes are deformed by the predictor, so the residual
displacement of most windows is below one voxel laterally and only the lags ``s`` of
:data:`AXIS_LAGS` are needed to locate and fit the peak: ``{-1, 0, 1}`` across and
``{-3, ..., 3}`` in depth, where a plenoptic camera reads positions worst and the residual
after a deformation is often a voxel or two (at the paper's full size, more than half
the windows of the first deformed pass peak one voxel off in depth and none laterally,
and a tenth two voxels off; design.md §7.5), so that a peak up to two voxels off in
depth is still fitted here. For a window with low corner ``L`` the normalised
correlation at lag ``s`` is the weighted Pearson coefficient

    r(s) = cov(s) / sqrt(var_a(s) var_b(s)),
    cov(s) = S_s[a(L + q) b(L + q + s)] - S_s[a(L + q)] S_s[b(L + q + s)] / S_s[1],

with ``S_s[f] = sum_q W(q + s/2) f(q)``: a separable Gaussian weight (the square of the
FFT path's, which weights both windows) centred between the two windows compared and
reaching three standard deviations, beyond the window itself (:func:`margin`); both
volumes are zero outside. A volume against itself is then exactly symmetric in ``s``, as
the FFT's circular autocorrelation is, which keeps iterative deformation from drifting.
Every ``S`` is a separable filter evaluated only at the window corners: three matrix
products (:class:`WindowSums`), independent of the overlap, about 30 sweeps over the
volume per pass instead of one 3-D FFT per window. :class:`HostSums` runs them on the
host with BLAS, each sum on one thread (:func:`parallel_sums`), so the results do not
depend on the thread count; :class:`plenocl.piv.devicesums.DeviceSums` runs the same sums
on an OpenCL device (``kernels/windowsums.cl``, banded instead of dense, each sum one
work-item's loop), which ``piv3d`` uses beside its device deformer.

:func:`correlate_direct` returns the 63 coefficients per window; :func:`fit_direct`
locates the peak and fits it per axis with the same three-point Gaussian as the FFT path
(:func:`plenocl.peaks.gaussian_subpixel`) where its neighbours are among the lags (the
peak at zero laterally and within two voxels in depth); :func:`correlate_deformed` sends
the other windows, and weak ones, to the FFT;
:func:`correlation_uncertainty` estimates each vector's uncertainty. The plain
per-window twin is :func:`plenocl.reference.direct.correlate_windows`.
"""

from __future__ import annotations

import itertools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy import ndimage
from threadpoolctl import threadpool_limits

from ..opencl.threads import thread_count
from ..peaks import gaussian_subpixel
from .correlation import Correlation, WindowGrid, correlate, gaussian_weight

#: The correlation's method, recorded with every batch field
#: (:func:`plenocl.batch.record.run_record`): a batch rerun re-correlates the pairs whose
#: fields an earlier method made from the same settings. Change it whenever the
#: correlation makes a different field from the same settings (rounding included).
METHOD = ("direct at 63 lags, three in depth (issue 46, 2026-11-28 evening); the windows "
          "fitted and the correlated-sum rows added in blocks on the device (2026-12-02)")
#: The lags of each axis ``(z, y, x)``: three voxels either way in depth, one across.
AXIS_LAGS = ((-3, -2, -1, 0, 1, 2, 3), (-1, 0, 1), (-1, 0, 1))
#: The lags ``(sz, sy, sx)`` of :func:`correlate_direct`, in C order (63 of them).
LAGS = np.array(list(itertools.product(*AXIS_LAGS)))
#: The index of lag zero in :data:`LAGS`.
CENTRE = int(np.flatnonzero((LAGS == 0).all(axis=1))[0])
#: The lags per axis and the farthest lag of each axis (voxels): the coefficients
#: reshaped to ``(*CUBE, ...)`` hold lag zero at index ``REACH``.
CUBE = tuple(len(lags) for lags in AXIS_LAGS)
REACH = tuple(max(lags) for lags in AXIS_LAGS)


def parallel_sums(function, items) -> list:
    """``function`` over ``items`` on :func:`plenocl.opencl.threads.thread_count` threads, each
    with a single-threaded BLAS: every window sum is then computed by one thread in one
    order, so the results do not depend on the number of threads (a serial run and Dask
    workers with fewer threads each give the same fields, bit for bit), while the sums
    still share the cores."""
    with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(thread_count()) as pool:
        return list(pool.map(function, items))


def margin(size: int, weighting: float | None) -> int:
    """Voxels the weight reaches beyond each face of a window of ``size``: far enough
    that the Gaussian (standard deviation ``weighting * size / sqrt 2``) has fallen to
    about 1 % (three standard deviations), so that shifting it by half a voxel either
    way treats both directions alike; none for top-hat windows."""
    if weighting is None:
        return 0
    return max(0, int(np.ceil(3.0 * weighting * size / np.sqrt(2.0) - 0.5 * size)))


def axis_taps(size: int, weighting: float | None, centre_shift: float = 0.0) -> np.ndarray:
    """Weight along one axis of a window of ``size`` voxels and its :func:`margin` on both
    sides: the square of the FFT path's Gaussian (which weights both windows, so their
    product carries it twice), centred ``centre_shift`` voxels off the window's centre;
    ones over the window for top-hat windows."""
    if weighting is None:
        return np.ones(size)
    m = margin(size, weighting)
    q = np.arange(size + 2 * m) - m - 0.5 * (size - 1) - centre_shift
    return np.exp(-(q / (weighting * size)) ** 2)


def _corner_matrix(n: int, corners: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """``(n, len(corners))`` matrix: column ``k`` holds ``taps`` from row ``corners[k]``."""
    m = np.zeros((n, len(corners)), np.float32)
    for k, c in enumerate(corners):
        m[c:c + len(taps), k] = taps
    return m


def lag_weight_sums(grid: WindowGrid, weighting: float | None, power: int = 1) -> np.ndarray:
    """``sum_q W(q + s/2)`` (to ``power``) per lag of :data:`LAGS`: the sum of a window's
    weights, ``(63,)``."""
    per_axis = [np.array([(axis_taps(w, weighting, -0.5 * s) ** power).sum() for s in lags])
                for w, lags in zip(grid.size, AXIS_LAGS)]
    return np.array([per_axis[0][i] * per_axis[1][j] * per_axis[2][k]
                     for i, j, k in LAGS + REACH])


class WindowSums:
    """Weighted window sums at every window corner of a grid, for the lags of
    :data:`AXIS_LAGS`, of volumes padded with zeros (:meth:`pad`).

    The weight of lag ``s`` sits at the midpoint between the two windows compared,
    ``W(q + s/2)`` for the first window's voxel ``q``, so that neither volume is
    favoured: ``first`` sums ``sum_q W(q + s/2) f(L + q)`` and ``second`` sums
    ``sum_q W(q - s/2) f(L + s + q)``, the second window's voxels seen from its own
    corner ``L + s``. With the Gaussian reaching its :func:`margin` beyond the window, the
    two sums of a volume with itself at lags ``+s`` and ``-s`` are equal, so a pair of
    identical windows gives exactly zero displacement, as the FFT's circular correlation
    does.

    Parameters
    ----------
    shape
        The unpadded volume's shape.
    grid
        Window grid.
    weighting
        Gaussian width as a fraction of the window, or ``None`` (top hat).
    power
        Raise the weights to this power (2 for sums of squared contributions).
    """

    def __init__(self, shape: tuple[int, int, int], grid: WindowGrid,
                 weighting: float | None, power: int = 1) -> None:
        self.grid, self.shape = grid, tuple(shape)
        self.margins = tuple(margin(w, weighting) for w in grid.size)
        corners = [o + s * np.arange(c) for o, s, c in zip(grid.offset, grid.step, grid.count)]
        #: zeros on each face: the weight's margin and the farthest lag
        self.pads = tuple(m + r for m, r in zip(self.margins, REACH))
        padded = [n + 2 * p for n, p in zip(shape, self.pads)]
        # the weight W(q + s/2) per axis and lag, the same for both windows
        taps = [[axis_taps(w, weighting, -0.5 * s) ** power for s in lags]
                for w, lags in zip(grid.size, AXIS_LAGS)]
        self._first = [[_corner_matrix(n, c + r, t) for t in axis]
                       for n, c, r, axis in zip(padded, corners, REACH, taps)]
        self._second = [[_corner_matrix(n, c + r + s, t) for s, t in zip(lags, axis)]
                        for n, c, r, lags, axis in zip(padded, corners, REACH, AXIS_LAGS, taps)]
        #: ``sum_q W(q + s/2)`` per lag of :data:`LAGS`.
        self.weight_sums = lag_weight_sums(grid, weighting, power)

    def pad(self, vol: np.ndarray) -> np.ndarray:
        """``vol`` with ``margin + reach`` voxels of zeros on every face (float32)."""
        return np.pad(np.asarray(vol, np.float32), [(p, p) for p in self.pads])

    def inner(self, padded: np.ndarray) -> np.ndarray:
        """The view of a padded volume holding the unpadded voxels."""
        return padded[tuple(slice(p, p + n) for p, n in zip(self.pads, self.shape))]

    def shifted(self, padded: np.ndarray, shift) -> np.ndarray:
        """The view of a padded volume at the unpadded voxels shifted by ``shift``."""
        return padded[tuple(slice(p + s, p + s + n)
                            for p, n, s in zip(self.pads, self.shape, shift))]

    def first(self, padded: np.ndarray) -> np.ndarray:
        """``sum_q W(q + s/2) f(L + q)`` for every lag: ``(63, *count)``."""
        return self._lagged(padded, self._first)

    def second(self, padded: np.ndarray) -> np.ndarray:
        """``sum_q W(q - s/2) f(L + s + q)`` for every lag: ``(63, *count)``."""
        return self._lagged(padded, self._second)

    def product(self, vol: np.ndarray, shift) -> np.ndarray:
        """``sum_q W(q + s/2) f(L + q)`` for one lag ``shift`` of an unpadded volume (zero
        outside, as a product with a padded volume is)."""
        rows = [slice(p, p + n) for p, n in zip(self.pads, self.shape)]
        mz, my, mx = (axis[s + reach][r]
                      for axis, s, reach, r in zip(self._first, shift, REACH, rows))
        return self._apply(np.asarray(vol, np.float32), mz, my, mx)

    def _lagged(self, padded: np.ndarray, axes) -> np.ndarray:
        mz, my, mx = (np.concatenate(axis, axis=1) for axis in axes)
        out = self._apply(padded, mz, my, mx)  # (lz cz, ly cy, lx cx): lags by corners
        (cz, cy, cx), (lz, ly, lx) = self.grid.count, CUBE
        out = out.reshape(lz, cz, ly, cy, lx, cx).transpose(0, 2, 4, 1, 3, 5)
        return out.reshape(len(LAGS), cz, cy, cx)

    @staticmethod
    def _apply(vol: np.ndarray, mz, my, mx) -> np.ndarray:
        nz, ny, nx = vol.shape
        rows = vol.reshape(nz * ny, nx) @ mx                       # (nz ny, cx)
        planes = np.matmul(my.T, rows.reshape(nz, ny, -1))         # (nz, cy, cx)
        return np.tensordot(mz, planes, axes=([0], [0]))           # (cz, cy, cx)


@dataclass
class DirectCorrelation:
    """What :func:`correlate_direct` measured, per window (arrays shaped ``grid.count``
    after the first axis)."""

    r: np.ndarray          # (63, ...) weighted Pearson coefficients at LAGS
    cov: np.ndarray        # (63, ...) the weighted covariances, r = cov / norm
    var_a: np.ndarray      # (63, ...) the windows' weighted variances (sums, not means)
    var_b: np.ndarray
    mean_a: np.ndarray     # weighted means of the two windows at lag zero
    mean_b: np.ndarray
    signal: np.ndarray     # bool: both windows had variance

    @property
    def norm(self) -> np.ndarray:
        """``sqrt(var_a var_b)``, the normaliser of each coefficient."""
        return np.sqrt(np.maximum(self.var_a, 0.0) * np.maximum(self.var_b, 0.0))


class SumEngine(Protocol):
    """Where the window sums are computed: :class:`HostSums` (NumPy and BLAS, the
    reference) or :class:`plenocl.piv.devicesums.DeviceSums` (an OpenCL device)."""

    def correlation_sums(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                         weighting: float | None) -> tuple[np.ndarray, ...]: ...

    def spread_sums(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                    weighting: float | None) -> np.ndarray: ...

    def correlated_factors(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                           weighting: float | None) -> list[float]: ...

    def window_fit(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                   weighting: float | None, uncertainty: bool = False) -> WindowFit: ...


@dataclass
class WindowFit:
    """One pass's direct correlation fitted per window (:func:`window_fit`): what
    :func:`correlate_deformed` reads (arrays shaped ``grid.count`` after the first axis)."""

    displacement: np.ndarray  # (3, ...) (dz, dy, dx) voxels: the peak, fitted (fit_direct)
    peak: np.ndarray          # the coefficient there (at lag zero where not fitted)
    fitted: np.ndarray        # bool: the peak could be fitted among the lags
    signal: np.ndarray        # bool: both windows had variance
    off_centre: np.ndarray    # bool: the highest coefficient is not at lag zero
    sigma: np.ndarray | None  # (3, ...) voxels (correlation_uncertainty), or None


class HostSums:
    """The window sums of :func:`correlate_direct` and :func:`correlation_uncertainty` on
    the host: :class:`WindowSums`' matrix products, one sum per thread
    (:func:`parallel_sums`). The twin of ``kernels/windowsums.cl``."""

    def correlation_sums(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                         weighting: float | None) -> tuple[np.ndarray, ...]:
        """``(s_a, s_b, raw_a, raw_b, products)``, each ``(63, *grid.count)`` float32: the
        first window's sums of ``a`` and ``a^2``, the second's of ``b`` and ``b^2``, and
        the sums of ``a(q) b(q + s)``, at every lag ``s`` of :data:`LAGS`."""
        sums = WindowSums(np.shape(vol_a), grid, weighting)
        a, b = sums.pad(vol_a), sums.pad(vol_b)
        inner = sums.inner(a)
        jobs = [lambda: sums.first(a), lambda: sums.second(b), lambda: sums.first(a * a),
                lambda: sums.second(b * b)]
        jobs += [lambda lag=lag: sums.product(inner * sums.shifted(b, lag), lag)
                 for lag in LAGS]
        s_a, s_b, raw_a, raw_b, *products = parallel_sums(lambda job: job(), jobs)
        return s_a, s_b, raw_a, raw_b, np.stack(products)

    def window_fit(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                   weighting: float | None, uncertainty: bool = False) -> WindowFit:
        """:func:`window_fit` on the host: :func:`correlate_direct`, :func:`fit_direct`
        and, with ``uncertainty``, :func:`correlation_uncertainty` of these sums."""
        direct = correlate_direct(vol_a, vol_b, grid, weighting, self)
        sigma = (correlation_uncertainty(vol_a, vol_b, grid, weighting, direct, self)
                 if uncertainty else None)
        return fitted_windows(direct, sigma)

    def correlated_factors(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                           weighting: float | None) -> list[float]:
        """:func:`correlated_factors` (of host copies of device volumes)."""
        return correlated_factors(on_host(vol_a), on_host(vol_b), grid, weighting)

    def spread_sums(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                    weighting: float | None) -> np.ndarray:
        """``(3, 9, *grid.count)`` float32: per axis ``e``, the sums (weight of lag ``e``)
        of ``X``, ``Da``, ``Db`` and (squared weight) of ``X^2``, ``Da^2``, ``Db^2``,
        ``X Da``, ``X Db``, ``Da Db`` (:func:`_asymmetry`)."""
        shape = np.shape(vol_a)
        sums = WindowSums(shape, grid, weighting)
        squares = WindowSums(shape, grid, weighting, power=2)
        a, b = sums.pad(vol_a), sums.pad(vol_b)

        def axis_sums(axis: int) -> np.ndarray:
            unit = tuple(int(u) for u in np.eye(3, dtype=int)[axis])
            a0, a1 = sums.inner(a), sums.shifted(a, unit)
            b0, b1 = sums.inner(b), sums.shifted(b, unit)
            cross, diff_a, diff_b = a0 * b1 - a1 * b0, a0 - a1, b1 - b0
            quadratic = (cross * cross, diff_a * diff_a, diff_b * diff_b, cross * diff_a,
                         cross * diff_b, diff_a * diff_b)
            return np.stack([sums.product(f, unit) for f in (cross, diff_a, diff_b)]
                            + [squares.product(f, unit) for f in quadratic])

        return np.stack(parallel_sums(axis_sums, range(3)))


def correlate_direct(vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                     weighting: float | None, sums: SumEngine | None = None
                     ) -> DirectCorrelation:
    """Normalised correlation of every window of ``grid`` at the 63 :data:`LAGS`.

    Parameters
    ----------
    vol_a, vol_b
        Volumes of equal shape, ``vol_b(p) ~ vol_a(p - d)`` for a small ``d``.
    grid
        Window grid (:func:`plenocl.piv.correlation.window_grid`).
    weighting
        Gaussian width as a fraction of the window (as ``piv3d``), or ``None`` for a
        top hat over the window (not symmetric between ``+s`` and ``-s`` for a volume
        against itself: ``piv3d`` correlates top-hat windows by FFT).
    sums
        Where the window sums run (:class:`SumEngine`); ``None``: :class:`HostSums`.

    Returns
    -------
    DirectCorrelation
        ``r[k]``, the weighted Pearson coefficient at lag ``LAGS[k]``, and its parts.
    """
    engine = HostSums() if sums is None else sums
    return direct_correlation(engine.correlation_sums(vol_a, vol_b, grid, weighting),
                              lag_weight_sums(grid, weighting))


def direct_correlation(sums: tuple[np.ndarray, ...], lag_weights: np.ndarray
                       ) -> DirectCorrelation:
    """:func:`correlate_direct` from the window sums ``(s_a, s_b, raw_a, raw_b,
    products)`` (:meth:`HostSums.correlation_sums`) and the lags' weight sums
    (:func:`lag_weight_sums`); the twin of ``kernels/windowfit.cl``'s coefficients."""
    s_a, s_b, raw_a, raw_b, products = sums
    n = np.asarray(lag_weights, np.float64).reshape(len(LAGS), *[1] * (s_a.ndim - 1))
    var_a = raw_a - s_a * s_a / n
    var_b = raw_b - s_b * s_b / n
    cov = products - s_a * s_b / n
    signal = ((var_a[CENTRE] > 1e-9 * raw_a[CENTRE])
              & (var_b[CENTRE] > 1e-9 * np.maximum(raw_a[CENTRE], 1e-30)))
    r = pearson(cov, var_a, var_b).astype(np.float64)
    return DirectCorrelation(r, *(v.astype(np.float64) for v in (cov, var_a, var_b)),
                             s_a[CENTRE] / n[CENTRE], s_b[CENTRE] / n[CENTRE], signal)


def pearson(cov: np.ndarray, var_a: np.ndarray, var_b: np.ndarray) -> np.ndarray:
    """``cov / sqrt(var_a var_b)``, 0 where either variance is not positive: the
    coefficients of one pair's window sums, or of sums added over an ensemble."""
    scale = np.maximum(var_a, 0.0) * np.maximum(var_b, 0.0)
    return np.where(scale > 0, cov / np.sqrt(np.where(scale > 0, scale, 1.0)), 0.0)


def correlation_uncertainty(vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                            weighting: float | None, corr: DirectCorrelation,
                            sums: SumEngine | None = None) -> np.ndarray:
    """Standard uncertainty of each window's sub-voxel displacement from the statistics
    of its correlation (Wieneke 2015, Measurement Science and Technology 26, 074002), per axis.

    On volumes deformed to a residual below a voxel, the fitted offset along an axis ``e``
    comes from the asymmetry ``C(+e) - C(-e)`` of the correlation. With the weight at
    the midpoint of each voxel pair, that asymmetry is a sum over pairs ``(i, i + e)`` of

        dc_i = W(i + e/2) [a'(i) b'(i + e) - a'(i + e) b'(i)],

    ``a'``, ``b'`` the windows less their weighted means: zero for every pair where the
    two volumes match, so its spread measures their mismatch (noise, ghosts, unresolved
    motion). The asymmetry's standard deviation is estimated from that spread,
    ``s^2 = k (sum_i dc_i^2 - (sum_i dc_i)^2 / N)`` with ``k`` the factor by which
    neighbouring contributions are correlated (:func:`correlated_sum_factor`: they share
    particle images, so they are not independent), and carried through the three-point
    Gaussian fit of the normalised coefficients: ``sigma = |fit(r- - ds, r0, r+ + ds) -
    fit(r- + ds, r0, r+ - ds)| / 2`` with ``ds = s / 2`` over each lag's normaliser.

    The window sums and the factors ``k`` run on ``sums`` (:class:`SumEngine`; ``None``:
    :class:`HostSums`).

    Returns
    -------
    numpy.ndarray
        ``(3, *grid.count)`` as ``(dz, dy, dx)`` in voxels; NaN without signal.
    """
    engine = HostSums() if sums is None else sums
    return uncertainty_from_sums(engine.spread_sums(vol_a, vol_b, grid, weighting),
                                 engine.correlated_factors(vol_a, vol_b, grid, weighting),
                                 weighed_voxels(grid, weighting), corr)


def weighed_voxels(grid: WindowGrid, weighting: float | None) -> float:
    """The voxels a window's weight covers (the window and its margins): the count of
    :func:`correlation_uncertainty`'s spread."""
    return float(np.prod([w + 2 * margin(w, weighting) for w in grid.size]))


def uncertainty_from_sums(raw: np.ndarray, factors, count: float, corr: DirectCorrelation
                          ) -> np.ndarray:
    """:func:`correlation_uncertainty` from the spread sums ``raw``
    (:meth:`HostSums.spread_sums`), the correlated-sum ``factors``, the windows'
    :func:`weighed_voxels` ``count`` and the correlation; the twin of
    ``kernels/windowfit.cl``'s uncertainty."""
    cube = corr.r.reshape(*CUBE, *corr.r.shape[1:])
    norm = corr.norm.reshape(cube.shape)
    sigma = np.full((3, *corr.r.shape[1:]), np.nan)
    for axis, factor in enumerate(factors):
        total, spread = _asymmetry(raw[axis], corr)
        half = 0.5 * np.sqrt(factor * np.maximum(spread - total ** 2 / count, 0.0))
        lo, hi = list(REACH), list(REACH)
        lo[axis], hi[axis] = REACH[axis] - 1, REACH[axis] + 1
        lo, hi = tuple(lo), tuple(hi)
        d_lo, d_hi = half / np.maximum(norm[lo], 1e-30), half / np.maximum(norm[hi], 1e-30)
        up = gaussian_subpixel(cube[lo] - d_lo, cube[REACH], cube[hi] + d_hi)
        down = gaussian_subpixel(cube[lo] + d_lo, cube[REACH], cube[hi] - d_hi)
        sigma[axis] = np.where(corr.signal, 0.5 * np.abs(up - down), np.nan)
    return sigma


def on_host(vol) -> np.ndarray:
    """A volume on the host: a device array's copy (``.get()``), a host array as it is."""
    return vol if isinstance(vol, np.ndarray) else vol.get()


def correlated_factors(vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                       weighting: float | None) -> list[float]:
    """:func:`correlated_sum_factor` of the contributions along each axis, ``(z, y, x)``,
    with the volumes less their local (window-sized box) means."""
    sums = WindowSums(np.shape(vol_a), grid, weighting)
    a, b = sums.pad(vol_a), sums.pad(vol_b)
    box = tuple(int(w) for w in grid.size)
    local = parallel_sums(lambda v: ndimage.uniform_filter(v, box, mode="constant"), (a, b))
    da, db = (v - m for v, m in zip((a, b), local))   # less each voxel's local mean

    def factor_of(axis: int) -> float:
        unit = tuple(int(u) for u in np.eye(3, dtype=int)[axis])
        field = (sums.inner(da) * sums.shifted(db, unit)
                 - sums.shifted(da, unit) * sums.inner(db))
        return correlated_sum_factor(field)

    return parallel_sums(factor_of, range(3))


#: The longest lag (voxels) over which neighbouring contributions are taken as correlated.
MAX_CORRELATION_LAG = 8


def correlated_sum_factor(field: np.ndarray) -> float:
    """How much larger the variance of a sum of the contributions ``dc_i`` is than the sum
    of their variances, because neighbouring voxels share a particle image: the sum of
    the contributions' autocorrelation coefficients over the lags where it stays
    positive, ``prod_axes (1 + 2 sum_l rho(l))``, one value for the whole volume.

    ``field`` holds every voxel's contribution, ``a'(i) b'(i+e) - a'(i+e) b'(i)`` with
    ``a'``, ``b'`` the volumes less their local (window-sized box) means.
    """
    def lagged(axis: int):
        for lag in range(1, correlation_lags(field.shape, axis) + 1):
            head = [slice(None)] * 3
            tail = [slice(None)] * 3
            head[axis], tail[axis] = slice(lag, None), slice(None, -lag)
            yield float(np.vdot(field[tuple(head)], field[tuple(tail)]))

    return sum_factor(float(np.vdot(field, field)), (lagged(axis) for axis in range(3)))


def correlation_lags(shape: tuple[int, ...], axis: int) -> int:
    """The lags along ``axis`` over which :func:`correlated_sum_factor` looks."""
    return min(MAX_CORRELATION_LAG, shape[axis] - 1)


def sum_factor(energy: float, lagged) -> float:
    """:func:`correlated_sum_factor` from the field's energy ``sum f^2`` and, per axis,
    its products ``sum f(i) f(i + l e)`` at lags ``l = 1, 2, ...`` (an iterable each,
    read only up to the first coefficient that is not positive)."""
    if energy <= 0:
        return 1.0
    factor = 1.0
    for products in lagged:
        total = 1.0
        for product in products:
            rho = product / energy
            if rho <= 0:
                break
            total += 2.0 * rho
        factor *= total
    return factor


def _asymmetry(raw: np.ndarray, corr: DirectCorrelation):
    """``sum_i dc_i`` and ``sum_i dc_i^2`` per window, for ``dc_i = W (X - mb Da - ma Db)``
    with ``X = a(i) b(i+e) - a(i+e) b(i)``, ``Da = a(i) - a(i+e)``, ``Db = b(i+e) - b(i)``
    and the windows' weighted means ``ma``, ``mb``, from one axis's nine sums ``raw``
    (:meth:`HostSums.spread_sums`)."""
    ma, mb = corr.mean_a, corr.mean_b
    total = raw[0] - mb * raw[1] - ma * raw[2]
    factors = (1.0, mb * mb, ma * ma, -2 * mb, -2 * ma, 2 * ma * mb)
    spread = sum(factor * part for factor, part in zip(factors, raw[3:]))
    return total, spread


def fit_direct(r: np.ndarray):
    """Peak of the 63 coefficients per window and its sub-voxel position.

    The highest coefficient is fitted per axis where its neighbours are among the lags:
    at zero laterally and within two voxels of zero in depth.

    Returns
    -------
    displacement : numpy.ndarray
        ``(3, *count)`` ``(dz, dy, dx)`` in voxels: the peak's lag plus its offset within
        ``[-0.5, 0.5]`` per axis, where ``fitted``.
    peak : numpy.ndarray
        The coefficient at the peak's lag (at lag zero where not ``fitted``).
    fitted : numpy.ndarray
        Bool: the peak could be fitted (else the window needs the FFT).
    """
    shape = r.shape[1:]
    lag = LAGS[np.argmax(r, axis=0)].reshape(-1, 3)
    fitted = (lag[:, 1] == 0) & (lag[:, 2] == 0) & (np.abs(lag[:, 0]) < REACH[0])
    cube = r.reshape(*CUBE, -1)
    k = np.where(fitted, lag[:, 0], 0) + REACH[0]      # the peak's (or zero's) depth index
    w, (cy, cx) = np.arange(k.size), REACH[1:]
    peak = cube[k, cy, cx, w]
    disp = np.stack([k - REACH[0] + gaussian_subpixel(cube[k - 1, cy, cx, w], peak,
                                                      cube[k + 1, cy, cx, w]),
                     gaussian_subpixel(cube[k, cy - 1, cx, w], peak, cube[k, cy + 1, cx, w]),
                     gaussian_subpixel(cube[k, cy, cx - 1, w], peak, cube[k, cy, cx + 1, w])])
    return disp.reshape(3, *shape), peak.reshape(shape), fitted.reshape(shape)


def fitted_windows(direct: DirectCorrelation, sigma: np.ndarray | None = None) -> WindowFit:
    """A :class:`WindowFit` of a direct correlation (:func:`fit_direct`, :func:`off_centre`)
    and its uncertainty ``sigma``."""
    disp, peak, fitted = fit_direct(direct.r)
    return WindowFit(disp, peak, fitted, direct.signal, off_centre(direct.r), sigma)


def window_fit(vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
               weighting: float | None, uncertainty: bool = False,
               sums: SumEngine | None = None) -> WindowFit:
    """Every window of ``grid`` correlated at the 63 :data:`LAGS`
    (:func:`correlate_direct`), its peak fitted (:func:`fit_direct`) and, with
    ``uncertainty``, its uncertainty (:func:`correlation_uncertainty`), where ``sums``
    runs (``None``: :class:`HostSums`; a :class:`plenocl.piv.devicesums.DeviceSums`
    fits them on its device, so that only the fit comes back)."""
    engine = HostSums() if sums is None else sums
    return engine.window_fit(vol_a, vol_b, grid, weighting, uncertainty)


def off_centre(r: np.ndarray) -> np.ndarray:
    """Windows whose highest coefficient is not at lag zero: the correlation's statistics
    (:func:`correlation_uncertainty`) hold at the centre lag only."""
    return np.argmax(r, axis=0) != CENTRE


#: A window whose correlation at lag zero is below this fraction of the pass's median is
#: re-correlated by FFT: its match is doubtful (a region without matching particles, a
#: wall, a block of noise), and the FFT's full plane lets the peak ratio and the outlier
#: test judge it as in an FFT pass. Uncorrelated particle volumes give coefficients
#: below 0.1; reconstructed pairs at the paper's optics a median of 0.6, 1 % below 0.37.
WEAK_PEAK = 0.5


def weak_peaks(peak: np.ndarray, signal: np.ndarray) -> np.ndarray:
    """Windows whose peak coefficient is below :data:`WEAK_PEAK` of the median."""
    if not signal.any():
        return np.zeros_like(signal)
    return signal & (peak < WEAK_PEAK * float(np.median(peak[signal])))


def correlate_deformed(vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                       weighting: float | None, uncertainty: bool = False,
                       sums: SumEngine | None = None, fft=None, **fft_options) -> Correlation:
    """Correlate deformed volumes directly at the 63 lags, and by FFT
    (:func:`plenocl.piv.correlation.correlate`, with ``fft_options``, or ``fft``'s
    ``correlate``: a :class:`plenocl.piv.devicefft.FFTRoute`) only the windows whose peak
    :func:`fit_direct` cannot fit or is weak (:func:`weak_peaks`). The volumes are host
    arrays, or device arrays where ``sums`` and ``fft`` take them.

    Parameters
    ----------
    uncertainty
        Also estimate each window's uncertainty (:func:`correlation_uncertainty`).
    sums
        Where the window sums run (:class:`SumEngine`; ``None``: :class:`HostSums`).

    Returns
    -------
    Correlation
        As the FFT path's, but for the peak ratio, NaN where the direct correlation
        decided (it sees no secondary peak); ``sigma`` with ``uncertainty``.
    """
    fit = window_fit(vol_a, vol_b, grid, weighting, uncertainty, sums)
    sigma, signal = fit.sigma, fit.signal
    disp, peak, fitted = fit.displacement, fit.peak, fit.fitted
    ratio = np.full(grid.count, np.nan)
    far = signal & (~fitted | weak_peaks(peak, signal))
    if far.any():
        weight = None if weighting is None else gaussian_weight(grid.size, weighting)
        wide = (correlate(vol_a, vol_b, grid, weight=weight, select=far, **fft_options)
                if fft is None else fft.correlate(vol_a, vol_b, grid, weight=weight,
                                                  select=far))
        disp[:, far], peak[far], ratio[far] = (wide.displacement[:, far], wide.peak[far],
                                               wide.peak_ratio[far])
        signal = signal & (fitted | wide.signal)
    disp[:, ~signal] = 0.0
    if sigma is not None:  # the statistics hold at the centre lag only
        sigma[:, far | ~signal | fit.off_centre] = np.nan
    return Correlation(disp, np.where(signal, peak, 0.0), ratio, signal, sigma)


def deformed_uncertainty(vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                         weighting: float | None, sums: SumEngine | None = None
                         ) -> np.ndarray:
    """:func:`correlation_uncertainty` on its own (for a pass correlated by FFT):
    ``(3, *grid.count)`` voxels, NaN where the peak is off lag zero; the window sums
    on ``sums`` (as :func:`correlate_deformed`)."""
    fit = window_fit(vol_a, vol_b, grid, weighting, True, sums)
    fit.sigma[:, fit.off_centre] = np.nan
    return fit.sigma
