"""The tracks of a time-resolved recording (docs/design.md §7.3)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_path
from ..io.npzfile import open_npz
from ..io.polylines import write_vtu
from .smoothing import TrackFit, smooth

#: What a tracks file says it is (``.npz``), and its layout's version.
FORMAT = "plenocl-tracks-1"


@dataclass(frozen=True)
class Tracks:
    """Particles followed through the frames of one camera.

    Every array is ``(n_tracks, n_frames, ...)`` and NaN where a track has no particle.
    Positions are object-space millimetres as ``(x, y, z)``; velocities are mm per unit
    of ``dt`` (mm/s for ``dt`` in seconds), accelerations mm per unit of ``dt`` squared.

    Attributes
    ----------
    positions
        The smoothed positions (:func:`plenocl.pipeline.smooth_tracks` in
        :func:`plenocl.track`; local polynomial fits in :meth:`from_measured`).
    measured
        The positions each frame's fit to its raw image gave.
    measured_sigma
        Their standard deviations (the fit's posterior).
    intensities
        Each particle's intensity (image units), ``(n_tracks, n_frames)``.
    velocities, accelerations
        The smoother's first and second derivatives (NaN where the track is too
        short).
    position_sigma, velocity_sigma, acceleration_sigma
        Their standard deviations.
    dt
        The time between frames.
    dropped
        The particles :func:`plenocl.track`'s fits to the raw images dropped, over every
        frame and refit (their fit left the grid or was not finite; docs/design.md
        §7.2): a track misses the frame where its particle was dropped.
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
    dropped: int = 0

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

    def save(self, path, record: dict | None = None, seconds: bool = False,
             frames=None) -> Path:
        """Write the tracks: ``.npz`` (every array and ``dt``, read back by :meth:`load`,
        and ``record``, JSON-ready, what made them: :meth:`record_of`) or ``.vtu``
        (poly-lines for ParaView: each track through its smoothed positions, with its
        velocity, speed, frame and track number per point; tracks with fewer than two
        positions are left out). Written atomically. ``.vtu`` with ``seconds`` (``dt`` in
        seconds, as a batch's): ``velocity_m_per_s`` and ``speed_m_per_s`` in m/s, the
        unit of every other product of a run; without it ``velocity`` and ``speed`` in mm
        per unit of ``dt``, as the tracks hold them. ``frames``: the frames' numbers (a
        run's, as its store's ``frame`` coordinate), which ``.vtu``'s ``frame`` then
        holds instead of the index from 0."""
        path = Path(path)
        if path.suffix == ".npz":
            extra = {} if record is None else {"record": np.asarray(json.dumps(record))}
            with atomic_path(path) as tmp:
                with open(tmp, "wb") as handle:
                    np.savez_compressed(handle, format=FORMAT, dt=self.dt,
                                        dropped=self.dropped, **extra,
                                        **{name: getattr(self, name) for name in _PER_TRACK})
        elif path.suffix == ".vtu":
            lines, data = self._lines(frames)
            for name in ("velocity", "speed") if seconds else ():  # mm/s to m/s
                data[f"{name}_m_per_s"] = [v * 1e-3 for v in data.pop(name)]
            write_vtu(path, lines, data)
        else:
            raise ValueError(f"tracks are written as .npz or .vtu (ParaView), not {path.name!r}")
        return path

    @classmethod
    def load(cls, path) -> Tracks:
        """Tracks written by :meth:`save` as ``.npz``."""
        with open_npz(path, "tracks (Tracks.save)") as data:
            if "format" not in data.files or str(data["format"]) != FORMAT:
                raise ValueError(f"{path} is not a plenocl tracks file (written by "
                                 "Tracks.save(... .npz))")
            dropped = int(data["dropped"]) if "dropped" in data.files else 0  # older files
            return cls(*(data[name] for name in _PER_TRACK), dt=float(data["dt"]),
                       dropped=dropped)

    @staticmethod
    def record_of(path) -> dict:
        """The ``record`` a ``.npz`` of :meth:`save` was written with (``{}``: none)."""
        with open_npz(path, "tracks (Tracks.save)") as data:
            return json.loads(str(data["record"])) if "record" in data.files else {}

    def _lines(self, frames=None) -> tuple[list[np.ndarray], dict[str, list[np.ndarray]]]:
        """Each track's smoothed positions as a line and its per-point arrays (``frame``:
        ``frames[k]`` of frame index ``k``, the index itself without ``frames``)."""
        count = self.positions.shape[1]
        number_of = (np.arange(count, dtype=float) if frames is None
                     else np.asarray(frames, float).reshape(-1))
        if len(number_of) != count:
            raise ValueError(f"frames names {len(number_of)} frame number(s) for tracks of "
                             f"{count} frames")
        lines, data = [], {"velocity": [], "speed": [], "frame": [], "track": []}
        for number, (pos, vel) in enumerate(zip(self.positions, self.velocities)):
            here = np.flatnonzero(np.all(np.isfinite(pos), axis=1))
            if len(here) < 2:
                continue
            lines.append(pos[here])
            data["velocity"].append(np.nan_to_num(vel[here]))
            data["speed"].append(np.linalg.norm(np.nan_to_num(vel[here]), axis=1))
            data["frame"].append(number_of[here])
            data["track"].append(np.full(len(here), float(number)))
        return lines, data

    def longer_than(self, frames: int) -> Tracks:
        """The tracks seen in at least ``frames`` frames."""
        keep = self.lengths >= frames
        return Tracks(*(getattr(self, name)[keep] for name in _PER_TRACK), dt=self.dt,
                      dropped=self.dropped)


_PER_TRACK = ("positions", "measured", "measured_sigma", "intensities", "velocities",
              "accelerations", "position_sigma", "velocity_sigma", "acceleration_sigma")
