"""Microlens image centres as a plain CSV, to bring another tool's calibration (LFIT,
plenopticam, a vendor's export) into a plenocl camera, or to take plenocl's out.

The format, one lens per line after a header (docs/design.md §3)::

    lens_col,lens_row,x_px,y_px
    0,0,8.47,8.52
    1,0,25.46,8.49

``lens_col``, ``lens_row``: the lens's column and row in the array, counted from 0 (the
``(rows, cols)`` order of ``Camera.microlens_centers``); ``x_px``, ``y_px``: its image
centre in pixels, column and row, with the centre of the first pixel at 0. Lenses not
listed (or with an empty or NaN centre) are missing; plenocl writes every lens, a missing
one with an empty centre, so that its files keep the array's extent.

LFIT's own calibration file (``<name>_calData.mat``, LFIT v2: the cell array ``calData``
whose first entry holds the centres, lens rows x lens columns x (x, y), in MATLAB's
1-based pixel coordinates) is read directly (:func:`read_lfit_calibration`).
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .atomic import atomic_path

#: The columns of a centres CSV, in order.
HEADER = ("lens_col", "lens_row", "x_px", "y_px")


def write_centers_csv(path: str | Path, centers: np.ndarray) -> None:
    """Write ``centers`` ``(rows, cols, 2)`` (``(col, row)`` px, ``NaN``: missing) as a
    centres CSV, atomically: every lens, row by row, a missing one with an empty centre,
    so that the file keeps the array's extent (read without a lens count, a dark last
    row or column of lenses is not lost)."""
    centers = np.asarray(centers, float)
    found = np.isfinite(centers).all(-1)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(HEADER)
        for (r, c), seen in np.ndenumerate(found):
            x, y = (repr(float(v)) if seen else "" for v in centers[r, c])
            out.writerow([c, r, x, y])


def read_centres(path: str | Path, ml_count: tuple[int, int] | None) -> np.ndarray:
    """The centres of a centres CSV, or of LFIT's ``.mat`` calibration (by the suffix);
    ``ml_count`` ``None``: the file's own array (a CSV's up to its largest indices)."""
    if Path(path).suffix.lower() == ".mat":
        return read_lfit_calibration(path, ml_count)
    return read_centers_csv(path, ml_count)


def read_lfit_calibration(path: str | Path, ml_count: tuple[int, int] | None) -> np.ndarray:
    """The centres ``(rows, cols, 2)`` (``(col, row)`` px from the first pixel's centre,
    ``NaN``: missing) of LFIT's calibration file: ``calData{1}``, rows x columns x
    (x, y) in MATLAB's pixel coordinates (the first pixel's centre at 1), less 1.
    Refused, naming the fix, when the file holds no ``calData`` or another array size
    than ``ml_count`` (``None``: any)."""
    from scipy.io import loadmat

    try:
        cal = loadmat(path)["calData"]
        points = np.asarray(cal.ravel()[0], dtype=np.float64)
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise ValueError(f"{path} is not an LFIT calibration file (a calData cell array "
                         f"whose first entry holds the centres): {exc}") from None
    cols, rows = ml_count or (points.shape[1::-1] if points.ndim == 3 else (0, 0))
    if points.shape != (rows, cols, 2):
        raise ValueError(
            f"{path} holds {points.shape[1] if points.ndim == 3 else '?'} x "
            f"{points.shape[0]} lens centres (columns x rows; LFIT leaves out lenses its "
            f"calibration cut at the sensor's edge) but the camera file has {cols} x "
            f"{rows}: give the camera file LFIT's count, or export LFIT's centres as a "
            "centres CSV with their lens indices")
    found = (points > 0).all(-1, keepdims=True)  # NaN, or 0 where LFIT found none
    return np.where(found, points - 1.0, np.nan)


def read_centers_csv(path: str | Path, ml_count: tuple[int, int] | None) -> np.ndarray:
    """The centres ``(rows, cols, 2)`` (``(col, row)`` px, ``NaN``: missing) of an array
    of ``ml_count`` = ``(columns, rows)`` lenses from a centres CSV (``None``: up to the
    largest indices listed); refused, naming the line, when the header, a number, a lens
    index or a repeated lens is wrong."""
    entries = _entries(path)
    if ml_count is None:  # the file's own extent (a negative index is refused below)
        entries = list(entries)
        ml_count = tuple(max([e[k] for _, e in entries], default=0) + 1 for k in (0, 1))
    cols, rows = ml_count
    centers = np.full((rows, cols, 2), np.nan)
    for number, entry in entries:
        _place(centers, entry, path, number)
    if not np.isfinite(centers).all(-1).any():
        raise ValueError(f"{path} lists no lens with a centre")
    return centers


def _entries(path: str | Path) -> Iterator[tuple[int, tuple[int, int, float, float]]]:
    """Each non-blank line's number and its parsed lens (:func:`_parse`), after the
    header is checked."""
    with open(path, newline="") as f:
        lines = csv.reader(f)
        header = tuple(cell.strip() for cell in next(lines, []))
        if header != HEADER:
            raise ValueError(f"{path}: the first line must be the header {','.join(HEADER)}, "
                             f"got {','.join(header) or 'nothing'}")
        for number, cells in enumerate(lines, start=2):
            if cells and any(cell.strip() for cell in cells):
                yield number, _parse(cells, path, number)


def _parse(cells: list[str], path, number: int) -> tuple[int, int, float, float]:
    """One line's lens column and row and its centre (``NaN`` for an empty cell)."""
    if len(cells) != len(HEADER):
        raise ValueError(f"{path}, line {number}: expected {len(HEADER)} values "
                         f"({','.join(HEADER)}), got {len(cells)}")
    try:
        kx, ky = (float(cell) for cell in cells[:2])
        x, y = (float(cell) if cell.strip() else np.nan for cell in cells[2:])
    except ValueError:
        raise ValueError(f"{path}, line {number}: {','.join(cells)} is not four numbers"
                         ) from None
    if kx != int(kx) or ky != int(ky) or np.isinf(x) or np.isinf(y):
        raise ValueError(f"{path}, line {number}: lens indices must be whole numbers and the "
                         f"centre finite (or empty: missing), got {','.join(cells)}")
    return int(kx), int(ky), x, y


def _place(centers: np.ndarray, entry: tuple[int, int, float, float], path,
           number: int) -> None:
    """Put one parsed line into ``centers``, refusing an index outside the array and a
    lens given twice."""
    kx, ky, x, y = entry
    rows, cols = centers.shape[:2]
    if not (0 <= kx < cols and 0 <= ky < rows):
        raise ValueError(f"{path}, line {number}: lens ({kx}, {ky}) is outside the camera's "
                         f"{cols} x {rows} array (columns x rows); indices count from 0 — "
                         "check the camera file's microlens count, or subtract 1 from "
                         "indices that count from 1")
    if not np.isnan(centers[ky, kx]).all():
        raise ValueError(f"{path}, line {number}: lens ({kx}, {ky}) is listed twice")
    centers[ky, kx] = (x, y)
