"""The mean profile of a field along an axis: each plane normal to it averaged over
its valid vectors (the paper's Fig. 19)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_figure
from .data import VectorData, check_axis, check_component

#: A colour per component, the same in every figure.
COLOURS = {"u": "tab:blue", "v": "tab:red", "w": "tab:green", "speed": "k"}


def plane_means(values: np.ndarray, axis: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, standard deviation and count of the finite values of ``(nz, ny, nx)`` over
    each plane normal to ``axis`` (NaN for a plane without any)."""
    along = {"z": 0, "y": 1, "x": 2}[check_axis(axis)]
    moved = np.moveaxis(np.asarray(values, float), along, 0).reshape(values.shape[along], -1)
    ok = np.isfinite(moved)
    count = ok.sum(axis=1)
    total = np.where(ok, moved, 0.0).sum(axis=1)
    mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    sq = np.where(ok, (moved - mean[:, None]) ** 2, 0.0).sum(axis=1)
    std = np.where(count > 0, np.sqrt(sq / np.maximum(count, 1)), np.nan)
    return mean, std, count


def profile_figure(path: str | Path, data: VectorData, axis: str = "z",
                   components: Sequence[str] = ("u", "v", "w")) -> Path:
    """The plane means of ``components`` along ``axis`` against its coordinate (on the
    vertical axis), error bars the spread over each plane, and the valid vectors per
    plane beside it."""
    axis = check_axis(axis)
    plt = pyplot()
    fig, (ax, ax_n) = plt.subplots(1, 2, figsize=(6.4, 4.4), sharey=True,
                                   gridspec_kw={"width_ratios": (3, 1)},
                                   constrained_layout=True)
    coord = data.coordinate(axis)
    for comp in components:
        mean, std, count = plane_means(data.component(check_component(comp)), axis)
        ax.errorbar(mean, coord, xerr=std, fmt="o-", ms=4, capsize=2, lw=1,
                    color=COLOURS[comp], label=data.label(comp).rsplit(" (", 1)[0])
    ax.axvline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel(f"plane mean ± spread over the plane ({data.unit})")
    ax.set_ylabel(data.label(axis))
    ax.legend(fontsize=8, frameon=False)
    ax.set_title(f"mean profile along {axis}", fontsize=10)
    ax_n.barh(coord, count / max(int(np.prod(data.shape)) // len(coord), 1), height=(
        abs(float(coord[1] - coord[0])) * 0.8 if len(coord) > 1 else 0.8), color="0.5")
    ax_n.set_xlim(0, 1.05)
    ax_n.set_xlabel("valid fraction")
    return save_figure(fig, path)


__all__ = ["COLOURS", "plane_means", "profile_figure"]
