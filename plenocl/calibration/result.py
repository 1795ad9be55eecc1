"""What a calibration found: :class:`CenterFit`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera


@dataclass(frozen=True)
class CenterFit:
    """Everything calibration measured; :func:`calibrate` keeps only ``centers``.

    Attributes
    ----------
    centers
        ``(rows, cols, 2)`` microlens image centres as ``(col, row)`` pixels, ``NaN``
        where no spot was found (unless filled from the model).
    centroids
        ``(rows, cols, 2)`` raw spot centroids, ``NaN`` where no spot was found; at full
        aperture with ``method="combined"``, each lens's own disk fit
        (:func:`plenocl.lenscentres.fit_disks`), ``NaN`` where it has none.
    model
        ``(rows, cols, 2)`` grid-model prediction for every lens (at full aperture with
        ``method="combined"``: refitted to the per-lens disk fits).
    found
        ``(rows, cols)`` lenses with a matched spot.
    inlier
        ``(rows, cols)`` spots used in the model fit (found, not cut by the sensor
        edge, not an outlier).
    degree
        Polynomial degree of the grid model (1: affine, 3: cubic distortion).
    rotation_deg, pitch_px, shift_px
        Measured array rotation, image pitch along the array's ``(x, y)`` axes, and
        shift of the array's centre against the camera's nominal layout.
    residual_rms_px
        RMS distance of the inlier centroids from the model (their noise and the lenses'
        true offsets from the lattice).
    method
        ``"combined"``, ``"fit"`` or ``"centroid"``: where ``centers`` came from.
    noise_px
        ``(rows, cols)`` estimated centroid noise per axis (px), from the two
        checkerboard halves of each spot's pixels; at full aperture with
        ``method="combined"``, each disk fit's deviation (``NaN`` where none).
    lattice_scatter_px
        Estimated RMS per axis (px) of the lenses' true offsets from the grid model
        (manufacturing errors), the centroid noise taken out.
    aperture
        ``"stopped"`` (small spots) or ``"full"`` (disks filling the lenses): how the
        image was read.
    camera
        The camera the centres belong to: the one given, or a region of interest's
        (:meth:`plenocl.Camera.cropped`) with the lens count and odd-row shift its white
        image shows and its nominal array placed on the measured one
        (:func:`plenocl.calibration.fit.find_centers`).
    """

    centers: np.ndarray
    centroids: np.ndarray
    model: np.ndarray
    found: np.ndarray
    inlier: np.ndarray
    degree: int
    rotation_deg: float
    pitch_px: tuple[float, float]
    shift_px: tuple[float, float]
    residual_rms_px: float
    method: str
    noise_px: np.ndarray
    lattice_scatter_px: float
    aperture: str = "stopped"
    camera: Camera | None = None

    @property
    def n_missing(self) -> int:
        """Lenses without a spot."""
        return int((~self.found).sum())

    @property
    def n_outliers(self) -> int:
        """Found spots left out of the model fit (outliers or cut by the sensor edge)."""
        return int((self.found & ~self.inlier).sum())
