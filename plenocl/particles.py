"""Synthetic particle fields: positions and intensities with a given seeding density."""

from __future__ import annotations

import numpy as np

from .options import is_integer


def random_particles(
    box_mm: tuple[tuple[float, float], tuple[float, float], tuple[float, float]],
    count: int | None = None,
    density_per_mm3: float | None = None,
    seed: int = 0,
    intensity: float | tuple[float, float] = 1000.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Particles uniformly distributed in a box.

    Parameters
    ----------
    box_mm
        ``((x0, x1), (y0, y1), (z0, z1))`` in mm (a :class:`~plenocl.Grid`'s extents).
    count, density_per_mm3
        Give exactly one: the number of particles, or a density (particles per mm³).
    seed
        Seed of NumPy's generator.
    intensity
        Counts per particle, or ``(low, high)`` for uniformly random intensities.

    Returns
    -------
    positions : (N, 3) float64 array of ``(x, y, z)`` mm
    intensities : (N,) float64 array
    """
    lo, hi = (np.array([b[i] for b in box_mm], dtype=float) for i in (0, 1))
    if lo.shape != (3,) or np.any(~np.isfinite(lo)) or np.any(hi <= lo):
        raise ValueError(f"box_mm must be ((x0,x1),(y0,y1),(z0,z1)) with lo < hi, got {box_mm}")
    if (count is None) == (density_per_mm3 is None):
        raise ValueError("give exactly one of count or density_per_mm3")
    if count is None:
        if not density_per_mm3 >= 0:
            raise ValueError(f"density_per_mm3 must be >= 0, got {density_per_mm3}")
        count = int(round(density_per_mm3 * float(np.prod(hi - lo))))
    if not is_integer(count) or count < 0:
        raise ValueError(f"count must be a whole number >= 0, got {count!r}")
    if not np.all(np.isfinite(hi)):
        raise ValueError(f"box_mm must be finite, got {box_mm}")
    if not (is_integer(seed) and seed >= 0):
        raise ValueError(f"seed must be a whole number >= 0, got {seed!r}")
    rng = np.random.default_rng(seed)
    positions = lo + rng.random((int(count), 3)) * (hi - lo)
    if np.ndim(intensity) == 0:
        intens = np.full(int(count), float(intensity))
    else:
        low, high = (float(v) for v in intensity)
        if not (np.isfinite(low) and np.isfinite(high) and 0 <= low <= high):
            raise ValueError(f"intensity (low, high) must be finite, 0 <= low <= high, got "
                             f"{intensity!r}")
        intens = rng.uniform(low, high, int(count))
    return positions, intens


def particles_per_microlens(count: int, camera) -> float:
    """Seeding density as the imaging community quotes it: particles per microlens."""
    return count / float(np.prod(camera.ml_count))
