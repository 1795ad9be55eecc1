"""A reconstructed volume: its maximum-intensity projections along each axis, or
slices, in mm."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_figure
from .data import check_axis
from .planes import plane_indices

#: For each projection axis: the (horizontal, vertical) axes of the image.
_VIEWS = {"z": ("x", "y"), "y": ("x", "z"), "x": ("y", "z")}
_ARRAY_AXIS = {"z": 0, "y": 1, "x": 2}


def _centres(grid, shape) -> dict[str, np.ndarray]:
    """Voxel centres (mm) along each axis; voxel indices without a grid."""
    if grid is None:
        return {a: np.arange(n, dtype=float) for a, n in zip("zyx", shape)}
    return {a: np.linspace(lo, hi, n + 1)[:-1] + (hi - lo) / (2 * n)
            for a, (lo, hi), n in zip("zyx", (grid.z, grid.y, grid.x), shape)}


def _edges(c: np.ndarray) -> tuple[float, float]:
    """The outer faces of voxels centred at ``c``."""
    half = 0.5 * (float(c[1] - c[0]) if len(c) > 1 else 1.0)
    return float(c[0]) - half, float(c[-1]) + half


def _image(ax, image2d, h, v, limits):
    ext = (*_edges(h), *_edges(v))
    return ax.imshow(image2d, origin="lower", extent=ext, vmin=limits[0], vmax=limits[1],
                     cmap="magma", aspect="equal", interpolation="nearest")


def _finite(vol: np.ndarray) -> np.ndarray:
    """The volume with its NaN and Inf voxels drawn as no light, said (a single NaN made
    the colour scale's percentile NaN: a saturated figure, in silence)."""
    bad = ~np.isfinite(vol)
    if not bad.any():
        return vol
    warnings.warn(f"{int(bad.sum())} voxel(s) of the volume are NaN or Inf (of "
                  f"{vol.size}): drawn as no light; check the file", stacklevel=3)
    return np.where(bad, 0.0, vol)


def volume_figure(path: str | Path, vol: np.ndarray, grid=None, view: str = "projection",
                  axis: str = "z", at: Sequence[float] | None = None) -> Path:
    """``view="projection"``: the maximum intensity along z, y and x (three panels);
    ``"slices"``: three slices normal to ``axis`` (nearest ``at`` mm, or spread evenly).
    Axes in mm with a grid, else in voxels; one colour scale, 0 to the 99.5th
    percentile of what is shown."""
    vol, axis = _finite(np.asarray(vol, float)), check_axis(axis)
    c = _centres(grid, vol.shape)
    unit = "mm" if grid is not None else "voxel"
    if view == "projection":
        panels = [(a, vol.max(axis=_ARRAY_AXIS[a]), f"maximum along {a}") for a in "zyx"]
    elif view == "slices":
        picks = plane_indices(c[axis], at, 3, unit)
        panels = [(axis, np.take(vol, k, axis=_ARRAY_AXIS[axis]),
                   f"{axis} = {c[axis][k]:.2f} {unit}") for k in picks]
    else:
        raise ValueError(f"a volume's views are 'projection' and 'slices', not {view!r}")
    hi = max(float(np.percentile(p[1], 99.5)) for p in panels)  # of what is shown
    limits = (0.0, hi if hi > 0 else 1.0)
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(4.0 * len(panels), 3.8),
                             squeeze=False, constrained_layout=True)
    for ax, (normal, image2d, title) in zip(axes[0], panels):
        h, v = _VIEWS[normal]
        im = _image(ax, image2d, c[h], c[v], limits)
        ax.set_xlabel(f"{h} ({unit})", fontsize=8)
        ax.set_ylabel(f"{v} ({unit})", fontsize=8)
        ax.set_title(title, fontsize=8)
        ax.tick_params(labelsize=7)
    fig.colorbar(im, ax=axes, shrink=0.8, label="reconstructed intensity (image counts)")
    return save_figure(fig, path)
