"""Step 4 (docs/design.md §3): the global grid model (affine, or cubic where an F-test
asks for it; a hexagonal array's odd rows' own offset) fitted robustly to the matched
centroids."""

from __future__ import annotations

import numpy as np
from scipy import stats

from ..camera import Camera, LensLayout

#: F-test p-value below which the cubic grid model replaces the affine one.
DISTORTION_P_VALUE = 1e-3

#: ... and must move the centres by more than this (px RMS).
DISTORTION_MIN_PX = 0.05


def _design(k: np.ndarray, shape: tuple[int, int], degree: int,
            layout: LensLayout) -> np.ndarray:
    """Polynomial terms of the normalised lens index, up to total ``degree``, and the
    ``layout``'s own terms (:meth:`~plenocl.camera.LensLayout.row_offset_terms`: a
    hexagonal array's odd rows' own offset from the even ones, which may sit off the
    camera file's half pitch, 0.46 pitch in issue 44 finding 3, and which no smooth
    function of the position represents)."""
    cols, rows = shape
    a = (k[:, 0] - (cols - 1) / 2) / max(1.0, (cols - 1) / 2)
    b = (k[:, 1] - (rows - 1) / 2) / max(1.0, (rows - 1) / 2)
    terms = [a**i * b**j for n in range(degree + 1) for j in range(n + 1) for i in [n - j]]
    return np.column_stack(terms + layout.row_offset_terms(k[:, 1]))


def _robust_fit(k, c, shape, degree, use, layout: LensLayout):
    """Least-squares polynomial fit with iterative outlier rejection; returns coef, use."""
    design = _design(k, shape, degree, layout)
    for _ in range(5):
        coef, *_ = np.linalg.lstsq(design[use], c[use], rcond=None)
        resid = np.hypot(*(design @ coef - c).T)
        sigma = float(np.median(resid[use])) / 1.1774  # Rayleigh median -> sigma
        new = use & (resid <= max(5 * sigma, 0.02))
        if np.array_equal(new, use) or new.sum() < design.shape[1] + 2:
            break
        use = new
    return coef, use


def _choose_degree(k, c, shape, use, degree, layout: LensLayout) -> int:
    """Affine unless ``degree`` says otherwise or, for ``"auto"``, a cubic model is both
    significantly better (F-test) and differs from the affine one by a relevant amount
    (a sub-pixel-phase bias of the centroids must not pass for distortion)."""
    if degree != "auto":
        if degree not in (1, 2, 3):
            raise ValueError(f"degree must be 1, 2, 3 or 'auto', got {degree!r}")
        return int(degree)
    p1, p3 = (2 * _design(k[:1], shape, d, layout).shape[1] for d in (1, 3))
    common = (_robust_fit(k, c, shape, 1, use, layout)[1]
              & _robust_fit(k, c, shape, 3, use, layout)[1])
    n = 2 * int(common.sum())
    if n <= 3 * p3:
        return 1
    rss, models = [], []
    for deg in (1, 3):
        design = _design(k, shape, deg, layout)
        coef, *_ = np.linalg.lstsq(design[common], c[common], rcond=None)
        rss.append(float(((design[common] @ coef - c[common]) ** 2).sum()))
        models.append(design @ coef)
    if rss[1] <= 0:
        return 1
    f_stat = (rss[0] - rss[1]) / (p3 - p1) / (rss[1] / (n - p3))
    effect = float(np.sqrt(np.mean(np.sum((models[1] - models[0]) ** 2, axis=1))))
    significant = stats.f.sf(f_stat, p3 - p1, n - p3) < DISTORTION_P_VALUE
    return 3 if significant and effect > DISTORTION_MIN_PX else 1


def grid_model(camera: Camera, c: np.ndarray, use: np.ndarray, degree):
    """The robust grid model of the centres ``c`` (``(rows·cols, 2)``, the lenses ``use``
    fitted): its degree, the lenses it kept and its ``(rows, cols, 2)`` prediction. A
    hexagonal array's model also fits its odd rows' offset (:func:`_design`)."""
    cols, rows = camera.ml_count
    kk = camera.lens_lattice_coords().reshape(-1, 2)  # affine in the lens positions
    layout = camera.layout
    deg = _choose_degree(kk, c, (cols, rows), use, degree, layout)
    coef, use = _robust_fit(kk, c, (cols, rows), deg, use, layout)
    return deg, use, (_design(kk, (cols, rows), deg, layout) @ coef).reshape(rows, cols, 2)
