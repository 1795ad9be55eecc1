"""Another tool's centres for a region of interest's camera (docs/design.md §3): a file of
the whole sensor's centres (the whole array's numbering, the whole sensor's pixels), from
which the region's lenses are taken as :meth:`plenocl.Camera.cropped` takes them, or a
file of the region's own lenses in its pixels; :func:`plenocl.calibration.import_centers`
reads a region's file with :func:`region_file_centres`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..camera.region import kept_centres, nearest_lenses
from ..io.centres import read_centres
from .checks import image_pitch_px


def lattice_offset(centres: np.ndarray, camera: Camera) -> float:
    """The median distance (pitches) of the found ``centres`` ``(rows, cols, 2)`` from
    ``camera``'s nominal lattice, lens by lens."""
    found = np.isfinite(centres).all(-1)
    off = np.hypot(*(centres - camera.ideal_microlens_centers())[found].T) / image_pitch_px(camera)
    return float(np.median(off))


def region_file_centres(path: str | Path, camera: Camera, tolerance: float) -> np.ndarray:
    """The centres of the region's lenses, in its pixels, from a centres file.

    The file is the region's own when it numbers no lens beyond the region's count and
    its centres lie within ``tolerance`` pitches (median) of the region's lattice; else
    the whole sensor's when, less the region's ``crop_origin``, its lenses matched to
    the region's by position (:func:`_from_whole`) lie within ``tolerance``.

    Parameters
    ----------
    path
        A centres CSV or LFIT ``.mat`` (:func:`plenocl.io.centres.read_centres`).
    camera
        A region's camera (:meth:`plenocl.Camera.cropped`: ``full_pixels`` given).
    tolerance
        :data:`plenocl.calibration.IMPORT_TOLERANCE`.

    Returns
    -------
    numpy.ndarray
        ``(rows, cols, 2)`` centres (``NaN``: missing).

    Raises
    ------
    ValueError
        When neither reading fits, naming both and the fix.
    """
    centres = read_centres(path, None)
    own, own_why = _as_own(centres, camera)
    if own is not None:
        own_off = lattice_offset(own, camera)
        if own_off <= tolerance:
            return own
        own_why = f"its lenses lie {own_off:.2f} pitches (median) from the region's lattice"
    whole, whole_why = _from_whole(centres, camera)
    if whole is not None:
        whole_off = lattice_offset(whole, camera)
        if whole_off <= tolerance:
            return whole
        whole_why = f"the region's lenses lie {whole_off:.2f} pitches (median) from its lattice"
    raise ValueError(_neither(path, camera, own_why, whole_why))


def _as_own(centres: np.ndarray, camera: Camera) -> tuple[np.ndarray | None, str]:
    """The file's ``centres`` as the region's own lenses (those it does not list:
    ``NaN``), or ``None`` and why not: it numbers more lenses than the region holds."""
    rows, cols = centres.shape[:2]
    if cols > camera.ml_count[0] or rows > camera.ml_count[1]:
        return None, f"it numbers {cols} x {rows} lenses"
    own = np.full((camera.ml_count[1], camera.ml_count[0], 2), np.nan)
    own[:rows, :cols] = centres
    return own, ""


def _from_whole(centres: np.ndarray, camera: Camera) -> tuple[np.ndarray | None, str]:
    """The region's lenses of a file of the whole sensor's ``centres``: less the region's
    ``crop_origin``, the file's lenses that lie in the region are matched to the region's
    nearest lattice nodes, and the index offset most of them share places the region's
    first lens in the file's numbering, which must hold every lens of the region (a
    region's own file read so, indices run past it); ``None`` and why not, else the
    centres (:func:`plenocl.camera.region.kept_centres`) and ``""``."""
    rows, cols = centres.shape[:2]
    q = centres - np.asarray(camera.crop_origin, dtype=np.float64)
    w, h = camera.pixels
    inside = np.isfinite(q).all(-1) & (q >= -0.5).all(-1) & (q[..., 0] <= w - 0.5) \
        & (q[..., 1] <= h - 0.5)
    if not inside.any():
        return None, "none of its centres lies in the region"
    k = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), axis=-1)[inside]
    offsets, votes = np.unique(k - nearest_lenses(camera, q[inside]), axis=0,
                               return_counts=True)
    first = tuple(int(v) for v in offsets[np.argmax(votes)])
    last = (first[0] + camera.ml_count[0] - 1, first[1] + camera.ml_count[1] - 1)
    if min(first) < 0 or last[0] >= cols or last[1] >= rows:
        return None, (f"its {cols} x {rows} lenses do not hold the region's, which would be "
                      f"its lenses {first} to {last}")
    mine = kept_centres(centres, first, camera.ml_count, camera.crop_origin)
    if not np.isfinite(mine).all(-1).any():
        return None, "it gives none of the region's lenses a centre"
    return mine, ""


def _neither(path, camera: Camera, own_why: str, whole_why: str) -> str:
    """The message refusing a file that fits the region neither way."""
    (c, r), (w, h), (fw, fh) = camera.crop_origin, camera.pixels, camera.full_pixels
    cols, rows = camera.ml_count
    return (
        f"the centres in {path} fit this camera's region of interest ({w} x {h} px from "
        f"({c}, {r}) of the {fw} x {fh} px sensor, {cols} x {rows} lenses) neither as the "
        f"whole sensor's centres (lenses numbered on the whole array, whole-sensor pixels: "
        f"{whole_why}) nor as the region's own (its {cols} x {rows} lenses numbered from its "
        f"first, the region's pixels: {own_why}). Check that x_px is the column and y_px "
        "the row, that lens indices count from 0, and that the camera is the whole "
        "sensor's camera file cropped to the region the centres are for (--crop COLUMN ROW "
        "WIDTH HEIGHT, Camera.cropped); or import them onto the whole sensor's camera and "
        "crop it after (Camera.cropped keeps the centres)")
