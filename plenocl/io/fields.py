"""Writing and reading PIV vector fields: ``.vti`` (ParaView), ``.npz`` and ``.h5``.

Every writer is atomic (a temporary file beside the target, then ``os.replace``), so a
crash never leaves a half-written field. Stored arrays, all on the vector grid
``(nz', ny', nx')`` in array order:

- ``displacement``: ``(3, nz', ny', nx')`` as ``(u, v, w)`` in voxels along x, y, z;
- ``displacement_uncertainty``: ``(3, nz', ny', nx')``, the standard uncertainty of
  ``(u, v, w)`` in voxels (NaN for invalid or replaced vectors; see
  :attr:`plenocl.PIVResult.sigma_u`), and ``velocity_uncertainty`` in m/s with ``dt``;
- ``valid``, ``outlier``, ``masked`` (flags) and ``peak_ratio``;
- ``velocity`` (m/s), ``vorticity`` (1/s) and ``q_criterion`` (1/s^2) when ``dt`` is
  given; without it ``vorticity`` and ``q_criterion`` are per ``dt`` (and per ``dt^2``);
- coordinates: ``x``, ``y``, ``z`` (voxel-index units) and ``x_mm``, ``y_mm``, ``z_mm``.

On a rotated grid (``rotation_deg``, stored too) the vector grid and ``displacement``
follow the grid's axes, while ``velocity`` and ``vorticity`` are given in object space
(the user's frame): their ``x``, ``y`` components are turned by the grid's rotation.

In ``.vti`` files the image origin and spacing are the vector grid's, in mm.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..vectorfield import FLAGS, PIVResult, voxel_size
from .atomic import atomic_path

__all__ = ["field_arrays", "field_metadata", "metadata_of", "read_npz", "save_field",
           "write_h5", "write_npz", "write_vti"]


def _geometry(voxel_size_mm, origin_mm, grid):
    """Voxel size ``(dz, dy, dx)`` and voxel-0 centre ``(z0, y0, x0)`` in mm."""
    if grid is not None:
        spacing = tuple(float(s) for s in grid.spacing)
        lows = (grid.z[0], grid.y[0], grid.x[0])
        return spacing, tuple(lo + 0.5 * s for lo, s in zip(lows, spacing))
    origin = tuple(float(o) for o in np.broadcast_to(np.asarray(origin_mm, float), (3,)))
    return voxel_size(voxel_size_mm), origin


def field_arrays(result: PIVResult, voxel_size_mm=1.0, origin_mm=(0.0, 0.0, 0.0),
                 dt: float | None = None, rotation_deg: float = 0.0,
                 metadata: dict | None = None) -> dict[str, np.ndarray]:
    """All arrays written by :func:`save_field`, keyed by name (see the module notes): the
    field's own (:meth:`plenocl.PIVResult.arrays`) and a JSON ``metadata`` entry, its
    :meth:`~plenocl.PIVResult.metadata` with ``metadata``'s entries; the parameters are
    :func:`save_field`'s.
    """
    out = result.arrays(voxel_size_mm, origin_mm, dt, rotation_deg)
    out["metadata"] = np.asarray(json.dumps({**(metadata or {}), **result.metadata(dt)}))
    return out


def save_field(path: str | Path, result: PIVResult, voxel_size_mm=1.0,
               origin_mm=(0.0, 0.0, 0.0), dt: float | None = None, grid=None,
               metadata: dict | None = None) -> Path:
    """Write a PIV result, choosing the format from the extension (.vti, .npz, .h5/.hdf5).

    Parameters
    ----------
    path
        Output file; its suffix selects the format.
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
        velocity and vorticity are written in object space (see the module notes).
    metadata
        JSON-ready entries stored with the field (``.npz``, ``.h5``; a batch run records
        each pair's source files here), read back by :func:`field_metadata`.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    path = Path(path)
    size, origin = _geometry(voxel_size_mm, origin_mm, grid)
    writers = {".vti": write_vti, ".npz": write_npz, ".h5": write_h5, ".hdf5": write_h5}
    writer = writers.get(path.suffix.lower())
    if writer is None:
        raise ValueError(f"cannot tell the field format from {path.name!r}: use a .vti "
                         f"(ParaView), .npz or .h5 file name")
    writer(path, result, size, origin, dt, 0.0 if grid is None else grid.rotation_deg,
           metadata=metadata)
    return path


def write_npz(path, result: PIVResult, voxel_size_mm=1.0, origin_mm=(0.0, 0.0, 0.0),
              dt: float | None = None, rotation_deg: float = 0.0,
              metadata: dict | None = None) -> None:
    """Write :func:`field_arrays` to a compressed ``.npz``, atomically."""
    arrays = field_arrays(result, voxel_size_mm, origin_mm, dt, rotation_deg, metadata)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def metadata_of(arrays) -> dict:
    """The JSON ``metadata`` entry of a field's arrays (``{}`` without one)."""
    return json.loads(str(arrays["metadata"])) if "metadata" in arrays else {}


def field_metadata(path) -> dict:
    """The JSON metadata of a field written by :func:`write_npz` (``{}`` without any),
    without reading its arrays."""
    with np.load(path) as data:
        return metadata_of(data)


def read_npz(path) -> tuple[PIVResult, dict[str, np.ndarray]]:
    """Read a field written by :func:`write_npz`.

    Returns
    -------
    result : PIVResult
        The displacement field and flags (per-pass diagnostics are not stored).
    arrays : dict
        Every stored array, including ``voxel_size_mm``, ``origin_mm`` and, if written,
        ``dt`` and ``velocity``.
    """
    with np.load(path) as data:
        arrays = {name: data[name] for name in data.files}
    return PIVResult.from_arrays(arrays, source=str(path)), arrays


def _vtk_order(arr: np.ndarray) -> np.ndarray:
    """``(nz, ny, nx)`` array as the ``(nx, ny, nz)`` view pyevtk writes x-fastest."""
    arr = np.ascontiguousarray(arr)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    return arr.T


def write_vti(path, result: PIVResult, voxel_size_mm=1.0, origin_mm=(0.0, 0.0, 0.0),
              dt: float | None = None, rotation_deg: float = 0.0,
              metadata: dict | None = None) -> None:
    """Write a VTK ImageData ``.vti`` file for ParaView (point data on the vector grid;
    ``metadata`` is not stored: the ``.npz`` or ``.h5`` beside it holds it)."""
    try:
        from pyevtk.hl import imageToVTK
    except ImportError as exc:  # pragma: no cover - pyevtk is a declared dependency
        raise ImportError("writing .vti needs pyevtk: pip install pyevtk") from exc
    arrays = field_arrays(result, voxel_size_mm, origin_mm, dt, rotation_deg)
    spacing = tuple(float(v) for v in arrays["vector_spacing_mm"])
    origin = tuple(float(v) for v in arrays["vector_origin_mm"])
    vectors = {"displacement_voxels": "displacement", "velocity_m_per_s": "velocity",
               "displacement_uncertainty_voxels": "displacement_uncertainty",
               "velocity_uncertainty_m_per_s": "velocity_uncertainty",
               "vorticity_per_s" if dt is not None else "vorticity_per_dt": "vorticity"}
    point = {name: tuple(_vtk_order(c) for c in arrays[key])
             for name, key in vectors.items() if key in arrays}
    point["q_criterion_per_s2" if dt is not None else "q_criterion_per_dt2"] = \
        _vtk_order(arrays["q_criterion"])
    for name in (*FLAGS, "peak_ratio"):
        point[name] = _vtk_order(arrays[name])
    with atomic_path(path) as tmp:
        written = imageToVTK(str(tmp.with_suffix("")), origin=origin, spacing=spacing,
                             pointData=point)  # pyevtk appends ".vti" itself
        if Path(written) != tmp:
            os.replace(written, tmp)


def write_h5(path, result: PIVResult, voxel_size_mm=1.0, origin_mm=(0.0, 0.0, 0.0),
             dt: float | None = None, rotation_deg: float = 0.0,
             metadata: dict | None = None) -> None:
    """Write :func:`field_arrays` to HDF5 (one dataset per array), atomically."""
    try:
        import h5py
    except ImportError as exc:
        raise ImportError("writing .h5 fields needs h5py: pip install h5py "
                          "(or save as .npz or .vti)") from exc
    arrays = field_arrays(result, voxel_size_mm, origin_mm, dt, rotation_deg, metadata)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as fh:
        meta = result.metadata(dt)
        units = meta["units"]
        for name, arr in arrays.items():
            if np.asarray(arr).dtype.kind == "U":  # text: a file attribute
                fh.attrs[name] = str(arr)
                continue
            opts = {"compression": "gzip"} if np.ndim(arr) >= 3 else {}
            data = fh.create_dataset(name, data=arr, **opts)
            if name in units:
                data.attrs["units"] = units[name]
        fh.attrs["axes"] = meta["axes"]
        fh.attrs["layout"] = "arrays (..., nz, ny, nx); displacement (u, v, w) in voxels"
