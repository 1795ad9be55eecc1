"""Which microlens a sensor pixel lies behind: one rule for every stage.

A rectangular array: a pixel belongs to the lens whose lattice cell (one image pitch
around the lens's centre on the lattice fitted to the calibrated image centres,
:class:`RectangularLattice`, so a rotated or sheared array is handled) contains the
pixel's centre. A hexagonal array (docs/design.md §2): to the lens whose calibrated
image centre is nearest, its hexagonal cell as the simulator draws it (a lens
calibration missed counts at its position on the lattice fitted in axial indices,
:func:`plenocl.camera.lattice.offset_to_axial`, where the array is affine). The
projector's axial view of a hexagonal array (:meth:`plenocl.camera.Camera.on_lens_lattice`,
layout ``"axial"``) gets the same hexagonal cells, numbered by the view's axial indices.
The light field (:func:`lens_owner`: ``-1`` beyond the array) and MART's view blocks
(:func:`pixel_lenses` with ``clamp``: beyond the array, the nearest edge lens) use it.

Two related maps are deliberately *not* this rule: the projector's lens index map
(:func:`plenocl.projection.weighting.lens_index_map`) takes continuous array-plane
points (not pixels) to fractional lens indices and drops a shear below ``shear_tol``
so that the separable path applies; the ray bundle
(:class:`plenocl.optics.raybundle.RayBundle`) shares a ray between two lenses within a
ramp of the cell edge so that its image is differentiable. Both start from the same
lattice fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..camera import Camera
from ..camera.lattice import RectangularLattice, lattice_fit, offset_to_axial

__all__ = ["lens_owner", "pixel_lenses"]

#: Sensor rows per chunk of the hexagonal cells (bounds the memory on a 16 MP sensor).
_CHUNK_ROWS = 256


def pixel_lenses(camera: Camera, centres: np.ndarray | None = None, clamp: bool = False
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Lens index ``(kx, ky)``, ``(H, W)`` int32 each, of the cell holding each pixel.

    Parameters
    ----------
    camera
        The camera (sensor size, layout; its microlens centres unless ``centres`` is
        given). A hexagonal camera's indices are its offset indices ``(kx, ky)``; its
        axial view's (layout ``"axial"``) the view's axial columns and rows.
    centres
        Optional ``(rows, cols, 2)`` image centres (pixels) to use instead of the camera's.
    clamp
        Give pixels beyond the array the nearest edge lens; otherwise their indices lie
        outside ``[0, cols) x [0, rows)`` (a hexagonal array or its axial view: ``(-1,
        -1)``).
    """
    centres = camera.microlens_centers if centres is None else centres
    if not camera.layout.hexagonal:
        lattice = RectangularLattice.fit(centres)
        kx, ky = lattice.cells(*camera.pixels)
        if clamp:
            rows, cols = lattice.shape
            np.clip(kx, 0, cols - 1, out=kx)
            np.clip(ky, 0, rows - 1, out=ky)
        return kx, ky
    return _hexagonal_cells(camera, np.asarray(centres, dtype=np.float64), clamp)


def lens_owner(camera: Camera, centres: np.ndarray | None = None) -> np.ndarray:
    """Flat index ``ky * cols + kx`` of the microlens each pixel lies behind, ``(H, W)``
    int32; ``-1`` outside the array (:func:`pixel_lenses`)."""
    cols, rows = camera.ml_count
    kx, ky = pixel_lenses(camera, centres)
    inside = (kx >= 0) & (kx < cols) & (ky >= 0) & (ky < rows)
    return np.where(inside, ky * cols + kx, -1).astype(np.int32)


# ---- hexagonal cells ------------------------------------------------------------------
@dataclass(frozen=True)
class _AxialLenses:
    """A hexagonal array's lenses on its axial lattice, with a ring of one lattice step
    around the view's parallelogram: ``table[r + 1, q + 1]`` the position (pixels) of view
    column ``q``, row ``r``: its calibrated centre where a lens sits (a lens calibration
    missed at its fitted position), its fitted lattice position elsewhere; ``real`` where
    a lens sits; ``model`` the affine fit ``[q, r, 1] @ model``; ``q_min`` the axial index
    of the view's first column."""

    table: np.ndarray
    real: np.ndarray
    model: np.ndarray
    q_min: int


