"""A tracking run's store, ``tracks.zarr``: the tracks and their binned field as named
arrays that ``xarray.open_zarr`` reads (docs/batch.md), written whole or not at all
(:func:`plenocl.io.zarrstore.write_store`).

- coordinates ``track``, ``frame`` (the frames' numbers), ``time`` (s from the first
  frame, along ``frame``), ``axis`` (``"x"``, ``"y"``, ``"z"``);
- per track and frame, NaN where the track has no particle: ``position`` (mm, smoothed),
  ``position_sigma``, ``measured`` and ``measured_sigma`` (mm, the fits'), ``velocity``
  and ``velocity_sigma`` (m/s), ``acceleration`` and ``acceleration_sigma`` (m/s²),
  shaped ``(track, frame, axis)``; ``intensity`` ``(track, frame)``; ``length``, the
  frames each track is seen in, ``(track,)``;
- the binned field on the windows' centres ``z``, ``y``, ``x`` (mm), one per
  ``field_time`` (s, the middle of the steps it pools; ``field_first_frame`` and
  ``field_last_frame`` give its frames, by number): ``u``, ``v``, ``w`` (m/s), their standard
  uncertainties ``u_sigma``, ``v_sigma``, ``w_sigma``, ``valid`` and ``outlier``,
  shaped ``(field_time, z, y, x)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..grid import Grid
from ..io.zarrstore import Variable, write_store
from ..ptv import Tracks
from ..vectorfield import PIVResult, field_arrays, grid_geometry

#: Tracks' per-frame vectors in the store: name, Tracks attribute, unit, scale from
#: the tracks' mm (per second) to the unit.
VECTORS = (("position", "positions", "mm", 1.0), ("position_sigma", "position_sigma", "mm", 1.0),
           ("measured", "measured", "mm", 1.0), ("measured_sigma", "measured_sigma", "mm", 1.0),
           ("velocity", "velocities", "m/s", 1e-3),
           ("velocity_sigma", "velocity_sigma", "m/s", 1e-3),
           ("acceleration", "accelerations", "m/s2", 1e-3),
           ("acceleration_sigma", "acceleration_sigma", "m/s2", 1e-3))
COMPONENTS = ("u", "v", "w")


def write_track_store(path: Path, tracks: Tracks, frame_numbers: Sequence[int],
                      fields: Sequence[tuple[int, int, PIVResult]], grid: Grid,
                      record: dict | None = None) -> Path:
    """Write ``tracks`` (frames numbered ``frame_numbers``, ``tracks.dt`` s apart) and
    their binned ``fields`` (``(first frame, last frame, field)``, frames counted from
    0) as the store (see the module notes); ``record``: what made them (JSON-ready),
    the store's ``record`` attribute."""
    variables = {**track_variables(tracks, frame_numbers),
                 **field_variables(fields, grid, tracks.dt, frame_numbers)}
    attrs = {"title": "plenocl tracks", "source": "plenocl run",
             "frame_interval_s": tracks.dt}
    if record is not None:
        attrs["record"] = record
    return write_store(path, variables, attrs)


def track_variables(tracks: Tracks, frame_numbers: Sequence[int]) -> dict[str, Variable]:
    """The tracks' arrays and their coordinates."""
    n, f, _ = tracks.positions.shape
    out: dict[str, Variable] = {
        "track": (("track",), np.arange(n), {"long_name": "track number"}),
        "frame": (("frame",), np.asarray(frame_numbers, np.int64),
                  {"long_name": "frame number (from the file name)"}),
        "time": (("frame",), np.arange(f) * tracks.dt,
                 {"units": "s", "long_name": "time from the first frame"}),
        "axis": (("axis",), np.array(["x", "y", "z"]), {"long_name": "component"}),
        "intensity": (("track", "frame"), tracks.intensities.astype(np.float32),
                      {"long_name": "particle intensity (image units)", "coordinates": "time"}),
        "length": (("track",), tracks.lengths.astype(np.int64),
                   {"long_name": "frames the track is seen in"}),
    }
    for name, attr, unit, scale in VECTORS:
        values = (getattr(tracks, attr) * scale).astype(np.float32)
        out[name] = (("track", "frame", "axis"), values,
                     {"units": unit, "long_name": attr.replace("_", " "), "coordinates": "time"})
    return out


def field_variables(fields: Sequence[tuple[int, int, PIVResult]], grid: Grid,
                    dt: float, frame_numbers: Sequence[int]) -> dict[str, Variable]:
    """The binned fields' arrays (m/s, object space) on their windows' centres (mm);
    each field's first and last frame by its number (the ``frame`` coordinate's)."""
    spacing, origin = grid_geometry(grid)
    arrays = [field_arrays(res, spacing, origin, dt, grid.rotation_deg)
              for _, _, res in fields]
    first, last = (np.array([f[k] for f in fields], np.int64) for k in (0, 1))
    dims = ("field_time", "z", "y", "x")
    frames = {"coordinates": "field_first_frame field_last_frame"}
    out: dict[str, Variable] = {
        "field_time": (("field_time",), (first + last) / 2 * dt,
                       {"units": "s", "long_name": "middle of the steps binned"}),
        "field_first_frame": (("field_time",), np.asarray(frame_numbers)[first],
                              {"long_name": "first frame binned (its number)"}),
        "field_last_frame": (("field_time",), np.asarray(frame_numbers)[last],
                             {"long_name": "last frame binned (its number)"}),
        **{axis: ((axis,), np.asarray(arrays[0][f"{axis}_mm"], float),
                  {"units": "mm", "long_name": f"{axis} of the window centre"})
           for axis in ("z", "y", "x")}}
    for k, comp in enumerate(COMPONENTS):
        out[comp] = (dims, np.stack([a["velocity"][k] for a in arrays]).astype(np.float32),
                     {"units": "m/s", "long_name": f"{comp} of the binned tracks", **frames})
        out[f"{comp}_sigma"] = (dims, np.stack([a["velocity_uncertainty"][k]
                                                for a in arrays]).astype(np.float32),
                                {"units": "m/s", "long_name": f"standard uncertainty of {comp}",
                                 **frames})
    for flag in ("valid", "outlier"):
        out[flag] = (dims, np.stack([a[flag] for a in arrays]), dict(frames))
    return out
