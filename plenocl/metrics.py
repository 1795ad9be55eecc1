"""Reconstruction quality: Elsinga's Q, particle recovery, ghost intensity, and
sub-voxel particle positions from a volume (DESIGN §6).

Distances are measured in voxels, with separate lateral (x, y) and depth (z)
tolerances because reconstructed particles are elongated along the line of sight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.special import erf

from .grid import Grid


def quality_q(vol: np.ndarray, truth: np.ndarray) -> float:
    """Elsinga's reconstruction quality ``Q = Σ E·T / sqrt(Σ E² Σ T²)`` (1 is perfect)."""
    e, t = np.asarray(vol, np.float64), np.asarray(truth, np.float64)
    if e.shape != t.shape:
        raise ValueError(f"volume {e.shape} and truth {t.shape} must have the same shape")
    den = np.sqrt((e * e).sum() * (t * t).sum())
    return float((e * t).sum() / den) if den > 0 else 0.0


def render_particles(grid: Grid, positions, intensities=1.0, sigma_vox: float = 0.6
                     ) -> np.ndarray:
    """The true volume: Gaussian particles integrated over each voxel (erf), float32."""
    idx = grid.to_index(positions)  # (ix, iy, iz) fractional
    inten = np.broadcast_to(np.asarray(intensities, float), (len(idx),))
    vol = np.zeros(grid.shape, np.float64)
    r = int(np.ceil(3 * sigma_vox)) + 1
    s = np.sqrt(2) * sigma_vox
    for p, w in zip(idx, inten):
        lo = np.floor(p).astype(int) - r + 1
        axes = [np.arange(lo[k], lo[k] + 2 * r) for k in range(3)]
        prof = [0.5 * (erf((a + 0.5 - p[k]) / s) - erf((a - 0.5 - p[k]) / s))
                for k, a in enumerate(axes)]
        block = w * prof[2][:, None, None] * prof[1][None, :, None] * prof[0][None, None, :]
        _add_clipped(vol, block, (lo[2], lo[1], lo[0]))
    return vol.astype(np.float32)


def _add_clipped(vol: np.ndarray, block: np.ndarray, origin) -> None:
    src, dst = [], []
    for n, o, b in zip(vol.shape, origin, block.shape):
        a0, a1 = max(o, 0), min(o + b, n)
        if a1 <= a0:
            return
        dst.append(slice(a0, a1))
        src.append(slice(a0 - o, a1 - o))
    vol[tuple(dst)] += block[tuple(src)]


def _fit3(m: np.ndarray, c: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Three-point Gaussian sub-voxel offset (parabolic where a value is not positive)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        lm, lc, lp = np.log(m), np.log(c), np.log(p)
        gauss = 0.5 * (lm - lp) / (lm - 2 * lc + lp)
        para = 0.5 * (m - p) / (m - 2 * c + p)
    ok = (m > 0) & (p > 0) & np.isfinite(gauss)
    off = np.where(ok, gauss, np.where(np.isfinite(para), para, 0.0))
    return np.clip(off, -0.5, 0.5)


def find_particles(vol: np.ndarray, threshold: float = 0.1, min_separation: int = 1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima above ``threshold · max`` with sub-voxel positions.

    Returns fractional voxel indices ``(N, 3)`` as ``(ix, iy, iz)`` and peak values,
    brightest first. Positions use a three-point Gaussian fit along each axis.
    """
    v = np.asarray(vol, np.float32)
    if v.ndim != 3:
        raise ValueError(f"expected a 3-D volume, got shape {v.shape}")
    vmax = float(v.max()) if v.size else 0.0
    if vmax <= 0:
        return np.zeros((0, 3)), np.zeros(0)
    size = 2 * min_separation + 1
    peaks = (v == ndimage.maximum_filter(v, size=size, mode="constant")) & (v > threshold * vmax)
    iz, iy, ix = np.nonzero(peaks)
    vals = v[iz, iy, ix]
    pad = np.pad(v, 1)
    pos = [ix, iy, iz]
    out = np.empty((len(vals), 3))
    for k, axis in enumerate((2, 1, 0)):
        step = [0, 0, 0]
        step[axis] = 1
        centre = (iz + 1, iy + 1, ix + 1)
        minus = pad[tuple(c - s for c, s in zip(centre, step))]
        plus = pad[tuple(c + s for c, s in zip(centre, step))]
        out[:, k] = pos[k] + _fit3(minus, vals, plus)
    order = np.argsort(-vals)
    return out[order], vals[order]


@dataclass(frozen=True)
class RecoveryReport:
    """Particle-level quality of a reconstruction."""

    recovered: int
    total: int
    found_peaks: int
    ghost_fraction: float
    position_rms_vox: float

    @property
    def fraction(self) -> float:
        """Fraction of true particles recovered."""
        return self.recovered / self.total if self.total else float("nan")


def _scaled(idx: np.ndarray, lateral: float, depth: float) -> np.ndarray:
    return np.asarray(idx, float) / np.array([lateral, lateral, depth])


def match_particles(found_idx, true_idx, lateral: float = 1.0, depth: float = 2.0
                    ) -> list[tuple[int, int]]:
    """One-to-one matches ``(true, found)`` within ``lateral`` voxels in x, y and
    ``depth`` voxels in z (an ellipsoid), minimising the total scaled distance."""
    f, t = _scaled(found_idx, lateral, depth), _scaled(true_idx, lateral, depth)
    if len(f) == 0 or len(t) == 0:
        return []
    d = np.linalg.norm(t[:, None, :] - f[None, :, :], axis=-1)
    cost = np.where(d <= 1.0, d, 1e6)
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if d[r, c] <= 1.0]


def ghost_fraction(vol: np.ndarray, true_idx, lateral: float = 2.0, depth: float = 4.0
                   ) -> float:
    """Fraction of reconstructed intensity farther than (``lateral``, ``depth``) voxels
    (an ellipsoid) from every true particle: intensity in ghosts."""
    v = np.asarray(vol, np.float64)
    total = v.sum()
    if total <= 0:
        return 0.0
    if len(true_idx) == 0:
        return 1.0
    iz, iy, ix = np.nonzero(v > 0)
    pts = _scaled(np.column_stack([ix, iy, iz]), lateral, depth)
    dist, _ = cKDTree(_scaled(true_idx, lateral, depth)).query(pts)
    return float(v[iz, iy, ix][dist > 1.0].sum() / total)


def recovery(vol: np.ndarray, grid: Grid, true_positions, threshold: float = 0.1,
             lateral: float = 1.0, depth: float = 2.0) -> RecoveryReport:
    """How many true particles (mm) a reconstructed volume recovers, and its ghosts.

    A true particle is recovered when a peak (above ``threshold · max``) lies within
    ``lateral`` voxels in x, y and ``depth`` voxels in z (one-to-one matching).
    """
    true_idx = grid.to_index(true_positions)
    found, _ = find_particles(vol, threshold)
    pairs = match_particles(found, true_idx, lateral, depth)
    err = [found[f] - true_idx[t] for t, f in pairs]
    rms = float(np.sqrt(np.mean(np.sum(np.square(err), 1)))) if err else float("nan")
    return RecoveryReport(len(pairs), len(true_idx), len(found),
                          ghost_fraction(vol, true_idx), rms)
