"""A vector field as a file: :class:`plenocl.PIVResult` written with its geometry
(``.vti`` for ParaView, ``.npz``, ``.h5``, Tecplot ``.dat``, ``.csv``) and read back
(``.npz``, ``.h5``).

The result gives its arrays and metadata (:meth:`plenocl.PIVResult.arrays`,
:meth:`~plenocl.PIVResult.metadata`); :mod:`plenocl.io.fields` writes and reads those
arrays and knows no vector-field type. The stored arrays are listed there.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .io.fields import check_field_path, read_field, write_field
from .vectorfield import PIVResult, voxel_size

__all__ = ["field_arrays", "grid_geometry", "read_npz", "save_field"]


def grid_geometry(grid) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """A grid's voxel size ``(dz, dy, dx)`` and voxel-0 centre ``(z0, y0, x0)`` in mm
    (what :meth:`plenocl.PIVResult.arrays` takes)."""
    spacing = tuple(float(s) for s in grid.spacing)
    lows = (grid.z[0], grid.y[0], grid.x[0])
    return spacing, tuple(lo + 0.5 * s for lo, s in zip(lows, spacing))


def _geometry(voxel_size_mm, origin_mm, grid):
    """Voxel size ``(dz, dy, dx)`` and voxel-0 centre ``(z0, y0, x0)`` in mm."""
    if grid is not None:
        return grid_geometry(grid)
    origin = tuple(float(o) for o in np.broadcast_to(np.asarray(origin_mm, float), (3,)))
    return voxel_size(voxel_size_mm), origin


def field_arrays(result: PIVResult, voxel_size_mm=1.0, origin_mm=(0.0, 0.0, 0.0),
                 dt: float | None = None, rotation_deg: float = 0.0,
                 metadata: dict | None = None) -> dict[str, np.ndarray]:
    """All arrays :func:`save_field` writes to a ``.npz``, keyed by name: the field's own
    (:meth:`plenocl.PIVResult.arrays`) and a JSON ``metadata`` entry, its
    :meth:`~plenocl.PIVResult.metadata` with ``metadata``'s entries; the parameters are
    :func:`save_field`'s."""
    out = result.arrays(voxel_size_mm, origin_mm, dt, rotation_deg)
    out["metadata"] = np.asarray(json.dumps(_metadata(result, dt, metadata)))
    return out


def _metadata(result: PIVResult, dt: float | None, metadata: dict | None) -> dict:
    return {**(metadata or {}), **result.metadata(dt)}


def save_field(path: str | Path, result: PIVResult, voxel_size_mm=1.0,
               origin_mm=(0.0, 0.0, 0.0), dt: float | None = None, grid=None,
               metadata: dict | None = None) -> Path:
    """Write a PIV result, choosing the format from the extension (.vti, .npz, .h5/.hdf5,
    Tecplot ASCII .dat, .csv; :data:`plenocl.io.fields.FIELD_FORMATS`), atomically.

    Parameters
    ----------
    path
        Output file; its suffix selects the format; its folder must be writable (both
        checked before anything is computed: a ``ValueError`` otherwise).
    result
        Output of :func:`plenocl.piv3d`.
    voxel_size_mm
        Scalar or ``(dz, dy, dx)`` in mm.
    origin_mm
        ``(z0, y0, x0)``: the centre of voxel ``(0, 0, 0)`` in mm.
    dt
        Time between the volumes (s); adds velocity in m/s and vorticity in 1/s.
    grid
        Optional :class:`plenocl.Grid` of the volumes; overrides ``voxel_size_mm`` and
        ``origin_mm`` (its extents are the volume's outer faces); on a rotated grid the
        velocity and vorticity are written in object space (:mod:`plenocl.io.fields`).
    metadata
        JSON-ready entries stored with the field (``.npz``, ``.h5``; a batch run records
        each pair's source files here), read back by
        :func:`plenocl.io.fields.field_metadata`.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    path = check_field_path(path)
    size, origin = _geometry(voxel_size_mm, origin_mm, grid)
    rotation = 0.0 if grid is None else grid.rotation_deg
    return write_field(path, result.arrays(size, origin, dt, rotation),
                       _metadata(result, dt, metadata))


def read_npz(path) -> tuple[PIVResult, dict[str, np.ndarray]]:
    """Read a field written by :func:`save_field` to a ``.npz`` or ``.h5`` (a file of the
    first layout comes back in the current one, :func:`plenocl.io.fields.read_field`).

    Returns
    -------
    result : PIVResult
        The displacement field and flags (per-pass diagnostics are not stored).
    arrays : dict
        Every stored array, including ``voxel_size_mm_xyz``, ``origin_mm_xyz`` (both
        (x, y, z)) and, if written, ``dt`` and ``velocity``.
    """
    arrays = read_field(path)
    return PIVResult.from_arrays(arrays, source=str(path)), arrays
