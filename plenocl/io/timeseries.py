"""The time series of a batch run as one chunked Zarr store, readable by xarray.

:func:`write_timeseries` gathers per-pair vector fields (``.npz`` files of
:func:`plenocl.vectorfield.save_field`) into ``timeseries.zarr``:

- coordinates ``time`` (s, or pair numbers where the pair interval is unknown), ``z``,
  ``y``, ``x`` (mm, the vector grid's centres) and ``pair`` (the pair's index in the run);
- per pair ``u``, ``v``, ``w`` (m/s), their standard uncertainties ``u_sigma``,
  ``v_sigma``, ``w_sigma`` (m/s, NaN where unknown), ``valid`` and ``outlier`` flags and
  ``peak_ratio``, shaped ``(time, z, y, x)``, one chunk per pair; the two source files of
  each pair, ``source_a`` and ``source_b`` (file names) and ``source_a_sha256``,
  ``source_b_sha256`` (empty where a field records none), shaped ``(time,)``;
- the ensemble over the run, shaped ``(z, y, x)``: ``u_mean``, ``v_mean``, ``w_mean``
  and the RMS fluctuations ``u_rms``, ``v_rms``, ``w_rms`` over the valid vectors, with
  ``valid_count``; with an ensemble correlation (``[piv] ensemble``), its mean field
  ``u_ensemble``, ``v_ensemble``, ``w_ensemble`` and ``valid_ensemble``.

A batch run records what the store was built from as the group attribute ``record``
(each pair's digest, the ensemble's; :func:`plenocl.batch.record.store_record`).

``xarray.open_zarr("timeseries.zarr")`` reads it with those names and units. The store
is written beside its final place and moved there when complete, so a run stopped
midway leaves the previous store (or none), never half of one.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .fieldformat import metadata_of, read_field
from .zarrstore import finish_store, partial_store

COMPONENTS = ("u", "v", "w")


def write_timeseries(path: str | Path, fields: Sequence[tuple[int, float, Path]],
                     time_units: str = "s", ensemble: str | Path | None = None,
                     record: dict | None = None) -> Path:
    """Write the store (see the module notes) from ``(pair index, time, .npz path)``.

    Parameters
    ----------
    path
        The store to write (a folder, ``*.zarr``); an existing one is replaced.
    fields
        One entry per pair, in time order; every field on the same vector grid, with
        velocities (written with ``dt``).
    time_units
        Units of the times (``"s"``, or ``"pair"`` when they are pair numbers).
    ensemble
        Optional ensemble-correlation field (``.npz``, same grid): stored as
        ``u_ensemble``, ``v_ensemble``, ``w_ensemble`` and ``valid_ensemble``.
    record
        JSON-ready record of what the store was built from (a batch run: each pair's
        digest), stored as the group attribute ``record``.

    Returns
    -------
    pathlib.Path
        The store.
    """
    import zarr

    if not fields:
        raise ValueError("no vector fields to gather into a time series")
    path = Path(path)
    partial = partial_store(path)
    group = zarr.open_group(partial, mode="w")
    first = read_field(fields[0][2])
    _coordinates(group, first, fields, time_units)
    stats = _Ensemble(first["velocity"].shape[1:])
    arrays = _per_pair_arrays(group, len(fields), stats.shape)
    sources = [("", "", "", "")] * len(fields)
    for k, (_, _, npz) in enumerate(fields):
        data = first if k == 0 else read_field(npz)
        _check_grid(data, first, npz)
        for comp, values in zip(COMPONENTS, data["velocity"]):
            arrays[comp][k] = values
        sigma = data.get("velocity_uncertainty")
        for comp, values in zip(COMPONENTS, sigma if sigma is not None else [np.nan] * 3):
            arrays[f"{comp}_sigma"][k] = values
        for name in ("valid", "outlier", "peak_ratio"):
            arrays[name][k] = data[name]
        stats.add(data["velocity"], data["valid"])
        sources[k] = _sources(data)
    _write_sources(group, sources)
    stats.write(group)
    if ensemble is not None:
        _write_ensemble(group, read_field(ensemble), first, Path(ensemble))
    # x, y are along the grid's axes, u, v along object space's (design.md §9): the turn
    # between them, for whoever differentiates or draws the velocities on those axes
    group.attrs.update({"title": "plenocl time series", "source": "plenocl run",
                        "rotation_deg": float(first.get("rotation_deg", 0.0))})
    if record is not None:
        group.attrs["record"] = record
    return finish_store(partial, path)


def _sources(data: dict) -> tuple[str, str, str, str]:
    """Names and SHA-256 of a field's two source files, from its metadata."""
    src = metadata_of(data).get("sources", {})
    return tuple(src.get(tag, {}).get(key, "") for key in ("name", "sha256") for tag in "ab")


