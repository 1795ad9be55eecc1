"""NumPy references of the multiplicative solvers (``plenocl.reconstruct``), on an
explicit weight matrix ``W`` (pixels x voxels; dense or ``scipy.sparse``).

Written for clarity; they double as the ``scipy.sparse`` baseline in the benchmarks.
Every update keeps voxels non-negative and finite:
the ratio ``I / max(P, eps)`` is clamped to ``[RATIO_MIN, RATIO_MAX]``; the
geometric-mean methods take an optional larger floor ``ratio_floor`` under the ratio
whose log they use.
"""

from __future__ import annotations

import numpy as np

EPS = 1e-12
RATIO_MIN, RATIO_MAX = 1e-6, 1e6
EXP_CLAMP = 30.0


def ratio(image: np.ndarray, proj: np.ndarray, threshold: float = 0.0,
          observed: np.ndarray | None = None) -> np.ndarray:
    """``I / max(P, eps)`` clamped; pixels at or below ``threshold`` count as dark (0);
    pixels without data (``observed`` False) are ``NaN``: the updates leave them out."""
    img = np.where(image > threshold, image, 0.0)
    r = np.clip(img / np.maximum(proj, EPS), 0.0, RATIO_MAX)
    return r if observed is None else np.where(observed, r, np.nan)


def sensitivity(W, observed: np.ndarray | None = None) -> np.ndarray:
    """``s_j = Σ_i w_ij``: the fraction of voxel j's light that reaches the sensor (its
    pixels with data, when ``observed`` is given)."""
    if observed is None:
        return np.asarray(W.sum(axis=0)).ravel()
    return np.asarray(W.T @ np.asarray(observed, np.float64)).ravel()


def mlem(W, image, iterations: int, relax: float = 1.0, start=None, threshold: float = 0.0,
         observed: np.ndarray | None = None):
    """Multiplicative EM: ``E ← E (Wᵀ r / s)^μ``, the arithmetic mean of the ratios
    (``observed``: bool per pixel, False where the image holds no data)."""
    img = np.asarray(image, np.float64).ravel()
    obs = None if observed is None else np.asarray(observed, bool).ravel()
    s = sensitivity(W, obs)
    e = _start(W, img, start, obs)
    for _ in range(iterations):
        b = W.T @ np.nan_to_num(ratio(img, W @ e, threshold, obs), nan=0.0)
        e = np.where(s > 0, e * np.power(np.maximum(b, 0) / np.maximum(s, EPS), relax), 0.0)
    return e


def smart(W, image, iterations: int, relax: float = 1.0, start=None, threshold: float = 0.0,
          ratio_floor: float = RATIO_MIN, observed: np.ndarray | None = None):
    """Simultaneous MART: ``E ← E exp(μ Wᵀ log r / s)``, the geometric mean of the ratios
    (``observed`` as in :func:`mlem`: log r = 0 where the image holds no data)."""
    img = np.asarray(image, np.float64).ravel()
    obs = None if observed is None else np.asarray(observed, bool).ravel()
    s = sensitivity(W, obs)
    e = _start(W, img, start, obs)
    for _ in range(iterations):
        r = ratio(img, W @ e, threshold, obs)
        logr = np.where(np.isnan(r), 0.0, np.log(np.maximum(np.nan_to_num(r, nan=1.0),
                                                            max(ratio_floor, RATIO_MIN))))
        expo = np.clip(relax * (W.T @ logr) / np.maximum(s, EPS), -EXP_CLAMP, EXP_CLAMP)
        e = np.where(s > 0, e * np.exp(expo), 0.0)
    return e


def mart_sequential(W, image, iterations: int, relax: float = 1.0, start=None,
                    threshold: float = 0.0):
    """The paper's MART, one pixel at a time: ``E_j ← E_j (I_i / Σ_j w_ij E_j)^(μ w_ij)``."""
    Wd = np.asarray(W.todense() if hasattr(W, "todense") else W, np.float64)
    img = np.asarray(image, np.float64).ravel()
    e = _start(Wd, img, start)
    for _ in range(iterations):
        for i in np.nonzero(Wd.sum(axis=1) > 0)[0]:
            row = Wd[i]
            r = ratio(img[i:i + 1], row @ e, threshold)[0]
            e = e * np.power(max(r, RATIO_MIN), relax * row)
    return e


def mart_blocks(W, image, blocks: list[np.ndarray], iterations: int, relax: float = 1.0,
                start=None, threshold: float = 0.0, ratio_floor: float = RATIO_MIN):
    """Block-sequential MART: for each block of pixels ``b``,
    ``E_j ← E_j Π_{i∈b} r_i^(μ w_ij) = E_j exp(μ Σ_{i∈b} w_ij log r_i)``."""
    img = np.asarray(image, np.float64).ravel()
    e = _start(W, img, start)
    for _ in range(iterations):
        for pix in blocks:
            logr = np.log(np.maximum(ratio(img, W @ e, threshold), max(ratio_floor, RATIO_MIN)))
            masked = np.zeros_like(logr)
            masked[pix] = logr[pix]
            e = e * np.exp(np.clip(relax * (W.T @ masked), -EXP_CLAMP, EXP_CLAMP))
    return e


def _start(W, img: np.ndarray, start, observed: np.ndarray | None = None) -> np.ndarray:
    """A uniform start scaled so that the first projection carries the image's intensity
    (onto the pixels with data, when ``observed`` is given)."""
    if start is not None:
        return np.asarray(start, np.float64).ravel().copy()
    total = float(sensitivity(W, observed).sum())
    if observed is not None:
        img = np.where(observed, img, 0.0)
    return np.full(W.shape[1], img.sum() / max(total, EPS))


def view_blocks(camera, n_per_axis: int) -> np.ndarray:
    """MART's block id per pixel, literally: the offset (rounded, in pixels) from the
    nearest calibrated microlens image centre, ``(offset_x mod n) + n (offset_y mod n)``."""
    from scipy.spatial import cKDTree

    w, h = camera.pixels
    centres = camera.microlens_centers.reshape(-1, 2)
    centres = centres[np.all(np.isfinite(centres), axis=1)]
    rows, cols = np.mgrid[0:h, 0:w]
    pix = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
    _, k = cKDTree(centres).query(pix)
    off = np.rint(pix - centres[k]).astype(int) % n_per_axis
    return (off[:, 0] + n_per_axis * off[:, 1]).astype(np.int32).reshape(h, w)
