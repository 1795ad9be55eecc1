"""MART's blocks: interleaved groups of sub-aperture views, from the lens lattice."""

from __future__ import annotations

import weakref

import numpy as np
import pyopencl.array as cla

from ..camera.lattice import RectangularLattice
from ..opencl.arrays import upload
from ..optics.ownership import pixel_lenses
from .operator import ProjectionOperator


def view_blocks(camera, n_per_axis: int) -> np.ndarray:
    """Block id (int32) of every pixel: interleaved groups of sub-aperture views.

    A pixel's view is its offset (rounded, in pixels) from the image centre of the
    microlens it lies behind: the lens of its lattice cell
    (:func:`plenocl.optics.ownership.pixel_lenses`; beyond the array, the nearest edge
    lens; a lens without a calibrated centre counts at its fitted lattice position).
    A hexagonal array (or the projector's axial view of it, which MART gets) is taken
    on its axial lattice, where it is affine: the pixels' cells are the lenses'
    hexagons, the same for either camera.
    Views are grouped by ``(offset_x mod n, offset_y mod n)``.
    Vectorised over the sensor from the lattice fit; the NumPy reference
    (:func:`plenocl.reference.reconstruct.view_blocks`) searches the nearest centre per
    pixel instead, and agrees except at cell borders of perturbed rectangular arrays
    (a hexagonal array's cells are the nearest centre's: they agree).
    """
    camera = camera.on_lens_lattice()
    w, h = camera.pixels
    kx, ky = pixel_lenses(camera, clamp=True)
    centres = np.asarray(camera.microlens_centers, dtype=np.float64)
    fitted = RectangularLattice.fit(centres).positions()
    centres = np.where(np.isfinite(centres), centres, fitted)
    off_x = np.rint(np.arange(w)[None, :] - centres[..., 0][ky, kx]).astype(np.int64) % n_per_axis
    off_y = np.rint(np.arange(h)[:, None] - centres[..., 1][ky, kx]).astype(np.int64) % n_per_axis
    return (off_x + n_per_axis * off_y).astype(np.int32)


#: MART's device block ids per projector and block count, made once (a projector
#: reconstructing many images sets them up once).
_BLOCKS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def device_view_blocks(projector: ProjectionOperator, n_per_axis: int) -> cla.Array:
    """:func:`view_blocks` of the projector's camera on its queue, cached per projector."""
    per_projector = _BLOCKS.setdefault(projector, {})
    if n_per_axis not in per_projector:
        per_projector[n_per_axis] = upload(projector.queue,
                                           view_blocks(projector.camera, n_per_axis))
    return per_projector[n_per_axis]