def _write_sources(group, sources: list[tuple[str, str, str, str]]) -> None:
    import zarr

    names = ("source_a", "source_b", "source_a_sha256", "source_b_sha256")
    for i, name in enumerate(names):
        arr = group.create_array(name, shape=(len(sources),), dimension_names=["time"],
                                 dtype=zarr.dtype.VariableLengthUTF8(),
                                 attributes={"long_name": f"{name.replace('_', ' ')} of "
                                             "the pair (exposure a or b)"})
        arr[:] = np.array([s[i] for s in sources], dtype=object)


def _coordinates(group, first: dict, fields, time_units: str) -> None:
    """The ``time``, ``pair``, ``z``, ``y``, ``x`` coordinate arrays."""
    times = np.array([t for _, t, _ in fields], float)
    group.create_array("time", data=times, dimension_names=["time"],
                       attributes={"units": time_units, "long_name": "time of the pair"})
    group.create_array("pair", data=np.array([k for k, _, _ in fields], np.int64),
                       dimension_names=["time"],
                       attributes={"long_name": "index of the pair in the run"})
    for axis in ("z", "y", "x"):
        group.create_array(axis, data=np.asarray(first[f"{axis}_mm"], float),
                           dimension_names=[axis],
                           attributes={"units": "mm", "long_name": f"{axis} of the vector"})
    group.attrs["coordinates"] = "pair"


def _per_pair_arrays(group, count: int, shape) -> dict:
    dims = ["time", "z", "y", "x"]
    chunks = (1, *shape)
    out = {}
    for comp in COMPONENTS:
        out[comp] = group.create_array(comp, shape=(count, *shape), chunks=chunks,
                                       dtype="f4", fill_value=np.nan, dimension_names=dims,
                                       attributes={"units": "m/s", "coordinates": "pair"})
        out[f"{comp}_sigma"] = group.create_array(
            f"{comp}_sigma", shape=(count, *shape), chunks=chunks, dtype="f4",
            fill_value=np.nan, dimension_names=dims,
            attributes={"units": "m/s", "coordinates": "pair",
                        "long_name": f"standard uncertainty of {comp}"})
    for name, dtype in (("valid", "bool"), ("outlier", "bool"), ("peak_ratio", "f4")):
        out[name] = group.create_array(name, shape=(count, *shape), chunks=chunks,
                                       dtype=dtype, dimension_names=dims,
                                       attributes={"coordinates": "pair"})
    return out


def _write_ensemble(group, data: dict, first: dict, npz: Path) -> None:
    """The ensemble-correlation mean field, ``(z, y, x)``."""
    _check_grid(data, first, npz)
    dims = ["z", "y", "x"]
    for comp, values in zip(COMPONENTS, data["velocity"]):
        group.create_array(f"{comp}_ensemble", data=values.astype(np.float32),
                           fill_value=np.nan, dimension_names=dims,
                           attributes={"units": "m/s", "long_name":
                                       f"{comp} of the ensemble correlation"})
    group.create_array("valid_ensemble", data=np.asarray(data["valid"], bool),
                       dimension_names=dims)


def _check_grid(data: dict, first: dict, npz: Path) -> None:
    if data["velocity"].shape != first["velocity"].shape:
        raise ValueError(f"{npz} holds a {data['velocity'].shape[1:]} vector grid, the "
                         f"others {first['velocity'].shape[1:]}: one run, one grid")


class _Ensemble:
    """Running mean and RMS fluctuation of the valid vectors at every grid point."""

    def __init__(self, shape) -> None:
        self.shape = tuple(shape)
        self.count = np.zeros(self.shape, np.int64)
        self.total = np.zeros((3, *self.shape))
        self.squares = np.zeros((3, *self.shape))

    def add(self, velocity: np.ndarray, valid: np.ndarray) -> None:
        values = np.where(valid, np.nan_to_num(velocity.astype(float)), 0.0)
        self.count += valid
        self.total += values
        self.squares += values**2

    def write(self, group) -> None:
        n = np.maximum(self.count, 1)
        mean = self.total / n
        var = (self.squares - n * mean**2) / np.maximum(self.count - 1, 1)
        rms = np.sqrt(np.maximum(var, 0.0))
        mean[:, self.count == 0] = np.nan
        rms[:, self.count < 2] = np.nan
        dims = ["z", "y", "x"]
        for k, comp in enumerate(COMPONENTS):
            group.create_array(f"{comp}_mean", data=mean[k].astype(np.float32),
                               fill_value=np.nan, dimension_names=dims, attributes={
                                   "units": "m/s", "long_name": f"ensemble mean of {comp} "
                                   "over the valid vectors"})
            group.create_array(f"{comp}_rms", data=rms[k].astype(np.float32),
                               fill_value=np.nan, dimension_names=dims, attributes={
                                   "units": "m/s", "long_name": f"RMS fluctuation of {comp} "
                                   "over the valid vectors"})
        # a lost chunk reads as unknown (NaN, -1), not as a valid zero mean (zarr's 0)
        group.create_array("valid_count", data=self.count, fill_value=-1,
                           dimension_names=dims,
                           attributes={"long_name": "valid vectors in the ensemble"})

