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
from dataclasses import dataclass, replace
from typing import ClassVar, Protocol, runtime_checkable

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
    if abs(angle) > 45:
        raise ValueError(f"the microlens centres' rows run along the sensor's columns (the "
                         f"lattice turned {angle:.1f} degrees): microlens_centers[row, col] "
                         "holds (x, y) = (column, row) pixel coordinates, so centres given "
                         "as (row, column) need their last axis swapped (centres[..., ::-1])")
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


def view_lean(odd_row_shift: float) -> int:
    """How far (columns per row) the projector's axial view leans from the axial indices:
    the view always steps from row to row by ``(+1/2, √3/2)`` pitch, whatever the
    numbering's shift, so 1 for a ``-0.5`` numbering (its axial ``e2`` is ``(-1/2,
    √3/2)``) and 0 otherwise. The projector splits a ray's light over the four lenses of
    the view's rhombus (docs/design.md §5.3), whose long diagonal follows ``e2``: one
    array numbered either way (a row more or fewer, a cropped region of interest) must
    give one projection."""
    return int(odd_row_shift < 0)


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


# ---- the array's layout -----------------------------------------------------------------
#: The microlens layouts a camera may have (docs/design.md §2).
LAYOUTS = ("rectangular", "hexagonal")
#: A hexagonal array's axial view (:meth:`plenocl.camera.Camera.on_lens_lattice`), for
#: the projector only: never a camera file's layout.
AXIAL = "axial"


@dataclass(frozen=True)
class LensLayout:
    """How an array's lenses are placed and numbered: the one object every stage asks
    about the layout (docs/design.md §2), held by the camera (``Camera.layout``).

    Lenses are numbered ``(kx, ky)``, ``kx`` along a row and ``ky`` the row; rows lie
    ``row_ratio`` pitches apart, and the odd rows (1, 3, ...) are shifted along the row
    by ``odd_row_shift`` pitches. In axial indices ``(q, r)`` (:func:`offset_to_axial`)
    every layout is an affine lattice. Use :func:`lens_layout` to make one.

    Parameters
    ----------
    count
        ``(columns, rows)`` of the numbering.
    odd_row_shift
        The odd rows' shift along the row, pitches.
    """

    count: tuple[int, int]
    odd_row_shift: float = 0.0

    #: The layout's name in a camera file (``[microlens_array] layout``).
    name: ClassVar[str] = "rectangular"
    #: Distance between neighbouring rows, in pitches.
    row_ratio: ClassVar[float] = 1.0
    #: Lattice neighbours of an inner lens.
    neighbours: ClassVar[int] = 4
    #: Whether a pixel or ray belongs to the lens whose centre is nearest (a hexagonal
    #: cell) rather than to the lattice cell around it (a parallelogram).
    hexagonal: ClassVar[bool] = False
    #: Whether this is a hexagonal array's axial view, the projector's numbering.
    is_view: ClassVar[bool] = False

    @property
    def staggered(self) -> bool:
        """Whether the odd rows sit off the even ones (a hexagonal array)."""
        return self.odd_row_shift != 0.0

    @property
    def array_count(self) -> tuple[int, int]:
        """``(columns, rows)`` of the array itself (an axial view numbers more columns)."""
        return self.count

    def lattice_coords(self) -> np.ndarray:
        """``(rows, cols, 2)`` position of every lens in the array's own frame, in
        pitches along the rows and rows down: ``(kx + shift·(ky odd), ky)``."""
        cols, rows = self.count
        ky, kx = np.mgrid[0:rows, 0:cols].astype(np.float64)
        return np.stack([kx + self.odd_row_shift * (ky % 2), ky], -1)

    def to_axial(self, k: np.ndarray) -> np.ndarray:
        """Axial indices ``(q, r)`` of lenses numbered ``(kx, ky)`` by this layout."""
        return offset_to_axial(k, self.odd_row_shift)

    def from_axial(self, qr: np.ndarray) -> np.ndarray:
        """This layout's ``(kx, ky)`` of axial indices ``(q, r)``: the inverse of
        :meth:`to_axial`."""
        return axial_to_offset(qr, self.odd_row_shift)

    def rows_within(self, height_pitches: float) -> int:
        """How many rows of lenses fit in ``height_pitches`` pitches."""
        return int(np.floor(height_pitches / self.row_ratio))

    def file_keys(self) -> dict:
        """The ``[microlens_array]`` keys that say this layout in a camera file (none for
        the default rectangular array)."""
        return {}

    def row_offset_terms(self, ky: np.ndarray) -> list[np.ndarray]:
        """The terms a calibration's grid model adds for this layout's rows, given the
        lenses' row indices: none (a hexagonal array: its odd rows' own offset)."""
        return []

    def require_array(self, message: str) -> None:
        """Raise ``ValueError(message)`` if this is the projector's axial view, which only
        the weighting function and projector take."""

    def lattice_view(self, camera):
        """``camera`` with its lenses numbered on an affine lattice
        (:meth:`plenocl.camera.Camera.on_lens_lattice`): the camera itself."""
        return camera

    def rotation_deg(self, row_step: np.ndarray, column_step: np.ndarray) -> float:
        """Rotation (degrees) of the array from its mean steps (pixels) along a row and
        from row to row: the mean of the two axes' turns."""
        ax, ay = row_step, column_step
        return math.degrees(math.atan2(ax[1] - ay[0], ax[0] + ay[1]))

    def column_note(self, lattice: RectangularLattice) -> str:
        """What a message about the array's turn adds about its columns: how far off
        square to the rows they are."""
        return f" and its columns {lattice.skew_deg:+.4f}° off square to them"


@dataclass(frozen=True)
class RectangularLayout(LensLayout):
    """A rectangular array: the base class's rules, rows one pitch apart, no shift."""


