"""Writing and reading PIV vector fields: ``.vti`` (ParaView), ``.npz``, ``.h5`` and
the tables Tecplot ``.dat`` and ``.csv`` (:mod:`.fieldtables`).

Every writer is atomic (a temporary file beside the target, then ``os.replace``), so a
crash never leaves a half-written field. One axis rule holds for every stored array:
gridded arrays are ``(..., nz', ny', nx')`` (array order, z slowest), while vector
components and every per-axis triple are ``(x, y, z)``, each triple's name ending in
``_xyz``. The arrays (``format_version`` 2):

- ``displacement``: ``(3, nz', ny', nx')`` as ``(u, v, w)`` in voxels along x, y, z;
- ``displacement_uncertainty``: ``(3, nz', ny', nx')``, the standard uncertainty of
  ``(u, v, w)`` in voxels (NaN for invalid or replaced vectors; see
  :attr:`plenocl.PIVResult.sigma_u`), and ``velocity_uncertainty`` in m/s with ``dt``;
- ``valid``, ``outlier``, ``masked`` (flags) and ``peak_ratio``;
- ``velocity`` (m/s), ``vorticity`` (1/s) and ``q_criterion`` (1/s^2) when ``dt`` is
  given; without it ``vorticity`` and ``q_criterion`` are per ``dt`` (and per ``dt^2``);
- coordinates: ``x``, ``y``, ``z`` (voxel-index units) and ``x_mm``, ``y_mm``, ``z_mm``;
- triples: ``voxel_size_mm_xyz``, ``origin_mm_xyz`` (the centre of voxel 0),
  ``window_xyz`` (the final window, voxels), ``vector_origin_mm_xyz`` and
  ``vector_spacing_mm_xyz`` (the vector grid, as in the ``.vti`` file);
- ``format_version``, ``rotation_deg`` and ``dt`` (s) as scalars.

Files written before ``format_version`` (version 1) held ``voxel_size_mm``,
``origin_mm`` and ``window`` in (z, y, x) order and ``vector_origin_mm``,
``vector_spacing_mm`` in (x, y, z); :func:`read_field` returns them in the layout above.

On a rotated grid (``rotation_deg``, stored too) the vector grid and ``displacement``
follow the grid's axes, while ``velocity`` and ``vorticity`` are given in object space
(the user's frame): their ``x``, ``y`` components are turned by the grid's rotation.

In ``.vti`` files the image origin and spacing are the vector grid's, in mm, and the
velocity in m/s is the default (active) vector where ``dt`` is given, else the
displacement in voxels.

This module writes and reads those arrays and a JSON-ready metadata dict; it knows no
vector-field type. :mod:`plenocl.vectorfield` turns a :class:`plenocl.PIVResult` into
them (:meth:`plenocl.PIVResult.arrays`) and back.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .fieldtables import write_csv, write_tecplot
from .npzfile import open_npz
from .outputs import check_output

__all__ = ["AXES", "FIELD_FORMATS", "FORMAT_VERSION", "READABLE_FIELD_FORMATS",
           "check_field_path", "current_layout", "field_metadata", "metadata_of",
           "read_field", "write_field", "write_h5", "write_npz", "write_vti"]

#: The layout of the arrays a field file holds; files without ``format_version`` are
#: version 1, where ``voxel_size_mm``, ``origin_mm`` and ``window`` were (z, y, x) (read
#: back converted: :func:`plenocl.io.fieldformat.read_field`).
FORMAT_VERSION = 2

#: Axis order and meaning of the stored arrays (also in every file's metadata).
AXES = ("gridded arrays (..., nz, ny, nx) on the vector grid, z slowest, x fastest; "
        "vector components and every per-axis triple (x, y, z), each triple's name ending "
        "in _xyz: voxel_size_mm_xyz, origin_mm_xyz (the centre of voxel 0), window_xyz, "
        "vector_origin_mm_xyz and vector_spacing_mm_xyz (the vector grid, as in the .vti "
        "file)")

#: The field file formats by suffix.
FIELD_FORMATS = {".vti": "VTK ImageData for ParaView", ".npz": "NumPy", ".h5": "HDF5",
                 ".hdf5": "HDF5", ".dat": "Tecplot ASCII", ".csv": "CSV table"}
#: The formats :func:`read_field` reads back (the others are for other programs).
READABLE_FIELD_FORMATS = (".npz", ".h5", ".hdf5")
#: Version-1 triples stored (z, y, x), by their version-2 names.
_ZYX_V1 = {"voxel_size_mm": "voxel_size_mm_xyz", "origin_mm": "origin_mm_xyz",
           "window": "window_xyz"}
#: Version-1 triples already stored (x, y, z), by their version-2 names.
_XYZ_V1 = {"vector_origin_mm": "vector_origin_mm_xyz",
           "vector_spacing_mm": "vector_spacing_mm_xyz"}


def write_field(path: str | Path, arrays: dict[str, np.ndarray],
                metadata: dict | None = None) -> Path:
    """Write a vector field's ``arrays`` (the module notes), choosing the format from the
    extension (:data:`FIELD_FORMATS`); ``metadata`` (JSON-ready; ``units`` and ``axes``
    become HDF5 attributes) is stored with ``.npz`` and ``.h5`` files.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    path = check_field_path(path)
    writers = {".vti": write_vti, ".npz": write_npz, ".h5": write_h5, ".hdf5": write_h5,
               ".dat": _table(write_tecplot), ".csv": _table(write_csv)}
    writers[path.suffix.lower()](path, arrays, metadata or {})
    return path


