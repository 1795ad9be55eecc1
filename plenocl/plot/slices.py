"""Contour slices of a field with its in-plane vectors (the paper's Figs. 16 and 18),
and measured beside true with their difference (the demo's comparison)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_figure
from .data import VectorData, check_axis
from .planes import (
    IN_PLANE,
    in_plane_components,
    plane_indices,
    reference_speed,
    take_plane,
    thinning_step,
)

#: Arrows per side of a slice, at most.
ARROWS_PER_SIDE = 12
#: What the grey areas of a figure are: no vector, or (derivatives) no whole stencil.
VECTOR_GAPS = "grey: no valid vector"
DERIVATIVE_GAPS = "grey: no valid vector there (derivatives use no invalid neighbour)"


def colour_limits(*fields: np.ndarray, symmetric: bool = False) -> tuple[float, float]:
    """A colour range the fields share, their 1st to 99th percentiles (a few outliers
    saturate instead of flattening the rest); symmetric about zero if asked."""
    both = np.concatenate([np.ravel(f)[np.isfinite(np.ravel(f))] for f in fields])
    if not both.size:
        return (-1.0, 1.0) if symmetric else (0.0, 1.0)
    if symmetric:
        lim = float(np.percentile(np.abs(both), 99)) or 1.0
        return -lim, lim
    lo, hi = (float(v) for v in np.percentile(both, [1, 99]))
    return widened(lo, hi)


def widened(lo: float, hi: float) -> tuple[float, float]:
    """``(lo, hi)``, or a range of ±5 % about it where the values are (nearly) one: a
    uniform field gets one colour and readable ticks."""
    if hi - lo > 1e-6 * max(abs(lo), abs(hi)) and hi > lo:
        return lo, hi
    pad = 0.05 * abs(lo) or 0.5
    return lo - pad, lo + pad


def _panel_grid(n: int, columns: int, width: float, height: float):
    plt = pyplot()
    fig, axes = plt.subplots(n, columns, figsize=(width * columns, height * n + 0.8),
                             squeeze=False, constrained_layout=True)
    return plt, fig, axes


def _panel_shape(data: VectorData, axis: str) -> tuple[float, float]:
    """Width and height (inches) of one panel that keeps the plane's aspect ratio."""
    return 3.6, 2.4 * _aspect(data, axis) + 0.75


def _aspect(data: VectorData, axis: str) -> float:
    """A plane's height over its width (within 0.3 to 1.5)."""
    h, v = (np.ptp(data.coordinate(a)) or 1.0 for a in IN_PLANE[axis])
    return float(np.clip(v / h, 0.3, 1.5))


def contour(ax, h, v, values, limits, cmap: str):
    """Filled contours of ``values`` ``(vertical, horizontal)`` on the plane, on a grey
    background where there is no valid vector; a plane one vector thin along either
    axis (a thin volume's field), which has no contours, as cells of the same colours."""
    ax.set_facecolor("0.85")
    from matplotlib.ticker import MaxNLocator

    levels = MaxNLocator(nbins=14).tick_values(*limits)
    shown = np.ma.masked_invalid(np.clip(values, levels[0], levels[-1]))
    if min(np.shape(values)) < 2:
        from matplotlib.colors import BoundaryNorm
        from matplotlib.pyplot import get_cmap

        norm = BoundaryNorm(levels, get_cmap(cmap).N)
        step = _spacing(h) or _spacing(v) or 1.0
        return ax.pcolormesh(_cell_edges(h, step), _cell_edges(v, step), shown, cmap=cmap,
                             norm=norm, shading="flat")
    return ax.contourf(h, v, shown, levels=levels, cmap=cmap, extend="neither")


def _spacing(coords) -> float:
    """The spacing of a plane's vector coordinates (0 for a single one)."""
    c = np.asarray(coords, float)
    return float(np.median(np.abs(np.diff(c)))) if len(c) > 1 else 0.0


def _cell_edges(coords, step: float) -> np.ndarray:
    """The edges of the cells centred on ``coords``: half-way between neighbours, half
    a spacing beyond the ends (``step`` where a single coordinate has no neighbour)."""
    c = np.asarray(coords, float)
    half = 0.5 * (_spacing(c) or step)
    return np.concatenate([[c[0] - half], 0.5 * (c[1:] + c[:-1]), [c[-1] + half]])


def arrows(ax, h, v, comp_h, comp_v, unit: str, max_per_side: int = ARROWS_PER_SIDE,
           key: bool = True) -> None:
    """The in-plane vectors, thinned to at most ``max_per_side`` a side, to scale, with
    a reference arrow labelled beside it (above the panel, clear of the field)."""
    step = thinning_step(comp_h.shape, max_per_side**2)
    sl = (slice(None, None, step), slice(None, None, step))
    hh, vv = np.meshgrid(h, v)
    mag = np.hypot(comp_h, comp_v)
    ref = reference_speed(mag[sl])
    spacing = step * min(abs(float(np.diff(h[:2])[0])) if len(h) > 1 else 1.0,
                         abs(float(np.diff(v[:2])[0])) if len(v) > 1 else 1.0)
    q = ax.quiver(hh[sl], vv[sl], comp_h[sl], comp_v[sl], angles="xy", scale_units="xy",
                  scale=ref / (0.9 * spacing), width=0.005, headwidth=4, headlength=5,
                  color="k", pivot="middle")
    if key:
        ax.quiverkey(q, 0.80, 1.03, ref, f"{ref:g} {unit}", labelpos="E",
                     coordinates="axes", fontproperties={"size": 7})


