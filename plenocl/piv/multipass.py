"""Multi-pass 3-D PIV with window deformation (WIDIM).

:func:`piv3d` correlates two particle volumes ``vol[iz, iy, ix]`` (docs/design.md §7, §9):
a large zero-padded first pass, then passes with smaller, overlapping windows on volumes
deformed symmetrically by the current predictor, normalised-median outlier detection and
replacement after every pass. The result holds window centres in voxel-index units
(index ``i`` is the centre of voxel ``i``) and displacements in voxels: a
:class:`plenocl.vectorfield.PIVResult`, whose methods turn them into velocity (m/s),
vorticity (1/s), the Q-criterion (1/s^2) and the arrays written to files.

Building blocks live in :mod:`plenocl.piv.correlation` (windows, FFT correlation, peak fit),
:mod:`plenocl.piv.interpolate` (predictor resampling, volume deformation) and
:mod:`plenocl.piv.validation` (outlier detection and replacement).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..opencl.arrays import device_copies
from ..opencl.volume import DeviceVolume, host_volume, resident
from ..options import with_keywords
from ..peaks import host_maxima
from ..vectorfield import PIVResult, Size3
from .correlation import gaussian_weight, window_fraction, window_grid
from .deformation import make_deformer
from .devicefft import FFTRoute
from .devicepeaks import DeviceMaxima
from .devicesums import sums_for
from .direct import correlate_deformed, deformed_uncertainty
from .interpolate import resample
from .settings import PIVSettings, window_schedule
from .validation import normalized_median_test, replace_outliers

__all__ = ["PIVResult", "check_volume", "piv3d"]


def check_volume(name: str, vol):
    """``vol`` as a float32 volume, refused by ``name`` (``"vol_a"``, or the file it came
    from) where it cannot be correlated, with a warning where a constant background would
    pull the vectors to zero; a :class:`DeviceVolume` stays on the device (its summary
    checked). :func:`piv3d` checks its volumes so."""
    if isinstance(vol, DeviceVolume):
        summary = vol.summary()
        bad, low, high = summary.nonfinite, summary.low, summary.high
        arr = vol
    else:
        arr = np.asarray(vol)
        if arr.ndim != 3:
            raise ValueError(f"{name} must be a 3-D volume vol[iz, iy, ix], got {arr.ndim}-D "
                             f"shape {arr.shape}")
        if not (np.issubdtype(arr.dtype, np.integer)
                or np.issubdtype(arr.dtype, np.floating)):
            raise TypeError(f"{name} must hold real numbers, got dtype {arr.dtype}")
        arr = arr.astype(np.float32, copy=False)
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        low, high = float(arr.min()), float(arr.max())  # read only where bad is 0
    if bad:
        raise ValueError(f"{name} contains {bad} NaN/Inf values; replace them (e.g. "
                         f"np.nan_to_num) or mask those voxels before correlating")
    _check_levels(name, low, high)
    return arr


def _check_levels(name: str, low: float, high: float) -> None:
    """A volume's darkest and brightest voxel checked: not constant, not negative."""
    if high == low:
        raise ValueError(f"{name} is constant ({low}): it holds no particles to "
                         f"correlate; check the reconstruction or the file loaded")
    if -low > max(high, 0.0):
        raise ValueError(f"{name} holds negative intensities down to {low:.4g} against a "
                         f"peak of {high:.4g}: a particle volume is non-negative; check its "
                         "sign and the tool that made it (noise or ringing below zero, "
                         "smaller than the peak, is accepted)")
    if low > 0 and low > high - low:
        warnings.warn(f"{name}'s darkest voxel ({low:.4g}) lies above its particles' height "
                      f"over it ({high - low:.4g}): a constant background correlates as a "
                      "plane and pulls the vectors towards zero; subtract it "
                      f"(vol - vol.min(), or its median)", stacklevel=4)


