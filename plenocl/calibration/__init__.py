"""Microlens image centres from a white image (docs/design.md §3, paper §II.A).

A white image is taken with the main lens stopped down: every microlens images the
small aperture as a spot centred on its image centre ``c_k = x_k (1 + f_ml/d)``.
Calibration finds those spots to sub-pixel accuracy and matches each to its lens
``(kx, ky)``:

1. **Detect** spots: Gaussian-smoothed local maxima above a threshold relative to the
   brightest spot nearby (so vignetted, dim edges are kept and dead lenses are not
   filled with noise).
2. **Centroid** each spot: background-subtracted (the median of a ring between the
   spots), Gaussian-windowed and iterated to convergence; a symmetric spot then gives
   its centre without the bias a fixed box window has toward its own middle.
3. **Match** the spots to the lattice: pitch and rotation from nearest-neighbour
   vectors, the sub-pitch shift from the phase of the lattice coordinates, the
   whole-pitch shift from the extent of the array on the sensor.
4. **Fit** a global grid model (affine: pitch, rotation, shear, shift; optionally a
   cubic polynomial for distortion, chosen by an F-test; a hexagonal array's odd rows'
   own offset) to the matched centroids,
   robustly. Its prediction carries the information of all spots instead of one
   lens's few noisy photons, but a real array's lenses also sit off any lattice by
   manufacturing errors of a fraction of a pixel.
5. **Combine** the model and each lens's own centroid by their uncertainties
   (``method="combined"``, the default): each centroid's noise is measured from the
   image itself (the two checkerboard halves of a spot's pixels see independent noise),
   the lenses' true scatter about the lattice is what the centroids scatter beyond that
   noise, and each centre moves from the model toward its centroid by
   ``τ² / (τ² + σ_k²)``. ``method="fit"`` keeps the model only, ``method="centroid"``
   the raw centroids (the paper's method).

White images are taken as they come: negative pixels (read noise after a dark frame is
subtracted) are used as they are, the background is estimated locally (gradients,
stray light), hot pixels are removed, dim vignetted edges and saturated spots are kept.

Shifts of the array of up to half a microlens-image pitch are matched without
ambiguity; larger ones are resolved by the array's edge when it is visible on the
sensor. Rotations of a few degrees (any angle within ±45° in principle) are handled.

The package follows those steps: :mod:`.checks`, :mod:`.spots` (1-2), :mod:`.disks`
(full aperture), :mod:`.matching` (3), :mod:`.gridmodel` (4), :mod:`.fit` (5 and the
entry points), :mod:`.result` (:class:`CenterFit`) and :mod:`.diagnostics`.
"""

from .checks import NEGATIVE_WARN
from .diagnostics import save_diagnostic, save_failure_diagnostic
from .disks import APERTURES, DISK_WINDOW, FULL_APERTURE_FRACTION
from .fit import (
    DEVIATION_SIGNIFICANCE,
    IMPORT_TOLERANCE,
    METHODS,
    MIN_FOUND_FRACTION,
    MIN_INTERIOR,
    ON_LATTICE,
    PER_LENS_MIN_PITCH_PX,
    REGULAR_SHARE,
    REGULAR_SPREAD,
    calibrate,
    find_centers,
    import_centers,
    warn_about,
)
from .gridmodel import DISTORTION_MIN_PX, DISTORTION_P_VALUE
from .matching import PITCH_TOLERANCE
from .result import CenterFit
from .spots import DUPLICATE_RADIUS, RELATIVE_THRESHOLD, WINDOW_MIN_PX, WINDOW_SCALE

__all__ = [
    "APERTURES", "CenterFit", "DEVIATION_SIGNIFICANCE", "DISK_WINDOW",
    "DISTORTION_MIN_PX", "DISTORTION_P_VALUE", "DUPLICATE_RADIUS",
    "FULL_APERTURE_FRACTION", "IMPORT_TOLERANCE", "METHODS", "MIN_FOUND_FRACTION",
    "MIN_INTERIOR", "NEGATIVE_WARN", "ON_LATTICE", "PER_LENS_MIN_PITCH_PX",
    "PITCH_TOLERANCE", "REGULAR_SHARE", "REGULAR_SPREAD", "RELATIVE_THRESHOLD",
    "WINDOW_MIN_PX", "WINDOW_SCALE", "calibrate", "find_centers", "import_centers",
    "save_diagnostic", "save_failure_diagnostic", "warn_about",
]
