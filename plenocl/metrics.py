"""Reconstruction quality: Elsinga's Q, particle recovery, ghost intensity, and
sub-voxel particle positions from a volume (docs/design.md §6).

Distances are measured in voxels, with separate lateral (x, y) and depth (z)
tolerances because reconstructed particles are elongated along the line of sight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from .grid import Grid
from .peaks import find_particles


def quality_q(vol: np.ndarray, truth: np.ndarray) -> float:
    """Elsinga's reconstruction quality ``Q = Σ E·T / sqrt(Σ E² Σ T²)`` (1 is perfect)."""
    e, t = np.asarray(vol, np.float64), np.asarray(truth, np.float64)
    if e.shape != t.shape:
        raise ValueError(f"volume {e.shape} and truth {t.shape} must have the same shape")
    den = np.sqrt((e * e).sum() * (t * t).sum())
    return float((e * t).sum() / den) if den > 0 else 0.0


def render_particles(grid: Grid, positions, intensities=1.0, sigma_vox: float = 0.6
                     ) -> np.ndarray:
    """The true volume: Gaussian particles integrated over each voxel (erf), float32; each
    particle's voxels sum to its intensity (``plenocl.flows.render_particles`` in mm)."""
    from .flows import render_particles as render_voxels

    per_peak = np.asarray(intensities, float) / (2 * np.pi * sigma_vox**2) ** 1.5
    return render_voxels(grid.shape, grid.to_index(positions), per_peak, sigma_vox)


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
    found, true_idx, pairs = _matches(vol, grid, true_positions, threshold, lateral, depth)
    err = [found[f] - true_idx[t] for t, f in pairs]
    rms = float(np.sqrt(np.mean(np.sum(np.square(err), 1)))) if err else float("nan")
    return RecoveryReport(len(pairs), len(true_idx), len(found),
                          ghost_fraction(vol, true_idx), rms)


def matched_errors(vol: np.ndarray, grid: Grid, true_positions, threshold: float = 0.1,
                   lateral: float = 1.0, depth: float = 2.0) -> np.ndarray:
    """``(matched, 3)`` error of each recovered particle, its peak less its true position
    in voxels ``(x, y, z)``, matched as :func:`recovery` matches (lateral and depth
    errors separately: columns ``:2`` and ``2``)."""
    found, true_idx, pairs = _matches(vol, grid, true_positions, threshold, lateral, depth)
    return np.array([found[f] - true_idx[t] for t, f in pairs]).reshape(-1, 3)


def recovered_particles(vol: np.ndarray, grid: Grid, true_positions, threshold: float = 0.1,
                        lateral: float = 1.0, depth: float = 2.0) -> np.ndarray:
    """A bool per true particle: whether a peak recovers it, matched as :func:`recovery`
    matches (so its mean is :attr:`RecoveryReport.fraction`)."""
    _, true_idx, pairs = _matches(vol, grid, true_positions, threshold, lateral, depth)
    hit = np.zeros(len(true_idx), bool)
    hit[[t for t, _ in pairs]] = True
    return hit


def _matches(vol, grid: Grid, true_positions, threshold: float, lateral: float,
             depth: float):
    """The volume's peaks, the true particles' indices and their one-to-one matches."""
    true_idx = grid.to_index(true_positions)
    found, _ = find_particles(vol, threshold)
    return found, true_idx, match_particles(found, true_idx, lateral, depth)
