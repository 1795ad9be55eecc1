"""Particle tracks in 3-D, coloured by speed (m/s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_figure
from ..units import DT_RANGE_S
from .slices import widened

#: Tracks drawn at most (the longest first): more make a tangle.
MAX_TRACKS = 2000


def tracks_figure(path: str | Path, positions: np.ndarray, velocities: np.ndarray,
                  speed_unit: str = "m/s", max_tracks: int = MAX_TRACKS,
                  title: str | None = None) -> Path:
    """Tracks through their ``positions`` ``(n_tracks, n_frames, 3)`` mm (x, y, z; NaN
    where unseen), each segment coloured by the mean speed of its ends from
    ``velocities`` (same shape, in ``speed_unit``), with x, y and z labelled in mm and a
    colour bar; the ``max_tracks`` longest are drawn."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    positions, velocities = np.asarray(positions, float), np.asarray(velocities, float)
    seen = np.all(np.isfinite(positions), axis=2) & np.all(np.isfinite(velocities), axis=2)
    order = np.argsort(-seen.sum(axis=1), kind="stable")[:max_tracks]
    segments, speeds = [], []
    for k in order:
        pts, speed = positions[k][seen[k]], np.linalg.norm(velocities[k][seen[k]], axis=1)
        segments += [pts[i:i + 2] for i in range(len(pts) - 1)]
        speeds += list((speed[1:] + speed[:-1]) / 2)
    if not segments:
        raise ValueError("no track is seen in two frames: nothing to draw")
    plt = pyplot()
    fig = plt.figure(figsize=(7.2, 5.8))
    ax = fig.add_subplot(projection="3d")
    lines = Line3DCollection(segments, cmap="viridis", linewidths=1.1)
    lines.set_array(np.asarray(speeds))
    lines.set_clim(*widened(float(np.min(speeds)), float(np.max(speeds))))
    ax.add_collection3d(lines)
    every = np.concatenate(segments)
    lo, hi = every.min(axis=0), every.max(axis=0)
    for name, a, b in zip("xyz", lo, hi):
        getattr(ax, f"set_{name}lim")(a, b if b > a else a + 1)
        getattr(ax, f"set_{name}label")(f"{name} (mm)", labelpad=8, fontsize=8)
    ax.set_box_aspect([max(float(b - a), 1e-6) for a, b in zip(lo, hi)], zoom=0.85)
    ax.tick_params(labelsize=7)
    shown = "" if len(order) == len(positions) else f" (the {len(order)} longest shown)"
    ax.set_title(title or f"{len(positions)} tracks{shown}, coloured by speed", fontsize=9)
    fig.colorbar(lines, ax=ax, shrink=0.6, pad=0.12, label=f"speed ({speed_unit})")
    return save_figure(fig, path)


def tracks_with_speeds(tracks) -> tuple[np.ndarray, np.ndarray, str]:
    """Positions (mm), velocities and their unit of :class:`plenocl.Tracks`: m/s where its
    ``dt`` is a time in seconds (within :data:`plenocl.units.DT_RANGE_S`), else mm per
    unit of ``dt`` (``plenocl.track`` takes any: a frame count, say), as
    :meth:`plenocl.Tracks.save`'s ``seconds`` for the ``.vtu``."""
    lo, hi = DT_RANGE_S
    if lo <= float(tracks.dt) < hi:  # 1: a frame, as likely as a second
        return tracks.positions, tracks.velocities * 1e-3, "m/s"
    return tracks.positions, tracks.velocities, f"mm per dt of {float(tracks.dt):g}"


def plot_tracks(path: str | Path, tracks) -> Path:
    """:func:`tracks_figure` of :class:`plenocl.Tracks` (speeds in m/s where its ``dt``
    is in seconds: :func:`tracks_with_speeds`)."""
    positions, velocities, unit = tracks_with_speeds(tracks)
    return tracks_figure(path, positions, velocities, unit)
