"""A reconstructed volume as a file, with the :class:`plenocl.Grid` it lives on
(``.npz``, ``.h5``; ``.npy`` holds the array alone).

:mod:`plenocl.io.files` writes and reads the array and the grid's numbers
(:func:`~plenocl.io.files.write_volume`, :func:`~plenocl.io.files.read_volume`) and
knows no grid type; this module turns a grid into them and back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .grid import Grid
from .io.files import read_volume, write_volume
from .io.npzfile import MissingArray

__all__ = ["load_volume", "save_volume"]


def save_volume(path: str | Path, vol: np.ndarray, grid: Grid | None = None) -> None:
    """Save a volume atomically: ``.npy`` (array only), ``.npz`` or ``.h5`` (with the grid).

    ``.h5`` needs h5py (``pip install h5py``). A volume of another shape than ``grid``'s
    is refused (it was written, and refused only when read for PIV).
    """
    if grid is not None and np.shape(vol) != tuple(grid.shape):
        raise ValueError(f"the volume's shape {np.shape(vol)} is not its grid's "
                         f"{tuple(grid.shape)} (z, y, x): save it with the grid it was made "
                         "on")
    meta = {} if grid is None else {"shape": np.array(grid.shape), "x_mm": np.array(grid.x),
                                    "y_mm": np.array(grid.y), "z_mm": np.array(grid.z),
                                    "rotation_deg": np.array(grid.rotation_deg)}
    write_volume(path, vol, meta)


def load_volume(path: str | Path) -> tuple[np.ndarray, Grid | None]:
    """Load a volume saved by :func:`save_volume`; returns ``(volume, grid or None)``."""
    vol, meta = read_volume(path)
    if not meta:
        return vol, None
    missing = [key for key in ("shape", "x_mm", "y_mm", "z_mm") if key not in meta]
    if missing:
        raise MissingArray(f"{path} is not a volume plenocl.save_volume wrote: beside the "
                           f"volume it holds {sorted(meta)}, not its grid ({missing[0]!r} "
                           "missing)")
    return vol, Grid(tuple(int(n) for n in meta["shape"]), tuple(meta["x_mm"]),
                     tuple(meta["y_mm"]), tuple(meta["z_mm"]),
                     float(meta.get("rotation_deg", 0.0)))
