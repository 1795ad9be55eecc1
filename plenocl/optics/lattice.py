"""The microlens lattice: one affine fit of the calibrated image centres, and what follows
from it (the position of lens ``(kx, ky)``, the fractional lens index of a point, the
cell each pixel lies in, the array's rotation).

:class:`LensLattice` is the interface a microlens array's layout offers;
:class:`RectangularLattice` implements it for a (possibly rotated or sheared)
rectangular array, by the affine fit :func:`lattice_fit`. A hexagonal array is a second
implementation of the same interface. The module functions below are the rectangular
lattice's building blocks, kept for their callers (calibration, grid, projector).

Plain NumPy on arrays of centres; it imports nothing else of plenocl, so every stage
(grid, weighting model, light field, solver) shares this one definition.
"""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import numpy as np

#: Lens-index drift (in lenses, across the array) below which a fitted layout counts as
#: axis-aligned: the projector drops its rotation/shear terms and uses its separable path.
DEFAULT_SHEAR_TOL = 1e-3


def rotation_matrix(degrees: float) -> np.ndarray:
    """``(2, 2)`` counter-clockwise rotation by ``degrees`` about the optical axis."""
    t = math.radians(degrees)
    return np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])


def lattice_fit(centres: np.ndarray, coords: np.ndarray | None = None) -> np.ndarray:
    """Affine least-squares fit of a lens lattice: ``(3, 2)`` ``M`` with
    ``centre(kx, ky) = [kx, ky, 1] @ M``, or ``[a, b, 1] @ M`` in given lattice
    coordinates.

    Parameters
    ----------
    centres
        ``(rows, cols, 2)`` positions of the lenses ``[ky, kx]`` in any length unit;
        ``NaN`` entries (missing lenses) are ignored.
    coords
        Optional ``(rows, cols, 2)`` lattice coordinates ``(a, b)`` of the lenses in which
        the array is affine (a hexagonal array's,
        :meth:`plenocl.camera.Camera.lens_lattice_coords`); ``None``: ``(kx, ky)``.

    Raises
    ------
    ValueError
        When fewer than 3 non-collinear centres are known.
    """
    c = np.asarray(centres, dtype=np.float64)
    rows, cols = c.shape[:2]
    if coords is None:
        ky, kx = np.mgrid[0:rows, 0:cols]
        coords = np.stack([kx, ky], axis=-1)
    ok = np.isfinite(c).all(axis=-1)
    design = np.column_stack([np.asarray(coords, np.float64)[ok], np.ones(int(ok.sum()))])
    if ok.sum() < 3 or np.linalg.matrix_rank(design) < 3:
        raise ValueError(f"only {int(ok.sum())} microlens centres are known, or they are "
                         "collinear: too few to fit the array layout; calibrate the camera "
                         "with a white image that lights the whole array")
    model, *_ = np.linalg.lstsq(design, c[ok], rcond=None)
    return model


def lattice_residual(centres: np.ndarray, model: np.ndarray) -> float:
    """Largest distance of a known centre from the fitted lattice (same units)."""
    c = np.asarray(centres, dtype=np.float64)
    rows, cols = c.shape[:2]
    ky, kx = np.mgrid[0:rows, 0:cols]
    fitted = np.stack([kx, ky, np.ones_like(kx)], -1) @ model
    ok = np.isfinite(c).all(axis=-1)
    return float(np.abs(fitted[ok] - c[ok]).max())


