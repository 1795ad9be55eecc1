"""A real calibrated microlens array on the projector's fast path (issue 46, item 5).

A real array is not a perfect lattice: plenoptomos' ``letters_ULF_M1_white.png``
(cicwi/plenoptomos, 27 x 20 lenses of 48 px), calibrated by ``plenocl calibrate``, has
rows turned 0.1322° and columns 0.0053° off square to them. :func:`replica_camera`
rebuilds that lattice (its fit, and its centroid scatter) so that the benchmark runs
without the image; :func:`agreement` says how far a projector's images lie from
another's, in the pixels users see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..camera.lattice import RectangularLattice
from ..grid import Grid
from ..optics.ownership import lens_owner

#: ``plenocl calibrate`` of plenoptomos' white image: ``centre(kx, ky) =
#: [kx, ky, 1] @ LETTERS_LATTICE`` in pixels, and the centroids' scatter about it.
LETTERS_LATTICE = np.array([[48.23439974, 0.11127139],
                            [-0.1068504, 48.23478689],
                            [7.00120564, 19.60155142]])
LETTERS_SCATTER_PX = 0.028


def nominal_camera() -> Camera:
    """That camera's nominal optics (plenoptomos' ``letters_ULF_M1.ini``: a 200 mm main
    lens of 6.6 mm aperture at unit magnification, 0.3 mm lenses of 18.6 mm focal length,
    6.45 µm pixels, the 1280 x 960 image): an ideal, axis-aligned lattice."""
    return Camera(200.0, 200.0 / 6.6, 1.0, 0.3, 18.6, (27, 20), 0.00645, (1280, 960))


def replica_camera(seed: int = 0) -> Camera:
    """:func:`nominal_camera` calibrated on :data:`LETTERS_LATTICE` with its scatter."""
    cam = nominal_camera()
    cols, rows = cam.ml_count
    ky, kx = np.mgrid[0:rows, 0:cols]
    centres = np.stack([kx, ky, np.ones_like(kx)], -1) @ LETTERS_LATTICE
    rng = np.random.default_rng(seed)
    return cam.with_centers(centres + rng.normal(0, LETTERS_SCATTER_PX, centres.shape))


def lens_centroid_shift(a: np.ndarray, b: np.ndarray, owner: np.ndarray) -> float:
    """Largest shift (pixels) between the light centroids of two images' lens images
    (``owner``: :func:`plenocl.optics.ownership.lens_owner`; the lenses holding at least
    1e-3 of ``b``'s brightest lens)."""
    inside = owner >= 0
    lens, rows, cols = owner[inside], *(c[inside] for c in np.indices(a.shape))

    def centroids(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = img[inside]
        light = np.bincount(lens, w)
        means = [np.bincount(lens, w * c) / np.where(light > 0, light, 1.0) for c in (rows, cols)]
        return light, np.stack(means)

    light, at_b = centroids(b)
    at_a = centroids(a)[1]
    lit = light > 1e-3 * light.max()
    return float(np.abs(at_a[:, lit] - at_b[:, lit]).max())


@dataclass(frozen=True)
class Agreement:
    """How two projections of the same volume differ: the largest pixel difference over
    the peak, the totals' relative difference, and the lens images' largest centroid
    shift (pixels)."""

    peak: float
    total: float
    centroid_px: float


def agreement(a: np.ndarray, b: np.ndarray, camera: Camera) -> Agreement:
    """:class:`Agreement` of image ``a`` against image ``b`` of ``camera``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return Agreement(float(np.abs(a - b).max() / np.abs(b).max()),
                     float(abs(a.sum() - b.sum()) / b.sum()),
                     lens_centroid_shift(a, b, lens_owner(camera)))


def sparse_volume(grid: Grid, count: int, seed: int) -> np.ndarray:
    """``count`` unit voxels at random places of ``grid`` (float32)."""
    rng = np.random.default_rng(seed)
    vol = np.zeros(grid.shape, np.float32)
    vol[tuple(rng.integers(0, s, count) for s in grid.shape)] = 1.0
    return vol


def skew_drift(camera: Camera) -> float:
    """Lens-index drift across the rows from the columns' skew (lenses): what the
    projector's ``shear_tol`` compares."""
    skew = RectangularLattice.fit(camera.microlens_centers).skew_deg
    return abs(math.tan(math.radians(skew))) * camera.ml_count[1]