def _where(data: VectorData, axis: str, pos: float) -> str:
    """``"x spanwise = 1.25 mm"`` (never ``-0.00``)."""
    return f"{data.label(axis).split(' (')[0]} = {round(float(pos), 2) + 0.0:.2f} mm"


def _style(ax, data: VectorData, axis: str, title: str) -> None:
    h_axis, v_axis = IN_PLANE[axis]
    ax.set_xlabel(data.label(h_axis), fontsize=8)
    ax.set_ylabel(data.label(v_axis), fontsize=8)
    ax.set_title(title, fontsize=8, loc="left")
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)


def slices_figure(path: str | Path, data: VectorData, axis: str = "z",
                  component: str = "speed", at: Sequence[float] | None = None,
                  count: int = 3, values: np.ndarray | None = None,
                  value_label: str | None = None, vectors: bool = True,
                  gap_note: str = VECTOR_GAPS) -> Path:
    """Contour slices normal to ``axis`` (the vector planes nearest ``at`` mm, or
    ``count`` spread evenly) of a component (or ``values`` ``(nz, ny, nx)`` named
    ``value_label``), with the in-plane vectors thinned and a labelled reference arrow;
    ``gap_note`` says what grey (NaN) areas are.
    """
    axis = check_axis(axis)
    if values is None:
        values, value_label = data.component(component), data.label(component)
    picks = plane_indices(data.coordinate(axis), at, count)
    width, _ = _panel_shape(data, axis)
    plt, fig, axes = _panel_grid(1, len(picks), width, width * _aspect(data, axis) + 0.4)
    limits = colour_limits(values)
    for col, k in enumerate(picks):
        ax = axes[0, col]
        h, v, ch, cv = in_plane_components(data, axis, k)
        filled = contour(ax, h, v, take_plane(values, axis, k), limits, "viridis")
        if vectors:
            arrows(ax, h, v, ch, cv, data.unit)
        pos = data.coordinate(axis)[k]
        _style(ax, data, axis, _where(data, axis, pos))
    fig.colorbar(filled, ax=axes, label=value_label, shrink=0.8)
    _note_gaps(fig, values, gap_note)
    return save_figure(fig, path)


def _note_gaps(fig, values: np.ndarray, note: str) -> None:
    """Say what the grey areas are, where there are any."""
    if not np.isfinite(values).all():
        fig.suptitle(note, fontsize=8)


def comparison_figure(path: str | Path, data: VectorData, measured: np.ndarray,
                      truth: np.ndarray, value_label: str, axis: str = "x",
                      count: int = 3, truth_label: str = "truth",
                      vectors: VectorData | None = None,
                      gap_note: str = VECTOR_GAPS) -> Path:
    """Measured, true and their difference (measured - truth) on ``count`` vector planes
    normal to ``axis``: one colour scale for the first two, a symmetric one for the
    difference, the RMS difference of each plane in its title; ``vectors`` (the measured
    field) adds its in-plane arrows to the measured panels; ``gap_note`` says what grey
    (NaN) areas are."""
    axis = check_axis(axis)
    picks = plane_indices(data.coordinate(axis), None, count)
    plt, fig, axes = _panel_grid(len(picks), 3, *_panel_shape(data, axis))
    limits = colour_limits(measured, truth)
    error = measured - truth
    err_limits = colour_limits(error, symmetric=True)
    for row, k in enumerate(picks):
        h, v, ch, cv = in_plane_components(vectors or data, axis, k)
        pos = _where(data, axis, data.coordinate(axis)[k])
        filled = contour(axes[row, 0], h, v, take_plane(measured, axis, k), limits, "viridis")
        if vectors is not None:
            arrows(axes[row, 0], h, v, ch, cv, vectors.unit, key=row == 0)
        contour(axes[row, 1], h, v, take_plane(truth, axis, k), limits, "viridis")
        diff = take_plane(error, axis, k)
        rms = float(np.sqrt(np.nanmean(diff**2))) if np.isfinite(diff).any() else np.nan
        unit = value_label[value_label.rfind("(") + 1:-1] if "(" in value_label else ""
        err_fill = contour(axes[row, 2], h, v, diff, err_limits, "RdBu_r")
        for col, name in enumerate(("plenocl", truth_label, f"difference, RMS {rms:.3g} {unit}")):
            _style(axes[row, col], data, axis, f"{name}\n{pos}")
    fig.colorbar(filled, ax=axes[:, :2], label=value_label, shrink=0.8, location="left")
    fig.colorbar(err_fill, ax=axes[:, 2], label=f"plenocl - truth ({unit})", shrink=0.8)
    _note_gaps(fig, measured, gap_note)
    return save_figure(fig, path)