def window_passes(shape: Size3, windows, overlaps, final_iterations: int
                  ) -> list[tuple[Size3, float]]:
    """The ``(size, overlap)`` of every pass of ``windows`` on a volume of ``shape``
    (:func:`~plenocl.piv.settings.window_schedule`'s, each window checked to fit the
    volume; a batch checks its grid with it before any pair).

    Raises
    ------
    ValueError
        A window larger than the volume along an axis (naming it, with windows that
        fit), or what :func:`~plenocl.piv.settings.window_schedule` refuses.
    """
    passes = window_schedule(windows, overlaps, final_iterations)
    for k, (size, _) in enumerate(passes[:len(passes) - int(final_iterations) + 1], start=1):
        for axis, s, n in zip("zyx", size, shape):
            if s > n:
                first = min(shape) // 8 * 8
                hint = (f"pass smaller windows, e.g. windows=({first}, "
                        f"{max(8, first * 2 // 3 // 8 * 8)})" if first >= 8 else
                        "the volume is smaller than the smallest window (8 voxels): use a "
                        "larger volume")
                raise ValueError(f"window {s} of pass {k} is larger than the volume along "
                                 f"{axis} ({n} voxels); {hint}")
        if k > 1 and any(a > b for a, b in zip(size, passes[k - 2][0])):
            warnings.warn(f"the window of pass {k} {size} is larger than pass {k - 1}'s "
                          f"{passes[k - 2][0]}: multi-pass PIV refines, so windows should "
                          "shrink (or stay) from pass to pass", stacklevel=3)
    return passes


@dataclass
class _Pass:
    """State carried from one pass to the next."""

    field: np.ndarray          # (3, nz, ny, nx) as (dz, dy, dx)
    centres: tuple             # (z, y, x) 1-D
    invalid: np.ndarray
    outlier: np.ndarray
    masked: np.ndarray
    peak_ratio: np.ndarray
    sigma: np.ndarray | None = None  # (3, nz, ny, nx) as (dz, dy, dx), final pass only


#: The window schedule :func:`piv3d` starts from when none is given; each window is cut
#: per axis to the largest multiple of 8 voxels the volume holds (:func:`auto_windows`).
DEFAULT_WINDOWS = (48, 32, 24)


#: The fewest particles a final window should hold on average: below about 10 the
#: correlation peak is noise (measured on reconstructed volumes at the paper's optics,
#: ``benchmarks/accuracy.py``: 4.5 particles per 24-voxel window gave 3.5 voxels of depth
#: error, 11 per 32-voxel window 2.9, 36 per 48-voxel window 2.1).
MIN_PARTICLES_PER_WINDOW = 10