def lattice_cells(model: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Lens index ``(kx, ky)``, ``(H, W)`` int32 each, of the lattice cell holding each pixel.

    The cell of lens ``k`` is the parallelogram of one lattice step around its fitted
    centre (``model``: :func:`lattice_fit` in pixels), so a rotated or sheared array is
    handled; indices outside ``[0, cols) x [0, rows)`` mean the pixel lies beyond the
    array. Vectorised over the sensor: no search per pixel.
    """
    inv = np.linalg.inv(model[:2].T)
    dc, dr = np.arange(width) - model[2, 0], np.arange(height) - model[2, 1]
    kx = np.rint(inv[0, 0] * dc[None, :] + inv[0, 1] * dr[:, None]).astype(np.int32)
    ky = np.rint(inv[1, 0] * dc[None, :] + inv[1, 1] * dr[:, None]).astype(np.int32)
    return kx, ky


def lattice_rotation_deg(centres: np.ndarray) -> float:
    """Rotation (degrees, counter-clockwise) of the microlens rows against the sensor's
    x axis, from :func:`lattice_fit` of ``(rows, cols, 2)`` image centres (pixels)."""
    return RectangularLattice.fit(centres).rotation_deg


def separable_rotation_deg(centres: np.ndarray, tol_lenses: float) -> float:
    """The frame rotation that makes the lattice axis-aligned: :func:`lattice_rotation_deg`,
    or 0 when that rotation moves a lens index by at most ``tol_lenses`` across the array
    (an aligned array stays in the sensor's frame)."""
    angle = lattice_rotation_deg(centres)
    rows, cols = np.asarray(centres).shape[:2]
    drift = abs(math.tan(math.radians(angle))) * max(rows, cols)
    return 0.0 if drift <= tol_lenses else angle


def axial_basis(odd_row_shift: float, row_ratio: float) -> np.ndarray:
    """``(2, 2)`` the array's two lattice steps as rows, in pitches along the array's
    axes: ``e1 = (1, 0)`` along a row and ``e2 = (shift, row_ratio)`` to the next row's
    lens (a rectangular array: ``(0, 1)``; a hexagonal one: ``(±1/2, √3/2)``). Any lens
    lies at ``q e1 + r e2`` for integer axial indices ``(q, r)``."""
    return np.array([[1.0, 0.0], [odd_row_shift, row_ratio]])


def offset_to_axial(k: np.ndarray, odd_row_shift: float) -> np.ndarray:
    """Axial indices ``(q, r)`` of lenses ``(kx, ky)`` (``(..., 2)`` int): ``r = ky``,
    ``q = kx - 2 shift floor(ky / 2)`` (the identity for a rectangular array)."""
    k = np.asarray(k, dtype=np.int64)
    step = int(round(2 * odd_row_shift))
    return np.stack([k[..., 0] - step * (k[..., 1] // 2), k[..., 1]], -1)


def axial_to_offset(qr: np.ndarray, odd_row_shift: float) -> np.ndarray:
    """Lens indices ``(kx, ky)`` of axial indices ``(q, r)``: the inverse of
    :func:`offset_to_axial`."""
    qr = np.asarray(qr, dtype=np.int64)
    step = int(round(2 * odd_row_shift))
    return np.stack([qr[..., 0] + step * (qr[..., 1] // 2), qr[..., 1]], -1)


@runtime_checkable
class LensLattice(Protocol):
    """What a microlens array's layout offers, whatever its shape.

    Lenses are numbered ``(kx, ky)`` (``kx`` along a row, ``ky`` the row), ``shape`` is
    ``(rows, cols)``; positions are in the unit of the centres the lattice was fitted to
    (pixels or millimetres).
    """

    shape: tuple[int, int]

    def positions(self) -> np.ndarray:
        """``(rows, cols, 2)`` fitted position of every lens."""

    def index(self, points) -> np.ndarray:
        """Fractional lens index ``(..., 2)`` ``(kx, ky)`` of points ``(..., 2)``."""

    def nearest(self, points) -> np.ndarray:
        """Index ``(..., 2)`` int ``(kx, ky)`` of the lens whose cell holds each point
        (may lie outside the array)."""

    def cells(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`nearest` of every pixel centre of a ``width x height`` sensor."""

    def residual(self, centres: np.ndarray) -> float:
        """Largest distance of a known centre from its fitted position."""

    @property
    def rotation_deg(self) -> float:
        """Rotation (degrees, counter-clockwise) of the lens rows against the x axis."""


class RectangularLattice:
    """A rectangular (possibly rotated or sheared) lattice: ``position(kx, ky) =
    [kx, ky, 1] @ model`` with ``model`` the ``(3, 2)`` affine fit (:func:`lattice_fit`).

    Parameters
    ----------
    model
        ``(3, 2)`` lens index to position map.
    shape
        ``(rows, cols)`` of the array.
    """

    def __init__(self, model: np.ndarray, shape: tuple[int, int]) -> None:
        self.model = np.asarray(model, dtype=np.float64)
        self.shape = (int(shape[0]), int(shape[1]))

    @classmethod
    def fit(cls, centres: np.ndarray) -> RectangularLattice:
        """The lattice fitted to ``(rows, cols, 2)`` centres (``NaN``: missing lenses)."""
        c = np.asarray(centres, dtype=np.float64)
        return cls(lattice_fit(c), c.shape[:2])

    def positions(self) -> np.ndarray:
        """``(rows, cols, 2)`` fitted position of every lens."""
        rows, cols = self.shape
        ky, kx = np.mgrid[0:rows, 0:cols]
        return np.stack([kx, ky, np.ones((rows, cols))], -1) @ self.model

    def index(self, points) -> np.ndarray:
        """Fractional lens index ``(..., 2)`` ``(kx, ky)`` of points ``(..., 2)``."""
        inv = np.linalg.inv(self.model[:2].T)
        return (np.asarray(points, dtype=np.float64) - self.model[2]) @ inv.T

    def nearest(self, points) -> np.ndarray:
        """Index ``(..., 2)`` int of the lens whose cell (one lattice step around its
        fitted position) holds each point; outside ``[0, cols) x [0, rows)``: beyond
        the array."""
        return np.rint(self.index(points)).astype(np.int32)

    def cells(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """:func:`lattice_cells` of this lattice (positions in pixels)."""
        return lattice_cells(self.model, width, height)

    def residual(self, centres: np.ndarray) -> float:
        """:func:`lattice_residual` of ``centres`` against this lattice."""
        return lattice_residual(centres, self.model)

    @property
    def rotation_deg(self) -> float:
        """Rotation (degrees, counter-clockwise) of the lens rows against the x axis."""
        return math.degrees(math.atan2(self.model[0, 1], self.model[0, 0]))

    @property
    def skew_deg(self) -> float:
        """How far (degrees) the lens columns are off square to the rows: 0 for a
        rectangular lattice, 30 for a hexagonal array's offset rows seen as columns."""
        row, col = self.model[0], self.model[1]
        cos = float(row @ col) / (math.hypot(*row) * math.hypot(*col))
        return math.degrees(math.asin(max(-1.0, min(1.0, cos))))
