"""The tracks of a time-resolved recording (docs/design.md §7.3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .smoothing import TrackFit, smooth


@dataclass(frozen=True)
class Tracks:
    """Particles followed through the frames of one camera.

    Every array is ``(n_tracks, n_frames, ...)`` and NaN where a track has no particle.
    Positions are object-space millimetres as ``(x, y, z)``; velocities are mm per unit
    of ``dt`` (mm/s for ``dt`` in seconds), accelerations mm per unit of ``dt`` squared.

    Attributes
    ----------
    positions
        The smoothed positions: each a local polynomial fit along its track.
    measured
        The positions each frame's fit to its raw image gave.
    measured_sigma
        Their standard deviations (the fit's posterior).
    intensities
        Each particle's intensity (image units), ``(n_tracks, n_frames)``.
    velocities, accelerations
        The fit's first and second derivative (NaN where the track is too short).
    position_sigma, velocity_sigma, acceleration_sigma
        Their standard deviations.
    dt
        The time between frames.
    """

    positions: np.ndarray
    measured: np.ndarray
    measured_sigma: np.ndarray
    intensities: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray
    position_sigma: np.ndarray
    velocity_sigma: np.ndarray
    acceleration_sigma: np.ndarray
    dt: float

    @classmethod
    def from_measured(cls, measured: np.ndarray, sigma: np.ndarray,
                      intensities: np.ndarray, dt: float, window: int = 7,
                      degree: int = 2) -> Tracks:
        """Tracks from their measured positions and standard deviations, smoothed by
        :func:`plenocl.ptv.smooth` (``window`` frames, polynomials of ``degree``)."""
        fit: TrackFit = smooth(measured, sigma, dt, window, degree)
        return cls(fit.positions, measured, sigma, intensities, fit.velocities,
                   fit.accelerations, fit.position_sigma, fit.velocity_sigma,
                   fit.acceleration_sigma, float(dt))

    @property
    def lengths(self) -> np.ndarray:
        """The frames each track has a particle in, ``(n_tracks,)``."""
        return np.all(np.isfinite(self.measured), axis=2).sum(axis=1)

    def displacements(self) -> np.ndarray:
        """The smoothed positions' steps from each frame to the next,
        ``(n_tracks, n_frames - 1, 3)`` mm (NaN where either end is missing)."""
        return np.diff(self.positions, axis=1)

    def longer_than(self, frames: int) -> Tracks:
        """The tracks seen in at least ``frames`` frames."""
        keep = self.lengths >= frames
        return Tracks(*(getattr(self, name)[keep] for name in _PER_TRACK), dt=self.dt)


_PER_TRACK = ("positions", "measured", "measured_sigma", "intensities", "velocities",
              "accelerations", "position_sigma", "velocity_sigma", "acceleration_sigma")
