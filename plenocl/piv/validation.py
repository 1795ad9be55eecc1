"""Universal outlier detection (normalised median test) and outlier replacement.

Westerweel & Scarano (2005), Exp. Fluids 39:1096: for every vector, the median ``U_m``
of its 26 neighbours and the median ``r_m`` of their residuals ``|U_i - U_m|`` give the
normalised residual ``r* = |U_0 - U_m| / (r_m + eps)`` per component; a vector is an
outlier where ``sqrt(sum of r*^2)`` over the components exceeds the threshold. The field is
padded by odd reflection (``2 U_0 - U_1``) so vectors along the faces are tested against
a linear continuation rather than against nothing (docs/design.md §7). Arrays are
``(C, nz, ny, nx)``.
"""

from __future__ import annotations

import numpy as np


def _neighbours(field: np.ndarray) -> np.ndarray:
    """The 26 neighbours of every vector: ``(26, C, nz, ny, nx)``, odd-reflection padded."""
    nz, ny, nx = field.shape[1:]
    padded = field
    for axis in (1, 2, 3):
        if field.shape[axis] > 1:
            width = [(0, 0)] * 4
            width[axis] = (1, 1)
            padded = np.pad(padded, width, mode="reflect", reflect_type="odd")
        else:
            padded = np.concatenate([padded] * 3, axis=axis)
    out = []
    for dz in range(3):
        for dy in range(3):
            for dx in range(3):
                if (dz, dy, dx) != (1, 1, 1):
                    out.append(padded[:, dz:dz + nz, dy:dy + ny, dx:dx + nx])
    return np.stack(out)


def nan_median(values: np.ndarray) -> np.ndarray:
    """``np.nanmedian(values, axis=0)``, bit for bit (NaN where a column has no finite
    value, without a warning), for a short first axis (the 26 neighbours): one sort
    along it (NaN sorts last) and the mean of the middle two of each column's finite
    values; NumPy's ``nanmedian`` takes a masked array's median there, about five times
    slower."""
    ordered = np.sort(values, axis=0)
    count = np.count_nonzero(~np.isnan(values), axis=0)
    low = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[None], 0)[0]
    high = np.take_along_axis(ordered, (count // 2)[None], 0)[0]
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, (low + high) / 2, np.nan)


def normalized_median_test(field: np.ndarray, eps: float = 0.1, threshold: float = 2.0,
                           ignore: np.ndarray | None = None) -> np.ndarray:
    """Flag outliers with the normalised median test.

    Parameters
    ----------
    field
        ``(C, nz, ny, nx)`` vector components (voxels).
    eps
        Acceptable fluctuation level (voxels), ``0.1`` for cross-correlation PIV.
    threshold
        Detection threshold on the normalised residual (2 in the original paper).
    ignore
        Boolean ``(nz, ny, nx)``: vectors left out of every neighbourhood (e.g. masked or
        already invalid); they are not flagged here.

    Returns
    -------
    numpy.ndarray
        Boolean ``(nz, ny, nx)``, ``True`` where a vector is an outlier.
    """
    data = np.asarray(field, np.float64).copy()
    if ignore is not None and ignore.any():
        data[:, ignore] = np.nan
    nbr = _neighbours(data)
    median = nan_median(nbr)  # NaN for vectors whose neighbours are all ignored
    r_m = nan_median(np.abs(nbr - median))
    with np.errstate(invalid="ignore"):
        norm = np.sqrt(np.sum(((data - median) / (r_m + eps)) ** 2, axis=0))
        flags = norm > threshold
    return flags if ignore is None else flags & ~ignore


def replace_outliers(field: np.ndarray, bad: np.ndarray, max_sweeps: int = 50) -> np.ndarray:
    """Replace flagged vectors by the median of their valid neighbours.

    Clusters of bad vectors are filled from their edges inwards, one sweep at a time;
    if no valid vector is left at all, the field becomes zero.

    Parameters
    ----------
    field
        ``(C, nz, ny, nx)`` vector components.
    bad
        Boolean ``(nz, ny, nx)``, ``True`` where a vector must be replaced.
    max_sweeps
        Upper bound on fill sweeps.

    Returns
    -------
    numpy.ndarray
        A new array with every flagged vector replaced.
    """
    out = np.asarray(field, np.float64).copy()
    todo = np.asarray(bad, bool).copy()
    if todo.all():
        return np.zeros_like(out)
    out[:, todo] = np.nan
    for _ in range(max_sweeps):
        if not todo.any():
            break
        fill = nan_median(_neighbours(out)[:, :, todo])  # NaN inside clusters
        ok = np.all(np.isfinite(fill), axis=0)
        where = np.flatnonzero(todo.ravel())[ok]
        out.reshape(out.shape[0], -1)[:, where] = fill[:, ok]
        todo.ravel()[where] = False
    out[np.isnan(out)] = 0.0
    return out

