"""A batch's time series (``timeseries.zarr``): a probe's velocity over time, the valid
fraction of each pair, and the summary figures ``plenocl run`` writes."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_figure
from .data import AXES, store_field
from .profiles import COLOURS, profile_figure
from .slices import slices_figure

#: The summary figures of a batch run, by file name (in ``OUT/figures``).
SUMMARY_FIGURES = ("mean_slices.png", "mean_profile.png", "valid_fraction.png",
                   "probe.png")


def _time_axis(arrays: dict, attrs: dict) -> tuple[np.ndarray, str]:
    """The pairs' times and their axis label (s, or pair numbers)."""
    units = attrs.get("arrays", {}).get("time", {}).get("units", "s")
    return np.asarray(arrays["time"], float), "pair" if units == "pair" else "time (s)"


def nearest_vector(arrays: dict, point: Sequence[float] | None) -> tuple[int, int, int]:
    """``(iz, iy, ix)`` of the vector nearest ``point`` (x, y, z mm; default: the grid's
    centre); a point outside the grid is refused with the grid's extent."""
    coords = [np.asarray(arrays[a], float) for a in AXES]
    if point is None:
        point = [float(np.median(c)) for c in coords]
    if len(point) != 3:
        raise ValueError(f"a probe is a point (x, y, z) in mm, got {point!r}")
    index = []
    for name, c, p in zip(AXES, coords, point):
        half = 0.5 * abs(float(c[1] - c[0])) if len(c) > 1 else 0.5
        if not c.min() - half <= p <= c.max() + half:
            raise ValueError(f"the probe's {name} = {p:g} mm is outside the vectors, which "
                             f"span {c.min():g} to {c.max():g} mm")
        index.append(int(np.argmin(np.abs(c - p))))
    ix, iy, iz = index
    return iz, iy, ix


def probe_figure(path: str | Path, arrays: dict, attrs: dict | None = None,
                 point: Sequence[float] | None = None) -> Path:
    """u, v, w over the pairs at the vector nearest ``point`` (x, y, z mm): filled
    markers where valid, open where the vector was replaced or missing; the run's mean
    as a line."""
    iz, iy, ix = nearest_vector(arrays, point)
    times, label = _time_axis(arrays, attrs or {})
    valid = np.asarray(arrays["valid"])[:, iz, iy, ix].astype(bool)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.8), constrained_layout=True)
    for comp in "uvw":
        series = np.asarray(arrays[comp], float)[:, iz, iy, ix]
        colour = COLOURS[comp]
        ax.plot(times, series, "-", color=colour, lw=0.8, alpha=0.6)
        ax.plot(times[valid], series[valid], "o", color=colour, ms=4, label=comp)
        ax.plot(times[~valid], series[~valid], "o", mfc="none", color=colour, ms=4)
        mean = arrays.get(f"{comp}_mean")
        if mean is not None and np.isfinite(mean[iz, iy, ix]):
            ax.axhline(float(mean[iz, iy, ix]), color=colour, lw=0.8, ls="--")
    where = ", ".join(f"{a} = {float(arrays[a][i]):.2f}" for a, i in zip(AXES, (ix, iy, iz)))
    ax.set_title(f"probe at {where} mm (open: not valid; dashed: the run's mean)",
                 fontsize=9)
    ax.set_xlabel(label)
    ax.set_ylabel("velocity (m/s)")
    ax.legend(fontsize=8, frameon=False, ncol=3)
    return save_figure(fig, path)


def valid_fraction_figure(path: str | Path, arrays: dict, attrs: dict | None = None) -> Path:
    """The share of valid vectors in each pair, with the run's median."""
    valid = np.asarray(arrays["valid"], bool)
    fraction = valid.reshape(len(valid), -1).mean(axis=1)
    pairs = np.asarray(arrays["pair"])
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.4), constrained_layout=True)
    ax.bar(pairs, 100 * fraction, color="tab:blue", width=0.8)
    ax.axhline(100 * float(np.median(fraction)), color="k", lw=0.8, ls="--",
               label=f"median {100 * float(np.median(fraction)):.0f} %")
    ax.set_ylim(0, 105)
    ax.set_xlabel("pair")
    ax.set_ylabel("valid vectors (%)")
    ax.set_title(f"valid vectors per pair ({valid[0].size} vectors each)", fontsize=9)
    ax.legend(fontsize=8, frameon=False, loc="lower right")
    return save_figure(fig, path)


def batch_figures(store: str | Path, out: str | Path) -> list[Path]:
    """The summary figures of a batch's store, written into the folder ``out``
    (:data:`SUMMARY_FIGURES`): the mean field's speed on three planes normal to z with
    its vectors, its mean profile along z, each pair's valid fraction and the velocity
    over time at the centre of the grid."""
    from ..io.zarrstore import read_store

    arrays, attrs = read_store(store)
    out = Path(out)
    mean = store_field(arrays, rotation_deg=float(attrs.get("rotation_deg", 0.0)))
    written = []
    if mean.valid.any():
        written.append(slices_figure(out / "mean_slices.png", mean, "z", "speed"))
        written.append(profile_figure(out / "mean_profile.png", mean, "z"))
    written.append(valid_fraction_figure(out / "valid_fraction.png", arrays, attrs))
    written.append(probe_figure(out / "probe.png", arrays, attrs))
    return written
