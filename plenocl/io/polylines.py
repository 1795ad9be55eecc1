"""Poly-lines for ParaView (a VTK UnstructuredGrid ``.vtu`` of poly-line cells): particle
tracks, one line each."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path


def write_vtu(path, lines: list[np.ndarray], point_data: dict[str, list[np.ndarray]]
              ) -> None:
    """Write poly-lines ``lines`` (each ``(m, 3)`` points ``(x, y, z)``, at least two) with
    per-point arrays (``point_data[name]``: one ``(m,)`` or ``(m, 3)`` array per line)
    as a ``.vtu`` file, atomically."""
    from pyevtk.hl import polyLinesToVTK

    if not lines:
        raise ValueError("no poly-lines to write: every track is shorter than two points")
    xyz = np.ascontiguousarray(np.concatenate(lines).T, dtype=np.float64)
    counts = np.array([len(line) for line in lines], dtype=np.int64)
    data = {}
    for name, parts in point_data.items():
        values = np.concatenate(parts).astype(np.float64)
        data[name] = (tuple(np.ascontiguousarray(values[:, k]) for k in range(3))
                      if values.ndim == 2 else np.ascontiguousarray(values))
    with atomic_path(path) as tmp:
        written = polyLinesToVTK(str(tmp.with_suffix("")), *xyz, pointsPerLine=counts,
                                 pointData=data)  # pyevtk appends ".vtu"
        if Path(written) != tmp:
            os.replace(written, tmp)