def _table(writer):
    """A table writer called as the others are (tables hold no metadata)."""
    return lambda path, arrays, metadata: writer(path, arrays)


def check_field_path(path: str | Path) -> Path:
    """``path`` as a ``Path``, or a ``ValueError`` when its suffix names no field format
    (:data:`FIELD_FORMATS`) or its folder cannot be written in; call it before the work
    that makes the field."""
    return check_output(path, FIELD_FORMATS, "field")


def write_npz(path, arrays: dict[str, np.ndarray], metadata: dict) -> None:
    """Write ``arrays`` and a JSON ``metadata`` entry to a compressed ``.npz``, atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays, metadata=np.asarray(json.dumps(metadata)))


def metadata_of(arrays) -> dict:
    """The JSON ``metadata`` entry of a field's arrays (``{}`` without one)."""
    return json.loads(str(arrays["metadata"])) if "metadata" in arrays else {}


def field_metadata(path) -> dict:
    """The JSON metadata of a field written by :func:`write_npz` or :func:`write_h5`
    (``{}`` without any), without reading its arrays."""
    if _readable(path) == ".npz":
        with open_npz(path, "a vector field (plenocl.save_field)") as data:
            return metadata_of(data)
    import h5py

    with h5py.File(path, "r") as fh:
        return json.loads(fh.attrs.get("metadata", "{}"))


def read_field(path) -> dict[str, np.ndarray]:
    """Every array of a field written by :func:`write_npz` or :func:`write_h5`
    (``metadata``: its JSON text), in the layout of the module notes: a file of the first
    layout (no ``format_version``) comes back converted."""
    if _readable(path) == ".npz":
        with open_npz(path, "a vector field (plenocl.save_field)") as data:
            arrays = {name: data[name] for name in data.files}
    else:
        arrays = _read_h5(path)
    return current_layout(arrays)


def _readable(path) -> str:
    """The suffix of a field file :func:`read_field` reads; a ``ValueError`` for others."""
    suffix = Path(path).suffix.lower()
    if suffix not in READABLE_FIELD_FORMATS:
        raise ValueError(f"{Path(path).name}: plenocl reads fields back from .npz and .h5 "
                         "files; .vti, .dat and .csv are written for ParaView, Tecplot and "
                         "spreadsheets")
    return ".npz" if suffix == ".npz" else ".h5"


def _read_h5(path) -> dict[str, np.ndarray]:
    import h5py

    with h5py.File(path, "r") as fh:
        arrays = {name: fh[name][()] for name in fh}
        if "metadata" in fh.attrs:
            arrays["metadata"] = np.asarray(fh.attrs["metadata"])
    return arrays


def current_layout(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A field's arrays in the layout of the module notes: those of a version-1 file
    (no ``format_version``) with its (z, y, x) triples turned to (x, y, z) and every
    triple renamed ``*_xyz``, its metadata's ``axes`` replaced and
    ``converted_from_version`` 1 added; current arrays as they are."""
    if "format_version" in arrays:
        return arrays
    out = {k: v for k, v in arrays.items() if k not in _ZYX_V1 and k not in _XYZ_V1}
    out.update({new: np.asarray(arrays[old])[::-1].copy()
                for old, new in _ZYX_V1.items() if old in arrays})
    out.update({new: arrays[old] for old, new in _XYZ_V1.items() if old in arrays})
    out["format_version"] = np.asarray(FORMAT_VERSION)
    if "metadata" in arrays:
        meta = {**metadata_of(arrays), "axes": AXES, "converted_from_version": 1}
        out["metadata"] = np.asarray(json.dumps(meta))
    return out


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
    spacing = tuple(float(v) for v in arrays["vector_spacing_mm_xyz"])
    origin = tuple(float(v) for v in arrays["vector_origin_mm_xyz"])
    with atomic_path(path) as tmp:
        written = imageToVTK(str(tmp.with_suffix("")), origin=origin, spacing=spacing,
                             pointData=_point_data(arrays))  # pyevtk appends ".vti"
        if Path(written) != tmp:
            os.replace(written, tmp)


def _point_data(arrays: dict[str, np.ndarray]) -> dict:
    """The ``.vti`` point arrays: vectors as component tuples, Q, the flags (every
    boolean array) and the peak ratio; per ``dt`` names where no ``dt`` was given. The
    first vector array is the file's active vectors (pyevtk's rule, what ParaView shows
    first): the velocity where there is one."""
    per = "_per_s" if "dt" in arrays else "_per_dt"
    vectors = {"velocity_m_per_s": "velocity", "displacement_voxels": "displacement",
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
        fh.attrs["layout"] = ("arrays (..., nz, ny, nx); vector components and *_xyz "
                              "triples (x, y, z); displacement (u, v, w) in voxels")
