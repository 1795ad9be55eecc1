"""A region of interest of the sensor (docs/design.md §2): the lenses whose image centre
lies in it, placed where they stand on the whole array, with the optical axis kept where
it crosses the whole sensor, and a calibrated camera's measured centres of those lenses.

:meth:`plenocl.camera.Camera.cropped` builds on :func:`region_fields`; the camera then
counts sensor millimetres from the axis (``full_pixels`` and ``crop_origin``), not from
the region's centre, so positions seen through an off-centre region are the whole
frame's. :func:`kept_centres` and :func:`nearest_lenses` also serve
:func:`plenocl.calibration.import_centers`, which takes a region's lenses from a file of
the whole sensor's centres.
"""

from __future__ import annotations

import math

import numpy as np

from .lattice import rotation_matrix

__all__ = ["kept_centres", "nearest_lenses", "region_fields"]

#: Lattice units a lens centre may lie beyond a region's pixel edge and still count
#: (rounding of the edge's position, not a real overlap).
_EDGE_SLACK = 1e-9


def region_fields(camera, origin: tuple[int, int], size: tuple[int, int]) -> dict:
    """The fields (:func:`dataclasses.replace` keywords) of ``camera`` seen through
    ``size`` = ``(columns, rows)`` pixels from ``origin`` = ``(column, row)`` of its
    sensor: the region's pixels, its origin and the whole sensor's size, and the
    sub-array of the lenses whose image centre lies in the region (their count, the
    offset of their centre, a hexagonal array's odd-row shift as the sub-array numbers
    its rows; the whole sensor keeps its array as it is).

    Raises
    ------
    ValueError
        When the region reaches beyond the sensor, holds no lens image centre, or the
        camera records a region without the whole sensor's size.
    """
    _check_inside(camera, origin, size)
    if camera.crop_origin is not None and camera.full_pixels is None:
        raise ValueError("this camera records a region of interest ([sensor] crop_origin) "
                         "but not the whole sensor's size: add [sensor] full_pixels = "
                         "[columns, rows] before cropping it again")
    base = camera.crop_origin or (0, 0)
    full = camera.full_pixels or camera.pixels
    whole = origin == (0, 0) and tuple(size) == camera.pixels
    # the whole: the array as it is
    lenses, first = ({}, (0, 0)) if whole else _sub_array(camera, origin, size)
    centres = None if not camera.calibrated else kept_centres(
        camera.microlens_centers, first, lenses.get("ml_count", camera.ml_count), origin)
    return dict(pixels=tuple(size), crop_origin=(base[0] + origin[0], base[1] + origin[1]),
                full_pixels=tuple(full), microlens_centers=centres, **lenses)


def kept_centres(centres: np.ndarray, first: tuple[int, int], count: tuple[int, int],
                 origin: tuple[int, int]) -> np.ndarray:
    """The centres of a region's lenses in its pixels.

    Parameters
    ----------
    centres
        ``(rows, cols, 2)`` centres ``(col, row)`` px of the array the region is cut
        from, on its sensor (``NaN``: missing, kept so).
    first
        ``(kx, ky)`` of the region's first lens on that array.
    count
        The region's ``(columns, rows)`` of lenses, lens ``(i, j)`` being the array's
        ``(kx + i, ky + j)`` (a hexagonal region flips its odd-row shift instead of
        renumbering, :func:`region_fields`).
    origin
        The region's first pixel ``(column, row)`` on that sensor.

    Returns
    -------
    numpy.ndarray
        ``(count[1], count[0], 2)`` centres less ``origin``.
    """
    (kx, ky), (cols, rows) = first, count
    cut = np.asarray(centres, dtype=np.float64)[ky:ky + rows, kx:kx + cols]
    return cut - np.asarray(origin, dtype=np.float64)


def nearest_lenses(camera, colrow) -> np.ndarray:
    """``(..., 2)`` integer ``(kx, ky)`` of the lens of ``camera``'s nominal layout whose
    ideal image centre lies nearest each ``(col, row)`` pixel point (on its lattice,
    extended beyond the array: indices may be negative or past the count)."""
    a, b = np.moveaxis(_lattice_position(camera, colrow), -1, 0)
    ky = np.rint(b).astype(np.int64)
    kx = np.rint(a - camera.layout.odd_row_shift * np.mod(ky, 2)).astype(np.int64)
    return np.stack([kx, ky], axis=-1)


