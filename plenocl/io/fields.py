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

This module writes and reads those arrays and a JSON-ready metadata dict; it knows no
vector-field type. :mod:`plenocl.vectorfile` turns a :class:`plenocl.PIVResult` into
them (:meth:`plenocl.PIVResult.arrays`) and back.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path

__all__ = ["FIELD_FORMATS", "check_field_path", "field_metadata", "metadata_of",
           "read_field", "write_field", "write_h5", "write_npz", "write_vti"]

#: The field file formats by suffix.
FIELD_FORMATS = {".vti": "VTK ImageData (ParaView)", ".npz": "NumPy", ".h5": "HDF5",
                 ".hdf5": "HDF5"}


def write_field(path: str | Path, arrays: dict[str, np.ndarray],
                metadata: dict | None = None) -> Path:
    """Write a vector field's ``arrays`` (the module notes), choosing the format from the
    extension (.vti, .npz, .h5/.hdf5); ``metadata`` (JSON-ready; ``units`` and ``axes``
    become HDF5 attributes) is stored with ``.npz`` and ``.h5`` files.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    path = check_field_path(path)
    writers = {".vti": write_vti, ".npz": write_npz, ".h5": write_h5, ".hdf5": write_h5}
    writers[path.suffix.lower()](path, arrays, metadata or {})
    return path


def check_field_path(path: str | Path) -> Path:
    """``path`` as a ``Path``, or a ``ValueError`` when its suffix names no field format."""
    path = Path(path)
    if path.suffix.lower() not in FIELD_FORMATS:
        raise ValueError(f"cannot tell the field format from {path.name!r}: use a .vti "
                         f"(ParaView), .npz or .h5 file name")
    return path


def write_npz(path, arrays: dict[str, np.ndarray], metadata: dict) -> None:
    """Write ``arrays`` and a JSON ``metadata`` entry to a compressed ``.npz``, atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays, metadata=np.asarray(json.dumps(metadata)))


def metadata_of(arrays) -> dict:
    """The JSON ``metadata`` entry of a field's arrays (``{}`` without one)."""
    return json.loads(str(arrays["metadata"])) if "metadata" in arrays else {}


def field_metadata(path) -> dict:
    """The JSON metadata of a field written by :func:`write_npz` (``{}`` without any),
    without reading its arrays."""
    with np.load(path) as data:
        return metadata_of(data)


def read_field(path) -> dict[str, np.ndarray]:
    """Every array of a field written by :func:`write_npz` (``metadata``: its JSON text)."""
    with np.load(path) as data:
        return {name: data[name] for name in data.files}


def _vtk_order(arr: np.ndarray) -> np.ndarray:
    """``(nz, ny, nx)`` array as the ``(nx, ny, nz)`` view pyevtk writes x-fastest."""
    arr = np.ascontiguousarray(arr)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    return arr.T


def write_vti(path, arrays: dict[str, np.ndarray], metadata: dict | None = None) -> None:
    """Write a VTK ImageData ``.vti`` file for ParaView (point data on the vector grid;
    ``metadata`` is not stored: the ``.npz`` or ``.h5`` beside it holds it)."""
    try:
        from pyevtk.hl import imageToVTK
    except ImportError as exc:  # pragma: no cover - pyevtk is a declared dependency
        raise ImportError("writing .vti needs pyevtk: pip install pyevtk") from exc
    spacing = tuple(float(v) for v in arrays["vector_spacing_mm"])
    origin = tuple(float(v) for v in arrays["vector_origin_mm"])
    with atomic_path(path) as tmp:
        written = imageToVTK(str(tmp.with_suffix("")), origin=origin, spacing=spacing,
                             pointData=_point_data(arrays))  # pyevtk appends ".vti"
        if Path(written) != tmp:
            os.replace(written, tmp)


def _point_data(arrays: dict[str, np.ndarray]) -> dict:
    """The ``.vti`` point arrays: vectors as component tuples, Q, the flags (every
    boolean array) and the peak ratio; per ``dt`` names where no ``dt`` was given."""
    per = "_per_s" if "dt" in arrays else "_per_dt"
    vectors = {"displacement_voxels": "displacement", "velocity_m_per_s": "velocity",
               "displacement_uncertainty_voxels": "displacement_uncertainty",
               "velocity_uncertainty_m_per_s": "velocity_uncertainty",
               "vorticity" + per: "vorticity"}
    point = {name: tuple(_vtk_order(c) for c in arrays[key])
             for name, key in vectors.items() if key in arrays}
    point["q_criterion" + per + "2"] = _vtk_order(arrays["q_criterion"])
    shape = np.shape(arrays["q_criterion"])
    for name, arr in arrays.items():
        if np.asarray(arr).dtype == bool and np.shape(arr) == shape:
            point[name] = _vtk_order(arr)
    point["peak_ratio"] = _vtk_order(arrays["peak_ratio"])
    return point


def write_h5(path, arrays: dict[str, np.ndarray], metadata: dict) -> None:
    """Write ``arrays`` to HDF5 (one dataset per array), atomically; ``metadata`` as a
    JSON file attribute, its ``units`` on the datasets and its ``axes`` on the file."""
    try:
        import h5py
    except ImportError as exc:
        raise ImportError("writing .h5 fields needs h5py: pip install h5py "
                          "(or save as .npz or .vti)") from exc
    units = metadata.get("units", {})
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as fh:
        for name, arr in arrays.items():
            opts = {"compression": "gzip"} if np.ndim(arr) >= 3 else {}
            data = fh.create_dataset(name, data=arr, **opts)
            if name in units:
                data.attrs["units"] = units[name]
        fh.attrs["metadata"] = json.dumps(metadata)
        if "axes" in metadata:
            fh.attrs["axes"] = metadata["axes"]
        fh.attrs["layout"] = "arrays (..., nz, ny, nx); displacement (u, v, w) in voxels"