def _axial_lenses(camera: Camera, centres: np.ndarray) -> _AxialLenses:
    """The lenses of a hexagonal camera (offset indices) or of its axial view, on the
    axial lattice."""
    layout = camera.layout
    cols, rows = layout.array_count
    ky, kx = np.mgrid[0:rows, 0:cols]
    q = offset_to_axial(np.stack([kx, ky], -1), layout.odd_row_shift)[..., 0]
    q_min = int(q.min())
    real = np.zeros((rows + 2, int(q.max()) - q_min + 3), bool)
    real[ky + 1, q - q_min + 1] = True
    own = layout.from_axial(np.stack([q, ky], -1))  # each lens in the camera's numbering
    axial = np.full((rows, real.shape[1] - 2, 2), np.nan)
    axial[ky, q - q_min] = centres[own[..., 1], own[..., 0]]
    model = lattice_fit(axial)
    rr, qq = np.mgrid[-1:rows + 1, -1:real.shape[1] - 1]
    table = np.stack([qq, rr, np.ones_like(qq)], -1) @ model
    known = real & np.pad(np.isfinite(axial).all(-1), 1)
    table[known] = np.pad(axial, ((1, 1), (1, 1), (0, 0)))[known]
    return _AxialLenses(table, real, model, q_min)


def _nearest_axial(lenses: _AxialLenses, cols: np.ndarray, rows: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Flat index into ``lenses.table`` of the lens (or ring point) nearest each pixel
    ``(cols[None, :], rows[:, None])``, and whether a lens of the array is nearest.

    The pixel's fractional axial index on the fitted lattice falls in a rhombus of two
    near-equilateral triangles; the nearest lens is one of its four corners (exact for
    centres within 0.18 pitch of the lattice). Pixels more than a lattice step beyond
    the array are beyond it."""
    height, width = lenses.real.shape
    inv = np.linalg.inv(lenses.model[:2].T)
    dc, dr = cols[None, :] - lenses.model[2, 0], rows[:, None] - lenses.model[2, 1]
    q0 = np.floor(inv[0, 0] * dc + inv[0, 1] * dr).astype(np.intp)
    r0 = np.floor(inv[1, 0] * dc + inv[1, 1] * dr).astype(np.intp)
    qc, rc = np.clip(q0, -1, width - 3), np.clip(r0, -1, height - 3)
    base = (rc + 1) * width + (qc + 1)
    tx, ty = lenses.table[..., 0].ravel(), lenses.table[..., 1].ravel()
    best, choice = np.full(base.shape, np.inf), np.zeros(base.shape, np.intp)
    for step in (0, 1, width, width + 1):
        d2 = (tx[base + step] - cols[None, :]) ** 2 + (ty[base + step] - rows[:, None]) ** 2
        closer = d2 < best
        best = np.where(closer, d2, best)
        choice[closer] = step
    index = base + choice
    return index, lenses.real.ravel()[index] & (qc == q0) & (rc == r0)


def _hexagonal_cells(camera: Camera, centres: np.ndarray, clamp: bool
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pixel_lenses` of a hexagonal camera or its axial view: the nearest centre."""
    lenses = _axial_lenses(camera, centres)
    width, height = camera.pixels
    index = np.empty((height, width), np.intp)
    beyond = np.empty((height, width), bool)
    cols = np.arange(width, dtype=np.float64)
    for start in range(0, height, _CHUNK_ROWS):
        rows = np.arange(start, min(start + _CHUNK_ROWS, height), dtype=np.float64)
        index[start:start + len(rows)], lens = _nearest_axial(lenses, cols, rows)
        beyond[start:start + len(rows)] = ~lens
    if clamp and beyond.any():  # the nearest edge lens
        index[beyond] = _nearest_real(lenses, np.argwhere(beyond)[:, ::-1])
    r, q = np.divmod(index, lenses.real.shape[1])
    k = camera.layout.from_axial(np.stack([q - 1 + lenses.q_min, r - 1], -1))
    q, r = k[..., 0], k[..., 1]
    if not clamp:
        q[beyond], r[beyond] = -1, -1
    return q.astype(np.int32), r.astype(np.int32)


def _nearest_real(lenses: _AxialLenses, points: np.ndarray) -> np.ndarray:
    """Flat index into ``lenses.table`` of the lens nearest each ``(col, row)`` point."""
    index = np.flatnonzero(lenses.real)
    tree = cKDTree(lenses.table.reshape(-1, 2)[index])
    return index[tree.query(points.astype(np.float64))[1]]
