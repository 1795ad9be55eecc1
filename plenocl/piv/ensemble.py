"""Ensemble correlation: the mean displacement of many volume pairs from their summed
correlations rather than from their averaged vectors.

Every pair is deformed by the same predictor (the mean field), correlated directly at the
63 lags around zero (:mod:`plenocl.piv.direct`), and the windows' weighted sums
(covariances and variances) are added over the pairs before the coefficients are formed
and fitted. True particles correlate at the same lag in every pair and add up; ghosts,
noise and unmatched particles do not. This is the standard remedy where each pair holds
too few particles or too much noise for a clean peak of its own (Meinhart, Wereley &
Santiago 2000; Westerweel, Geelhoed & Lindken 2004). It gives the mean field only, not
its fluctuations; a few iterations refine the predictor.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from ..vectorfield import PIVResult
from .correlation import window_grid
from .deformation import make_deformer
from .devicesums import sums_for
from .direct import CENTRE, LAGS, correlate_direct, fit_direct, off_centre, pearson
from .interpolate import resample
from .validation import normalized_median_test, replace_outliers

#: The ensemble correlation's method (:func:`ensemble_piv` at its defaults, which the
#: batch's ensemble field runs), recorded with that field
#: (:func:`plenocl.batch.record.ensemble_record`): a rerun correlates the ensemble again
#: instead of keeping one an earlier method made. Change it whenever the ensemble makes
#: another field from the same pairs and predictor (rounding included).
METHOD = ("the pairs deformed by the predictor, their direct correlations' window sums "
          "at 63 lags added, 2 passes at overlap 0.75, Gaussian weight 0.35, cubic "
          "deformation (2026-12-01)")
#: A zero-argument callable yielding ``(vol_a, vol_b)`` volume pairs, called once per
#: iteration (volumes are read one pair at a time, never all held at once).
PairSource = Callable[[], Iterable[tuple[np.ndarray, np.ndarray]]]


def ensemble_piv(pairs: PairSource, predictor: PIVResult, *, window=None,
                 overlap: float = 0.75, iterations: int = 2, weighting: float = 0.35,
                 queue=None, deform_order: int = 3) -> PIVResult:
    """The ensemble-correlation mean displacement of volume pairs.

    Parameters
    ----------
    pairs
        Yields every ``(vol_a, vol_b)`` of the ensemble (same shape) on each call.
    predictor
        A first estimate of the mean field (e.g. the average of the pairs' own fields)
        within about a voxel: its window grid and values seed the first iteration.
    window
        Window size ``(wz, wy, wx)`` (default: the predictor's).
    overlap
        Window overlap fraction.
    iterations
        Passes over the ensemble, each deforming by the previous result.
    weighting
        Gaussian window weight (a fraction of the window).
    queue
        OpenCL device for the deformation (``None``: the default device, as
        :func:`plenocl.piv3d`; ``False``: SciPy on the host).
    deform_order
        Interpolation of the deformation (1 or 3; 5 on the host only).

    Returns
    -------
    PIVResult
        The mean displacement (voxels) on the window grid; ``valid`` where the summed
        correlation peaked at the centre lag and passed the median test; ``peak_ratio``
        and the uncertainties are NaN (not defined for an ensemble).
    """
    if iterations < 1:
        raise ValueError(f"iterations must be at least 1, got {iterations!r}")
    window = tuple(int(w) for w in (predictor.window if window is None else window))
    field = np.stack([predictor.w, predictor.v, predictor.u])
    centres = (predictor.z, predictor.y, predictor.x)
    deformer = make_deformer(deform_order, queue)
    sums = sums_for(deformer)
    result = None
    for k in range(iterations):
        result = _ensemble_pass(pairs, field, centres, window, overlap, weighting,
                                (deformer, sums), final=k == iterations - 1)
        field = np.stack([result.w, result.v, result.u])
        centres = (result.z, result.y, result.x)
    return result


def _ensemble_pass(pairs: PairSource, field, centres, window, overlap, weighting,
                   engines, final: bool) -> PIVResult:
    """One pass: deform every pair by ``field``, sum the window sums, fit; ``engines`` the
    deformer and the window sums' engine (:func:`plenocl.piv.devicesums.sums_for`)."""
    deformer, sums = engines
    totals, grid, base, count = None, None, None, 0
    for vol_a, vol_b in pairs():
        shape = np.shape(vol_a)
        if grid is None:
            grid = window_grid(shape, window, overlap)
            dense = deformer.predictor(np.nan_to_num(field), centres, shape)
            base = resample(np.nan_to_num(field), centres, grid.centres)
        da = deformer(deformer.prepare(vol_a), dense, -0.5)
        db = deformer(deformer.prepare(vol_b), dense, +0.5)
        corr = correlate_direct(da, db, grid, weighting, sums)
        parts = (corr.cov, corr.var_a, corr.var_b)
        totals = parts if totals is None else tuple(t + p for t, p in zip(totals, parts))
        count += 1
    if count == 0:
        raise ValueError("the ensemble holds no volume pairs")
    return _fit_ensemble(totals, grid, base, final)


def _fit_ensemble(totals, grid, base, final: bool) -> PIVResult:
    """Coefficients of the summed sums, their peaks, the median test. A window whose
    peak is off the centre lag moves by that lag (whole voxels) for the next pass; after
    the last pass it is invalid and replaced from its neighbours."""
    cov, var_a, var_b = totals
    r = pearson(cov, var_a, var_b)
    disp, _, _ = fit_direct(r)
    centred = ~off_centre(r)              # fitted at lag zero only: a sparse ensemble's
    best = np.argmax(r, axis=0)           # peak elsewhere moves by its lag, refit next pass
    disp = np.where(centred, disp, LAGS[best].transpose(3, 0, 1, 2))
    signal = (var_a[CENTRE] > 0) & (var_b[CENTRE] > 0)
    total = base + disp
    outlier = normalized_median_test(total, ignore=~signal)
    invalid = ~signal | ~centred
    total = replace_outliers(total, outlier | ~signal | (~centred if final else False))
    z, y, x = grid.centres
    nan = np.full(grid.count, np.nan)
    return PIVResult(x=x, y=y, z=z, u=total[2], v=total[1], w=total[0],
                     valid=~(invalid | outlier), peak_ratio=nan, outlier=outlier,
                     masked=np.zeros(grid.count, bool), window=grid.size,
                     passes=[{"ensemble": True, "window": grid.size}],
                     sigma_u=nan, sigma_v=nan, sigma_w=nan)
