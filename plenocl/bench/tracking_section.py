"""Time series with known particles and the errors of their tracks (issue 30):
what ``benchmarks/tracking.py`` prints and the tracking tests check.

A series holds ``frames`` raw images of particles moved by a :class:`Motion` at every
frame (uniform: its shift per frame; rotation: its angle per frame about the grid's
lateral x axis), ray traced exactly with 0.8 px blur, photon and read noise, as
:func:`plenocl.bench.accuracy_section.budget_scene` does for a pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..grid import Grid
from ..particles import random_particles
from ..ptv import Tracks
from ..simulate import simulate_image
from .accuracy_section import Motion

#: A match between a track and a true particle: mean distance per frame within these
#: (x, y, z voxels), as the pairs of the pair chain.
MATCH = (1.0, 1.0, 3.0)
#: Tracks evaluated: those seen in at least this many frames (issue 30).
MIN_FRAMES = 4
#: The focal zone reported apart: ``|z|`` below this (mm) at the step's midpoint.
FOCAL_ZONE_MM = 2.0


@dataclass(frozen=True)
class Series:
    """A simulated recording: true positions ``(n, frames, 3)`` mm and the raw images."""

    truth: np.ndarray
    frames: list


def simulate_series(cam: Camera, grid: Grid, ppm: float, frames: int, seed: int, queue,
                    motion: Motion, rays: int = 2000) -> Series:
    """``frames`` images of particles at ``ppm`` per microlens, centred in time on the
    positions drawn (so the series stays inside the volume as the pair scenes do)."""
    box = tuple((lo + 0.3, hi - 0.3) for lo, hi in (grid.x, grid.y, grid.z))
    count = max(2, int(round(ppm * cam.ml_count[0] * cam.ml_count[1])))
    pos, inten = random_particles(box, count=count, seed=seed, intensity=2e4)
    mid = (frames - 1) / 2
    truth = np.stack([motion.moved(pos, k - mid) for k in range(frames)], axis=1)
    kw = dict(rays_per_particle=rays, blur_px=0.8, photon_noise=True, background=20.0,
              read_noise=3.0, queue=queue)
    images = [simulate_image(cam, truth[:, k], inten, seed=seed * 100 + k, **kw)
              for k in range(frames)]
    return Series(truth, images)


def match_tracks(tracks: Tracks, truth: np.ndarray, grid: Grid) -> np.ndarray:
    """The true particle of each track (``-1``: a ghost track), one to one: the closest
    by mean scaled distance over the track's frames, within :data:`MATCH`."""
    voxel = np.asarray(grid.spacing[::-1]) * np.asarray(MATCH)
    seen = np.isfinite(tracks.measured[..., 0])
    out = np.full(len(tracks.measured), -1)
    cost = np.full((len(tracks.measured), len(truth)), np.inf)
    for i, (pos, mask) in enumerate(zip(tracks.measured, seen)):
        d = np.linalg.norm((truth[:, mask] - pos[mask]) / voxel, axis=2).mean(axis=1)
        cost[i] = np.where(d <= 1.0, d, np.inf)
    taken = np.zeros(len(truth), bool)
    for i in np.argsort(cost.min(axis=1)):  # the best-matched tracks choose first
        free = np.flatnonzero(np.isfinite(cost[i]) & ~taken)
        if len(free):
            out[i] = free[np.argmin(cost[i, free])]
            taken[out[i]] = True
    return out


def track_errors(tracks: Tracks, truth: np.ndarray, grid: Grid, seconds: float) -> dict:
    """Per-step displacement errors (voxels) of the tracks seen in :data:`MIN_FRAMES`
    frames against the truth: smoothed and as measured, lateral (RMS over x and y) and
    depth, the focal zone's depth apart; the share of true particles tracked, ghost
    tracks, and seconds per frame."""
    long = tracks.longer_than(MIN_FRAMES)
    owner = match_tracks(long, truth, grid)
    real = owner >= 0
    voxel = np.asarray(grid.spacing[::-1])
    true_steps = np.diff(truth[owner[real]], axis=1) / voxel
    mid_z = (truth[owner[real], 1:, 2] + truth[owner[real], :-1, 2]) / 2
    stay = _frames_inside(truth, grid) >= MIN_FRAMES
    out = {"tracked": float(np.isin(np.flatnonzero(stay), owner[real]).mean()),
           "ghosts": float((~real).mean()) if len(real) else 0.0,
           "tracks": int(len(real)), "seconds_per_frame": seconds / truth.shape[1]}
    for name, pos in (("smoothed", long.positions), ("measured", long.measured)):
        err = np.diff(pos[real], axis=1) / voxel - true_steps
        ok = np.all(np.isfinite(err), axis=2)
        focal = ok & (np.abs(mid_z) < FOCAL_ZONE_MM)
        out[name] = {"lateral": _rms(err[ok][:, :2]), "depth": _rms(err[ok][:, 2]),
                     "focal_depth": _rms(err[focal][:, 2]), "steps": int(ok.sum())}
    return out


def _frames_inside(truth: np.ndarray, grid: Grid) -> np.ndarray:
    """How many frames each true particle spends inside the grid."""
    n, f, _ = truth.shape
    index = grid.to_index(truth.reshape(-1, 3)).reshape(n, f, 3)
    limit = np.asarray(grid.shape[::-1]) - 0.5
    return np.all((index >= -0.5) & (index <= limit), axis=2).sum(axis=1)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")