@dataclass(frozen=True)
class HexagonalLayout(LensLayout):
    """A hexagonal array: rows ``pitch·√3/2`` apart, the odd rows shifted by ±1/2 pitch;
    a lens owns the points nearest its centre (docs/design.md §2)."""

    odd_row_shift: float = 0.5
    name: ClassVar[str] = "hexagonal"
    row_ratio: ClassVar[float] = math.sqrt(3) / 2
    neighbours: ClassVar[int] = 6
    hexagonal: ClassVar[bool] = True

    def file_keys(self) -> dict:
        """``layout`` and ``odd_row_shift``."""
        return {"layout": self.name, "odd_row_shift": self.odd_row_shift}

    def row_offset_terms(self, ky: np.ndarray) -> list[np.ndarray]:
        """The odd rows' own offset from the even ones (1 on an odd row): a real array's
        odd rows may sit off the nominal half pitch."""
        return [np.rint(ky) % 2]

    def lattice_view(self, camera):
        """``camera``'s axial view (docs/design.md §5): the lenses at axial indices
        ``(q - q_min, r)``, ``NaN`` where the parallelogram holds no lens."""
        cols, rows = self.count
        ky, kx = np.mgrid[0:rows, 0:cols]
        q = offset_to_axial(np.stack([kx, ky], -1), self.odd_row_shift)[..., 0]
        q = q - view_lean(self.odd_row_shift) * ky  # the view's steps: see view_lean
        width = int(q.max() - q.min()) + 1
        centres = np.full((rows, width, 2), np.nan)
        centres[ky, q - q.min()] = camera.microlens_centers
        return replace(camera, ml_layout=AXIAL, ml_count=(width, rows),
                       ml_odd_row_shift=self.odd_row_shift, microlens_centers=centres)

    def rotation_deg(self, row_step: np.ndarray, column_step: np.ndarray) -> float:
        """Rotation (degrees) of the rows alone: the step from row to row is not square
        to them."""
        return math.degrees(math.atan2(row_step[1], row_step[0]))

    def column_note(self, lattice: RectangularLattice) -> str:
        """Nothing: a hexagonal array's columns are not square to its rows."""
        return ""


@dataclass(frozen=True)
class AxialView(HexagonalLayout):
    """A hexagonal array numbered by its axial indices, ``(q - q_min, r)``: the
    projector's affine view of it (:meth:`plenocl.camera.Camera.on_lens_lattice`), whose
    ``count`` pads each row to the parallelogram (``NaN`` centres where it holds no
    lens). Only the weighting function and projector take it."""

    name: ClassVar[str] = AXIAL
    is_view: ClassVar[bool] = True

    @property
    def array_count(self) -> tuple[int, int]:
        """``(columns, rows)`` of the hexagonal array the view stands for (the view's
        last column holds row 0's last lens)."""
        width, rows = self.count
        return width + self.q_min, rows

    @property
    def q_min(self) -> int:
        """The view's index ``q - lean r`` (:func:`view_lean`) of its first column."""
        rows = self.count[1]
        r = np.arange(rows)
        first = np.stack([np.zeros(rows, np.int64), r], -1)
        q = offset_to_axial(first, self.odd_row_shift)[:, 0]
        return int((q - view_lean(self.odd_row_shift) * r).min())

    def to_axial(self, k: np.ndarray) -> np.ndarray:
        """Axial indices of the view's ``(column, row)``: ``(column + q_min + lean row,
        row)``."""
        k = np.asarray(k, dtype=np.int64)
        lean = view_lean(self.odd_row_shift)
        return np.stack([k[..., 0] + self.q_min + lean * k[..., 1], k[..., 1]], -1)

    def from_axial(self, qr: np.ndarray) -> np.ndarray:
        """The view's ``(column, row)`` of axial indices."""
        qr = np.asarray(qr, dtype=np.int64)
        lean = view_lean(self.odd_row_shift)
        return np.stack([qr[..., 0] - self.q_min - lean * qr[..., 1], qr[..., 1]], -1)

    def file_keys(self) -> dict:
        """Refused: the view is the projector's, not a camera file."""
        raise ValueError("a hexagonal array's axial view (Camera.on_lens_lattice) is the "
                         "projector's, not a camera file: write the camera itself")

    def require_array(self, message: str) -> None:
        """Raise ``ValueError(message)``: this is the axial view."""
        raise ValueError(message)

    def lattice_view(self, camera):
        """The view itself."""
        return camera


_LAYOUTS = {cls.name: cls for cls in (RectangularLayout, HexagonalLayout, AxialView)}


def lens_layout(name: str, count: tuple[int, int], odd_row_shift: float | None = None,
                *, view: bool = True) -> LensLayout:
    """The layout called ``name`` (:data:`LAYOUTS`; ``"axial"`` too unless ``view`` is
    false) of an array of ``count`` ``(columns, rows)`` lenses.

    Raises
    ------
    ValueError
        For an unknown layout, or an odd-row shift the layout cannot have (a rectangular
        array's is 0; a hexagonal one's +0.5, the default, or -0.5).
    """
    cls = _LAYOUTS.get(name) if (view or name != AXIAL) else None
    if cls is None:
        raise ValueError(f"microlens layout must be one of {LAYOUTS}, got {name!r} "
                         "([microlens_array] layout)")
    allowed = (0.0,) if cls is RectangularLayout else (0.5, -0.5)
    if odd_row_shift is not None and odd_row_shift not in allowed:
        raise ValueError(f"odd_row_shift must be one of {allowed} (pitches) for a "
                         f"{name} array, got {odd_row_shift!r}")
    shift = allowed[0] if odd_row_shift is None else float(odd_row_shift)
    return cls(count=tuple(count), odd_row_shift=shift)