def _lattice_position(camera, colrow) -> np.ndarray:
    """``(col, row)`` pixel points as ``camera``'s lattice coordinates ``(kx + shift·(ky
    odd), ky)``, the frame of :meth:`~plenocl.camera.Camera.lens_lattice_coords`."""
    on_array = camera.px_to_mm(colrow) / camera.lens_image_scale - camera.ml_offset_mm
    along = on_array @ rotation_matrix(camera.ml_rotation_deg)  # into the array's frame
    pitch = np.array([camera.ml_pitch_mm, camera.ml_row_pitch_mm])
    return along / pitch + (np.array(camera.ml_count) - 1) / 2


def _check_inside(camera, origin: tuple[int, int], size: tuple[int, int]) -> None:
    """Refuse a region that reaches beyond the camera's sensor."""
    if any(o + n > full for o, n, full in zip(origin, size, camera.pixels)):
        raise ValueError(
            f"the region of {size[0]} x {size[1]} px from ({origin[0]}, {origin[1]}) reaches "
            f"beyond the {camera.pixels[0]} x {camera.pixels[1]} px sensor: give a region "
            "inside it (COLUMN + WIDTH <= columns, ROW + HEIGHT <= rows)")


def _sub_array(camera, origin: tuple[int, int], size: tuple[int, int]
               ) -> tuple[dict, tuple[int, int]]:
    """``ml_count``, ``ml_offset_mm`` and ``ml_odd_row_shift`` of the lenses whose image
    centre lies in the region, counted as the whole array is: along the array's own
    rows and columns (its rotation aside), a hexagonal array's columns on its first
    row; and ``(kx, ky)`` of its first lens on the whole array."""
    (cols, rows), layout = camera.ml_count, camera.layout
    pitch = np.array([camera.ml_pitch_mm, camera.ml_row_pitch_mm])
    centre, half = _region_in_lattice(camera, origin, size, pitch)
    ky = _index_span(centre[1] - half[1], centre[1] + half[1], rows)
    first_odd = ky[0] % 2 == 1
    shift = layout.odd_row_shift * first_odd
    kx = _index_span(centre[0] - half[0] - shift, centre[0] + half[0] - shift, cols)
    if kx[1] < kx[0] or ky[1] < ky[0]:
        raise ValueError(
            f"the region of {size[0]} x {size[1]} px from ({origin[0]}, {origin[1]}) holds no "
            "microlens image centre: give a region at least a lens image wide and high")
    count = (kx[1] - kx[0] + 1, ky[1] - ky[0] + 1)
    # the sub-array's centre on the whole array's lattice, in the array's frame (mm)
    move = np.array([kx[0] + shift + (count[0] - 1) / 2 - (cols - 1) / 2,
                     ky[0] + (count[1] - 1) / 2 - (rows - 1) / 2]) * pitch
    offset = tuple(np.add(camera.ml_offset_mm, rotation_matrix(camera.ml_rotation_deg) @ move))
    odd = -layout.odd_row_shift if first_odd else layout.odd_row_shift
    return dict(ml_count=count, ml_offset_mm=offset,
                ml_odd_row_shift=odd if layout.staggered else None), (kx[0], ky[0])


def _region_in_lattice(camera, origin, size, pitch: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The region's centre as the whole array's lattice coordinates ``(kx, ky)`` (even
    rows), and its half-width and half-height in pitches and rows (its pixel edges)."""
    middle = np.asarray(origin, float) + (np.asarray(size, float) - 1) / 2
    centre = _lattice_position(camera, middle)
    half = np.asarray(size, float) / 2 * camera.pixel_pitch_mm / camera.lens_image_scale / pitch
    return centre, half


def _index_span(lo: float, hi: float, count: int) -> tuple[int, int]:
    """The first and last whole lens index in ``[lo, hi]`` (lattice units) within the
    array's ``count`` lenses."""
    return (max(0, math.ceil(lo - _EDGE_SLACK)),
            min(count - 1, math.floor(hi + _EDGE_SLACK)))
