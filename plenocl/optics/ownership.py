"""Which microlens a sensor pixel lies behind: one rule for every stage.

A pixel belongs to the lens whose lattice cell (one image pitch around the lens's centre
on the lattice fitted to the calibrated image centres, :class:`RectangularLattice`, so a
rotated or sheared array is handled) contains the pixel's centre. The light field
(:func:`lens_owner`: ``-1`` beyond the array) and MART's view blocks
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

import numpy as np

from ..camera import Camera
from .lattice import RectangularLattice

__all__ = ["lens_owner", "pixel_lenses"]


def pixel_lenses(camera: Camera, centres: np.ndarray | None = None, clamp: bool = False
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Lens index ``(kx, ky)``, ``(H, W)`` int32 each, of the lattice cell holding each pixel.

    Parameters
    ----------
    camera
        The camera (sensor size; its microlens centres unless ``centres`` is given).
    centres
        Optional ``(rows, cols, 2)`` image centres (pixels) to use instead of the camera's.
    clamp
        Give pixels beyond the array the nearest edge lens; otherwise their indices lie
        outside ``[0, cols) x [0, rows)``.
    """
    camera.require_rectangular("the pixels' lens cells")
    centres = camera.microlens_centers if centres is None else centres
    lattice = RectangularLattice.fit(centres)
    kx, ky = lattice.cells(*camera.pixels)
    if clamp:
        rows, cols = lattice.shape
        np.clip(kx, 0, cols - 1, out=kx)
        np.clip(ky, 0, rows - 1, out=ky)
    return kx, ky


def lens_owner(camera: Camera, centres: np.ndarray | None = None) -> np.ndarray:
    """Flat index ``ky * cols + kx`` of the microlens each pixel lies behind, ``(H, W)``
    int32; ``-1`` outside the array (:func:`pixel_lenses`)."""
    cols, rows = camera.ml_count
    kx, ky = pixel_lenses(camera, centres)
    inside = (kx >= 0) & (kx < cols) & (ky >= 0) & (ky < rows)
    return np.where(inside, ky * cols + kx, -1).astype(np.int32)