def auto_windows(shape, max_displacement: float | None = None,
                 particles: int | None = None) -> tuple[tuple[int, ...], ...]:
    """The default window schedule for a volume of ``shape``: :data:`DEFAULT_WINDOWS`,
    each cut per axis to the largest multiple of 8 voxels that fits (``(wz, wy, wx)``
    windows for flat volumes).

    Parameters
    ----------
    shape
        The volume's ``(nz, ny, nx)``.
    max_displacement
        The largest expected displacement (voxels): the first window is at least 4 times
        it where the volume allows, since a zero-padded first pass finds displacements up
        to about a quarter of its window.
    particles
        How many particles the volume holds: the final window grows (in steps of 8
        voxels) until it holds :data:`MIN_PARTICLES_PER_WINDOW` on average, and the
        passes before it are larger by half.

    Raises
    ------
    ValueError
        When an axis holds fewer than 8 voxels (no window fits).
    """
    shape = tuple(int(n) for n in shape)
    if min(shape) < 8:
        raise ValueError(f"a volume of shape {shape} holds no 8-voxel window along every axis: "
                         "reconstruct on a grid of at least 8 voxels per axis")
    fit = [n // 8 * 8 for n in shape]
    schedule = list(DEFAULT_WINDOWS)
    if particles:
        need = MIN_PARTICLES_PER_WINDOW * float(np.prod(shape)) / particles
        final = max(DEFAULT_WINDOWS[-1], int(np.ceil(need ** (1 / 3) / 8)) * 8)
        if final > DEFAULT_WINDOWS[-1]:
            schedule = [max(DEFAULT_WINDOWS[0], (final * 3 // 2 + 7) // 8 * 8), final]
    if max_displacement is not None:
        schedule[0] = max(schedule[0], int(np.ceil(4 * float(max_displacement) / 8)) * 8)
    return tuple(tuple(min(w, f) for f in fit) for w in schedule)


def count_particles(vol: np.ndarray, threshold: float = 0.1,
                    maxima: Callable | None = None, on_device=None) -> int:
    """Local maxima above ``threshold`` of the volume's maximum: about the particles (and
    ghosts) a reconstructed volume holds; found by ``maxima``
    (:func:`plenocl.peaks.host_maxima`, the default, or a device's
    :class:`plenocl.piv.devicepeaks.DeviceMaxima`, which reads ``on_device``, the
    volume's device copy, where both are given)."""
    if isinstance(vol, DeviceVolume):  # a device's maxima read it where it is
        v, top = vol, vol.maximum()
    else:
        v = np.asarray(vol, np.float32)
        top = float(v.max()) if v.size else 0.0
    if top <= 0:
        return 0
    if maxima is None:
        return len(host_maxima(host_volume(v), threshold * top))
    return len(maxima(v if on_device is None else on_device, threshold * top))


def piv3d(vol_a, vol_b, settings: PIVSettings | None = None, *, mask=None, queue=None,
          on_device: tuple | None = None, **keywords) -> PIVResult:
    """Multi-pass 3-D PIV of two particle volumes with symmetric window deformation.

    Parameters
    ----------
    vol_a, vol_b
        Volumes ``vol[iz, iy, ix]`` at ``t`` and ``t + dt`` (same shape, finite, real).
    settings
        Every option below but ``mask`` and ``queue`` as one :class:`PIVSettings`
        (``None``: the defaults). The options may instead be given as keywords, which
        build one; keywords that differ from a given ``settings`` are an error.
    windows
        Window size per pass: ints (cubes) or ``(wz, wy, wx)``; each >= 8 voxels and no
        larger than the volume. By default :func:`auto_windows` of the volume's shape and
        of the particles ``vol_a`` holds (48, 32, 24, cut to what the volume holds per
        axis, larger where fewer than 10 particles would fall in a 24-voxel window); the
        windows used are in ``result.passes``.
    overlaps
        Overlap fraction per pass (or one for all), in ``[0, 1)``; by default 0.5 for
        every pass but the last and 0.75 for the last.
    final_iterations
        How many times the last pass runs (each re-deforms with the updated predictor).
    pad_first
        Zero-pad the first pass by at least a third of the window (linear correlation,
        :func:`plenocl.piv.correlation.padded_size`), so that it finds displacements up
        to about a quarter of the window without aliasing.
    weighting
        Gaussian weight on both windows of the later (deformed) passes, its standard
        deviation as a fraction of the window size; ``None`` for top-hat windows. The
        Gaussian's transfer function has no negative lobes, so iterative deformation
        converges on structures about the window size (a Lamb-Oseen core is resolved
        2-3x better than with top-hat windows, measured), at a slightly higher random
        error in noisy volumes.
    deform_order
        Interpolation of the volume deformation: 3 cubic B-spline (default), 1 trilinear
        (about 6x the bias), 5 quintic B-spline (about 2x the deformation time).
    predictor
        ``"cubic"`` (natural cubic spline) or ``"linear"`` interpolation of the predictor
        between vectors; both extrapolate linearly beyond the outermost vectors.
    mask
        Optional boolean volume, ``True`` for voxels to exclude (walls, outside the flow).
        Excluded voxels take the mean of the others (:func:`masked_volume`); windows more
        than a quarter excluded (:data:`MASKED_FRACTION`) give NaN vectors (``masked``;
        the earlier passes keep windows up to half excluded). A mask that leaves no
        first-pass window is refused.
    median_eps, median_threshold
        Normalised median test parameters (voxels; dimensionless).
    min_peak_ratio
        If given, vectors whose peak ratio is below it are also invalid and replaced.
    workers
        Threads for the FFTs (``-1``: all cores).
    queue
        The OpenCL device to deform the volumes on (``kernels/deform.cl``; a queue,
        context, device or name): by default the default device, as every stage
        (``PYOPENCL_CTX``, else the preferred one; the host for ``deform_order=5``, which
        has no kernel). ``False`` deforms on the host with SciPy, the reference. Both give
        the same volumes to float32 rounding; the device is several times faster even on
        a CPU (all cores instead of one).
    fft
        Where the FFT correlations run (the first pass, and the windows a direct pass
        sends to the FFT): ``"fftw"`` or ``"scipy"`` (the host's; SciPy the reference),
        ``"device"`` (``kernels/fftcorr.cl`` on ``queue``'s device: the windows gathered,
        transformed and their peaks fitted there, only six numbers per window back), or
        ``None`` (default): for each device and FFT box, whichever of the device and the
        host's FFTW (SciPy without pyfftw) correlated its first call faster
        (:class:`plenocl.piv.devicefft.FFTRoute`; on 2 CPU cores the host, on a GPU the
        device). The routes taken are in ``result.passes`` (``fft_route``). Without a
        device (``queue=False``, the quintic B-spline) the host's.
    on_device
        The two volumes' float32 device copies ``(dev_a, dev_b)`` on ``queue``'s context,
        holding the same values (a reconstruction's ``info.volume_on_device``:
        :func:`plenocl.process_pair` passes them): read where the volumes go to the
        device (the particle count, the deformation, the device's FFT of the first
        pass) instead of uploading them again. Not used with a ``mask`` (the masked
        volumes differ) or on the host.
    correlation
        ``"auto"`` (default): the deformed passes correlate each window directly at the
        63 lags around zero, one voxel across and three in depth (:mod:`plenocl.piv.direct`:
        linear, not circular, with the Gaussian weight centred between the two windows;
        about 3x faster than the FFT and more accurate for sub-voxel residuals), and by
        FFT only the windows whose peak cannot be fitted there (off laterally or three
        voxels off in depth). The first pass, top-hat windows (``weighting=None``)
        and, when ``min_peak_ratio`` is given, the final iteration (which then needs the
        secondary peak) use the FFT. ``"fft"``: every pass by FFT.

    Returns
    -------
    PIVResult
        Window centres (voxel-index units) and displacements (voxels) of the final pass.
    """
    a, b = check_volume("vol_a", vol_a), check_volume("vol_b", vol_b)
    if a.shape != b.shape:
        raise ValueError(f"vol_a and vol_b must have the same shape, got {a.shape} and "
                         f"{b.shape}")
    opts = with_keywords(PIVSettings, settings, keywords, "piv3d")
    windows, weighting = opts.windows, opts.weighting
    deformer = make_deformer(opts.deform_order, queue)
    sums = sums_for(deformer)
    fft = FFTRoute(opts.fft, None if sums is None else sums.kernels.queue, opts.workers)
    copies = None if sums is None else device_copies(
        on_device or resident(a, b, sums.kernels.queue.context), a.shape,
        sums.kernels.queue.context)
    if copies is None:  # the volumes are read on the host
        a, b = host_volume(a), host_volume(b)
    if windows is None:
        maxima = None if sums is None else DeviceMaxima(sums.kernels.queue)
        windows = auto_windows(a.shape, particles=count_particles(
            a, maxima=maxima, on_device=None if copies is None else copies[0]))
    schedule = window_passes(a.shape, windows, opts.overlaps, opts.final_iterations)
    mask = _check_mask(mask, a.shape, schedule[0])
    if mask is not None:
        a, b = (masked_volume(host_volume(v), mask) for v in (a, b))
        copies = None
    coeffs = tuple(deformer.prepare(v) for v in copies or (a, b))
    state, log = None, []
    for k, (size, overlap) in enumerate(schedule):
        t0 = time.perf_counter()
        pad = opts.pad_first and k == 0
        weight = None if pad or weighting is None else gaussian_weight(size, weighting)
        final = k == len(schedule) - 1
        direct = (opts.correlation == "auto" and k > 0 and weighting is not None
                  and not (final and opts.min_peak_ratio is not None))
        fft.used.clear()
        state = _run_pass(a, b, (deformer, *coeffs), state, size, overlap, mask, pad, weight,
                          opts, direct, final, (sums, fft, copies))
        # a direct pass gives a peak ratio only to the windows it sent to the FFT
        by_fft = int((~np.isnan(state.peak_ratio)).sum()) if direct else state.invalid.size
        log.append({"window": size, "overlap": overlap, "vectors": state.invalid.size,
                    "correlation": "direct" if direct else "fft", "fft_windows": by_fft,
                    "fft_route": "+".join(sorted(fft.used)) or None,
                    "outliers": int(state.outlier.sum()), "invalid": int(state.invalid.sum()),
                    "seconds": time.perf_counter() - t0})
        if k == 0:
            _warn_if_far(state, size)
    result = _result(state, schedule[-1][0], log)
    _warn_if_thin(result, a.shape)
    _warn_if_none_valid(result)
    return result


#: A final window more than this fraction masked is left out (its vector NaN,
#: ``masked``): above it the mask's edge, fixed in both volumes, pulls the displacement
#: across it towards zero (docs/design.md §7, "Masks"). The earlier passes, which only
#: predict, keep windows up to :data:`PREDICTOR_MASKED` masked.
MASKED_FRACTION = 0.25
PREDICTOR_MASKED = 0.5
#: The first pass's displacements are reliable up to this fraction of its windows (the
#: one-quarter rule of Keane & Adrian 1990): beyond it :func:`piv3d` warns.
FAR_FRACTION = 0.25


def masked_volume(vol: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``vol`` with the voxels ``mask`` marks set to the mean of the others: a level that
    window means nearly remove, where zeros (a band identical in both volumes) would
    correlate at zero displacement and pull the vectors beside the mask towards zero
    (the component across the edge 2-7 % low in windows 10-20 % masked, against 1-4 %;
    docs/design.md §7, "Masks")."""
    kept = vol[~mask]
    level = np.float32(kept.mean()) if kept.size else np.float32(0)
    return np.where(mask, level, vol).astype(np.float32, copy=False)


def _warn_if_far(state: _Pass, size: Size3) -> None:
    """The first pass's valid displacements beyond a quarter of its windows along an axis
    (their median): a displacement the windows cannot hold, or volumes that do not
    belong together, correlate into vectors that look valid and are not."""
    valid = ~(state.invalid | state.outlier | state.masked)
    if not valid.any():
        return
    medians = [float(np.median(np.abs(comp[valid]))) for comp in state.field]
    far = [(axis, d, w) for axis, d, w in zip("zyx", medians, size) if d > FAR_FRACTION * w]
    if far:
        said = ", ".join(f"{d:.1f} voxels along {axis} in windows of {w}"
                         for axis, d, w in far)
        warnings.warn(
            f"the first pass's displacements reach {said}: beyond a quarter of the window, "
            "where correlation finds them unreliably (or the volumes do not belong "
            "together), and the vectors may look valid and be wrong. Give larger first "
            "windows (windows=(64, ...), --windows), or a shorter time between the "
            "exposures", stacklevel=3)


def _warn_if_none_valid(result: PIVResult) -> None:
    """No vector of the final pass valid: its field holds no measurement."""
    if not result.valid.any():
        warnings.warn(
            "no vector passed validation (the peak ratio, the outlier test or the mask): "
            "the field's vectors are fill values (zeros), not measurements; check the "
            "volumes and the settings (min_peak_ratio, windows, mask)", stacklevel=3)


def _warn_if_thin(result: PIVResult, shape: tuple[int, ...]) -> None:
    """Fewer than 3 vectors along an axis: no gradient, no vorticity, and the outlier
    test has no neighbours there; say so with the fix."""
    counts = result.u.shape
    thin = [axis for axis, n in zip("zyx", counts) if n < 3]
    if thin:
        warnings.warn(
            f"the final windows {tuple(result.window)} give {counts[0]} x {counts[1]} x "
            f"{counts[2]} vectors (z, y, x) in a {shape[0]} x {shape[1]} x {shape[2]} voxel "
            f"volume: fewer than 3 along {', '.join(thin)}, so no gradient or vorticity "
            "there. Reconstruct a larger volume along that axis (a wider z range, or "
            "thinner voxels: Grid.for_camera(..., depth_voxel_mm=...), plenocl grid "
            "--depth-voxel-mm) or give smaller windows (windows=, --windows)", stacklevel=3)


def _check_mask(mask, shape: Size3, first: tuple[Size3, float]) -> np.ndarray | None:
    """``mask`` checked: the volumes' shape, boolean, and leaving some window of the
    ``first`` pass ``(size, overlap)`` to correlate."""
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(f"mask must have the volumes' shape {shape}, got {m.shape}")
    if m.dtype != bool:
        raise TypeError(f"mask must be boolean (True = exclude the voxel), got dtype {m.dtype}")
    if (window_fraction(m, window_grid(shape, *first)) > PREDICTOR_MASKED).all():
        raise ValueError(f"the mask covers {m.mean():.0%} of the volume and more than "
                         f"{PREDICTOR_MASKED:.0%} of every first-pass window {first[0]}: "
                         "nothing is left to correlate; True marks voxels to exclude "
                         "(pass ~mask if yours marks the voxels to keep)")
    return m


def _run_pass(a, b, prepared, prev: _Pass | None, size: Size3, overlap: float, mask, pad: bool,
              weight, opts: PIVSettings, direct: bool, final: bool, engines: tuple) -> _Pass:
    """One correlation pass: deform by the predictor, correlate, validate, replace;
    ``engines``: the direct correlation's window sums (``None``: the host), the
    :class:`~plenocl.piv.devicefft.FFTRoute` and the volumes' device copies (``None``:
    none; the first pass's device FFT reads them). Deformed volumes stay on the device
    where the window sums run there."""
    grid = window_grid(a.shape, size, overlap)
    centres = grid.centres
    copies = None
    if prev is None:
        da, db, base, copies = a, b, 0.0, engines[2]
    else:
        deformer, coeff_a, coeff_b = prepared
        dense = deformer.predictor(prev.field, prev.centres, a.shape, opts.predictor)
        keep = engines[0] is not None
        da = deformer(coeff_a, dense, -0.5, keep)
        db = deformer(coeff_b, dense, +0.5, keep)
        base = resample(prev.field, prev.centres, centres, opts.predictor)
    corr = _correlate_pass(da, db, grid, pad, weight, opts, direct,
                           final and prev is not None, engines[:2], copies)
    limit = MASKED_FRACTION if final else PREDICTOR_MASKED
    masked = (np.zeros(grid.count, bool) if mask is None
              else window_fraction(mask, grid) > limit)
    invalid = ~corr.signal | masked
    if opts.min_peak_ratio is not None:
        invalid |= corr.peak_ratio < opts.min_peak_ratio
    total = base + corr.displacement
    outlier = normalized_median_test(total, opts.median_eps, opts.median_threshold,
                                     ignore=invalid)
    total = replace_outliers(total, outlier | invalid)
    return _Pass(total, centres, invalid, outlier, masked, corr.peak_ratio, corr.sigma)


def _correlate_pass(da, db, grid, pad: bool, weight, opts: PIVSettings, direct: bool,
                    uncertainty: bool, engines: tuple, on_device: tuple | None = None):
    """Correlate one pass directly or by FFT; with ``uncertainty`` (the final pass on
    deformed volumes) also estimate each vector's uncertainty; ``on_device``: device
    copies of host volumes ``da``, ``db`` for the device's FFT."""
    sums, fft = engines
    if direct:
        return correlate_deformed(da, db, grid, opts.weighting, uncertainty, sums, fft)
    corr = fft.correlate(da, db, grid, pad=pad, weight=weight, on_device=on_device)
    if uncertainty:
        corr.sigma = deformed_uncertainty(da, db, grid, opts.weighting, sums)
    return corr


def _result(state: _Pass, window: Size3, log: list[dict]) -> PIVResult:
    dz, dy, dx = (c.copy() for c in state.field)
    for comp in (dx, dy, dz):
        comp[state.masked] = np.nan
    valid = ~(state.invalid | state.outlier)
    sigma = (np.full((3, *valid.shape), np.nan) if state.sigma is None
             else np.where(valid, state.sigma, np.nan))
    z, y, x = state.centres
    return PIVResult(x=x, y=y, z=z, u=dx, v=dy, w=dz, valid=valid,
                     peak_ratio=state.peak_ratio, outlier=state.outlier, masked=state.masked,
                     window=window, passes=log, sigma_u=sigma[2], sigma_v=sigma[1],
                     sigma_w=sigma[0])
