"""A chunked Zarr store that xarray opens, written whole or not at all.

:func:`write_store` writes named arrays, each with its dimension names and attributes,
into a store built beside its place (``NAME.partial``) and moved there when complete
(:func:`finish_store`), so a run stopped midway leaves the previous store (or none),
never half of one. :mod:`plenocl.io.timeseries` finishes its store the same way.
"""

from __future__ import annotations

import os
import shutil
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np

# A type: one array of a store: its dimension names, its values and its attributes.
Variable = tuple[tuple[str, ...], np.ndarray, dict]


def partial_store(path: str | Path) -> Path:
    """The folder a store is built in before it is moved to ``path`` (emptied)."""
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    return partial


def write_store(path: str | Path, variables: Mapping[str, Variable],
                attributes: Mapping | None = None) -> Path:
    """Write ``variables`` (``{name: (dims, values, attributes)}``) as a Zarr store at
    ``path``, replacing an older one; string arrays are stored as UTF-8 text.

    Returns
    -------
    pathlib.Path
        The store (``xarray.open_zarr(path)`` reads it).
    """
    import zarr

    partial = partial_store(path)
    group = zarr.open_group(partial, mode="w")
    for name, (dims, values, attrs) in variables.items():
        values = np.asarray(values)
        if values.dtype.kind in "UO":
            arr = group.create_array(name, shape=values.shape, dimension_names=list(dims),
                                     dtype=zarr.dtype.VariableLengthUTF8(), attributes=attrs)
            arr[...] = values.astype(object)
        else:
            group.create_array(name, data=values, dimension_names=list(dims),
                               attributes=dict(attrs))
    group.attrs.update(dict(attributes or {}))
    return finish_store(partial, Path(path))


def finish_store(partial: Path, path: Path) -> Path:
    """Consolidate the metadata of the store built in ``partial`` (one read opens it) and
    move it to ``path``, replacing an older store."""
    import zarr

    with warnings.catch_warnings():  # zarr: "not part of the Zarr 3 specification" (yet)
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        zarr.consolidate_metadata(partial)
    old = path.with_name(path.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if path.exists():
        os.replace(path, old)
    os.replace(partial, path)
    shutil.rmtree(old, ignore_errors=True)
    return path


def read_store(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """Every array of a store written by :func:`write_store` or
    :func:`plenocl.io.timeseries.write_timeseries`, by name, and the store's attributes
    with each array's under ``"arrays"`` (``attrs["arrays"]["time"]["units"]``).

    Raises
    ------
    ValueError
        When ``path`` is no Zarr store (a folder with ``zarr.json``).
    """
    import zarr

    path = Path(path)
    if not (path / "zarr.json").is_file():
        raise ValueError(f"{path} is not a Zarr store (a folder holding zarr.json, as "
                         "plenocl run writes: timeseries.zarr, tracks.zarr)")
    group = zarr.open_group(path, mode="r")
    members = dict(group.arrays())
    arrays = {name: np.asarray(arr[...]) for name, arr in members.items()}
    return arrays, {**dict(group.attrs),
                    "arrays": {name: dict(arr.attrs) for name, arr in members.items()}}
