"""Derivatives of a PIV field on its vector grid for display: vorticity whose
smoothing the field's resolution supports.

A PIV vector is the mean over its window; vectors closer than the window (overlap)
are not independent, so a central difference of neighbours amplifies their noise
without adding resolution. The least-squares stencil (Raffel et al., *Particle Image
Velocimetry*, §10.3) ``(2 f[i+2] + f[i+1] - f[i-1] - 2 f[i-2]) / (10 h)`` spans
``±2`` vectors, about the window at 50-75 % overlap, and is exact for a linear
field. Where that stencil reaches an invalid vector or the edge, the central
difference is used, then a one-sided difference of the next vector (first order: on
independent noise of variance s² it passes 2 s²/h², a one-sided second-order stencil
6.5 s²/h², the least-squares one 0.1 s²/h²); where no stencil is whole the derivative
is NaN (not drawn), never made up from invalid neighbours.
"""

from __future__ import annotations

import numpy as np


def _shift(f: np.ndarray, k: int, axis: int) -> np.ndarray:
    """``g[i] = f[i + k]`` along ``axis``, NaN beyond the ends."""
    out = np.full(f.shape, np.nan)
    n = f.shape[axis]
    if abs(k) >= n:
        return out
    dst, src = [slice(None)] * f.ndim, [slice(None)] * f.ndim
    dst[axis], src[axis] = (slice(0, n - k), slice(k, n)) if k >= 0 else (slice(-k, n),
                                                                          slice(0, n + k))
    out[tuple(dst)] = f[tuple(src)]
    return out


def derivative(f: np.ndarray, spacing: float, axis: int) -> np.ndarray:
    """``df/dx`` along ``axis`` of ``f`` (NaN where invalid) on a uniform grid of
    ``spacing``: the least-squares stencil, else central, else one-sided (module notes);
    NaN where ``f`` is NaN or no stencil is whole; zero along an axis of one node."""
    f = np.asarray(f, float)
    if f.shape[axis] < 2:
        return np.where(np.isfinite(f), 0.0, np.nan)
    s = {k: _shift(f, k, axis) for k in (-2, -1, 1, 2)}
    h = float(spacing)
    candidates = (
        (2 * s[2] + s[1] - s[-1] - 2 * s[-2]) / (10 * h),
        (s[1] - s[-1]) / (2 * h),
        (s[1] - f) / h,
        (f - s[-1]) / h,
    )
    out = np.full(f.shape, np.nan)
    for cand in candidates:
        out = np.where(np.isfinite(out), out, cand)
    return np.where(np.isfinite(f), out, np.nan)


def grid_spacing(coord: np.ndarray) -> float:
    """The (uniform) step of a 1-D coordinate; 1 for a single node."""
    coord = np.asarray(coord, float)
    return float(coord[1] - coord[0]) if len(coord) > 1 else 1.0


def vorticity(velocity: np.ndarray, valid: np.ndarray, x, y, z,
              scale: float = 1e3) -> np.ndarray:
    """Vorticity ``(3, nz, ny, nx)`` (x, y, z components) of a field ``(3, nz, ny, nx)``
    on coordinates ``x, y, z`` (mm), NaN where the stencils reach no valid vector.

    ``scale`` turns velocity per mm into the result's unit: ``1e3`` for m/s over mm
    gives 1/s.
    """
    vel = np.where(valid, np.asarray(velocity, float), np.nan)
    steps = {0: grid_spacing(z), 1: grid_spacing(y), 2: grid_spacing(x)}  # array axes

    def d(comp: int, axis: int) -> np.ndarray:
        return derivative(vel[comp], steps[axis], axis) * scale

    wx = d(2, 1) - d(1, 0)   # dw/dy - dv/dz
    wy = d(0, 0) - d(2, 2)   # du/dz - dw/dx
    wz = d(1, 2) - d(0, 1)   # dv/dx - du/dy
    return np.stack([wx, wy, wz])


def vorticity_magnitude(velocity: np.ndarray, valid: np.ndarray, x, y, z,
                        scale: float = 1e3) -> np.ndarray:
    """``|ω|`` (1/s for m/s on mm) of :func:`vorticity`."""
    return np.sqrt(np.sum(vorticity(velocity, valid, x, y, z, scale) ** 2, axis=0))
