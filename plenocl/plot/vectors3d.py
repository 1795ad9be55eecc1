"""3-D figures of a field: its vectors thinned so they read, with a labelled reference
arrow (the paper's Fig. 14), and iso-surfaces of a scalar (Figs. 15 and 17)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_figure
from .data import VectorData
from .planes import reference_speed, thinning_step
from .slices import widened

#: Arrows of a 3-D vector figure, at most.
MAX_ARROWS = 300


def thinned(data: VectorData, max_arrows: int = MAX_ARROWS):
    """The vectors kept by thinning: one in ``step`` along every axis, the smallest step
    that leaves at most ``max_arrows`` valid ones. Returns ``(points (n, 3) mm,
    vectors (n, 3), step)``."""
    step = thinning_step(data.shape, max_arrows, int(data.valid.sum()))
    zz, yy, xx = np.meshgrid(data.z, data.y, data.x, indexing="ij")
    sl = (slice(None, None, step),) * 3
    keep = data.valid[sl]
    while keep.sum() > max_arrows:  # thinning on a grid rounds; never more than asked
        step += 1
        sl = (slice(None, None, step),) * 3
        keep = data.valid[sl]
    points = np.column_stack([a[sl][keep] for a in (xx, yy, zz)])
    vectors = np.column_stack([c[sl][keep] for c in data.velocity])
    return points, vectors, step


def _axes3d(data: VectorData, size=(7.2, 5.6)):
    plt = pyplot()
    fig = plt.figure(figsize=size)
    ax = fig.add_subplot(projection="3d")
    _label3d(ax, data)
    return plt, fig, ax


def _label3d(ax, data: VectorData) -> None:
    ax.set_xlabel(data.label("x"), labelpad=8, fontsize=8)
    ax.set_ylabel(data.label("y"), labelpad=8, fontsize=8)
    ax.set_zlabel(data.label("z"), labelpad=8, fontsize=8)
    ax.tick_params(labelsize=7)
    for name in "xyz":
        c = data.coordinate(name)
        getattr(ax, f"set_{name}lim")(float(np.min(c)), float(np.max(c)) + (
            0.0 if len(c) > 1 else 1.0))
    ax.set_box_aspect([float(np.ptp(data.coordinate(a))) or 1.0 for a in "xyz"], zoom=0.85)


def _reference_arrow(ax, data: VectorData, ref: float, scale: float) -> None:
    """A reference arrow along x at the top corner with its label before its tail
    (clear of the arrow and its head)."""
    x0, y0, z0 = float(np.min(data.x)), float(np.min(data.y)), float(np.max(data.z))
    length = ref * scale
    ax.quiver([x0], [y0], [z0], [length], [0], [0], color="k", linewidth=1.8,
              arrow_length_ratio=0.25)
    # +x runs to the right in the default view: the label ends left of the tail
    ax.text(x0, y0, z0, f"{ref:g} {data.unit}  ", fontsize=8, ha="right", va="center")


def arrow_scale(data: VectorData, vectors: np.ndarray, step: int) -> tuple[float, float]:
    """A round reference speed for ``vectors`` and the arrows' scale (mm per unit of
    velocity) that draws it 0.9 of the thinned vectors' spacing long."""
    ref = reference_speed(np.linalg.norm(vectors, axis=1))
    spacing = step * min((abs(float(c[1] - c[0])) for c in (data.x, data.y, data.z)
                          if len(c) > 1), default=1.0)
    return ref, 0.9 * spacing / ref


def vectors_figure(path: str | Path, data: VectorData, colour: str = "speed",
                   max_arrows: int = MAX_ARROWS, title: str | None = None) -> Path:
    """The field's vectors in 3-D, thinned to at most ``max_arrows``, to scale, coloured
    by ``colour`` (a component or the speed) with a colour bar, and a reference arrow
    labelled before its tail."""
    plt, fig, ax = _axes3d(data)
    points, vectors, step = thinned(data, max_arrows)
    if not len(points):
        raise ValueError("the field has no valid vector to draw")
    ref, scale = arrow_scale(data, vectors, step)
    mags = np.linalg.norm(vectors, axis=1)
    col = mags if colour == "speed" else vectors[:, "uvw".index(colour)]
    lo, hi = (-1, 1) if not col.size else (float(np.percentile(col, 2)),
                                            float(np.percentile(col, 98)))
    cmap = "coolwarm" if colour != "speed" and lo < 0 < hi else "viridis"
    if cmap == "coolwarm":
        lo, hi = -max(-lo, hi), max(-lo, hi)
    norm = plt.Normalize(*widened(lo, hi))
    rgba = plt.get_cmap(cmap)(norm(col))
    ax.quiver(*points.T, *(vectors * scale).T, colors=np.concatenate(
        [rgba, np.repeat(rgba, 2, axis=0)]), linewidth=1.3, arrow_length_ratio=0.3)
    _reference_arrow(ax, data, ref, scale)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, shrink=0.6, pad=0.12,
                 label=data.label(colour))
    count = f"{len(points)} vectors ({_every(step)}), to scale"
    ax.set_title(f"{title}\n{count}" if title else count, fontsize=9)
    return save_figure(fig, path)


def _every(step: int) -> str:
    return "every vector" if step == 1 else f"one vector in {step} along each axis"


def _filled(values: np.ndarray) -> np.ndarray:
    """``values`` with NaN replaced by the nearest finite value (marching cubes needs a
    value everywhere; surfaces near invalid vectors follow their neighbours)."""
    from scipy.ndimage import distance_transform_edt

    bad = ~np.isfinite(values)
    if not bad.any() or bad.all():
        return np.nan_to_num(values)
    idx = distance_transform_edt(bad, return_distances=False, return_indices=True)
    return values[tuple(idx)]


#: What an iso-surface figure of a field with invalid vectors says of its gaps.
SURFACE_GAPS = "no surface farther than half a vector spacing from a valid vector"


def isosurfaces(values: np.ndarray, levels: Sequence[float], data: VectorData):
    """Triangles ``(n, 3, 3)`` mm (x, y, z) of the iso-surface of ``values``
    ``(nz, ny, nx)`` at each level (an empty array where it does not cross it); none
    whose nearest vector is not valid (finite): the NaN filled for marching cubes drew
    surfaces across masked regions."""
    from skimage.measure import marching_cubes

    values = np.asarray(values, float)
    filled, near = _filled(values), np.isfinite(values)
    near = None if near.all() else near
    out = []
    for level in levels:
        if not (np.nanmin(filled) < level < np.nanmax(filled)) or min(filled.shape) < 2:
            out.append(np.zeros((0, 3, 3)))
            continue
        verts, faces, _, _ = marching_cubes(filled, level=float(level))
        if near is not None:  # each triangle's nearest vector must hold data
            centre = np.rint(verts[faces].mean(axis=1)).astype(int)
            centre = np.clip(centre, 0, np.array(near.shape) - 1)
            faces = faces[near[tuple(centre.T)]]
        mm = np.column_stack([np.interp(verts[:, k], np.arange(len(c)), c)
                              for k, c in ((2, data.x), (1, data.y), (0, data.z))])
        out.append(mm[faces])
    return out


def isosurface_figure(path: str | Path, data: VectorData, values: np.ndarray,
                      levels: Sequence[float], value_label: str,
                      title: str | None = None, arrows: int = 0) -> Path:
    """Iso-surfaces of ``values`` at ``levels`` (semi-transparent, one colour each, in
    a legend with their values); with ``arrows``, the field's vectors thinned to at most
    that many drawn over them in black, to scale, with a reference arrow (the paper's
    Fig. 14)."""
    from matplotlib.patches import Patch
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    plt, fig, ax = _axes3d(data)
    colours = plt.get_cmap("plasma")(np.linspace(0.15, 0.85, max(len(levels), 1)))
    handles = []
    for level, tris, colour in zip(levels, isosurfaces(values, levels, data), colours):
        if len(tris):
            faces = np.tile(colour, (len(tris), 1))
            ax.add_collection3d(Poly3DCollection(tris, facecolors=faces, edgecolors=faces,
                                                 linewidths=0, alpha=0.45, shade=True))
        handles.append(Patch(color=colour, label=f"{level:.4g}"
                             + ("" if len(tris) else " (not reached)")))
    ax.legend(handles=handles, title=value_label, fontsize=7, title_fontsize=8,
              loc="upper left", bbox_to_anchor=(0.0, 1.0))
    if arrows:
        points, vectors, step = thinned(data, arrows)
        if len(points):
            ref, scale = arrow_scale(data, vectors, step)
            ax.quiver(*points.T, *(vectors * scale).T, color="k", linewidth=0.7,
                      arrow_length_ratio=0.3)
            _reference_arrow(ax, data, ref, scale)
            title = (title or "") + f"\n{len(points)} vectors ({_every(step)}), to scale"
    ax.set_title(title or f"iso-surfaces of {value_label}", fontsize=9)
    if not np.all(np.isfinite(values)):
        fig.text(0.01, 0.01, SURFACE_GAPS, fontsize=7, color="0.35")
    return save_figure(fig, path)


def default_levels(values: np.ndarray, count: int = 3) -> list[float]:
    """``count`` levels spread between the 10th and 90th percentiles of the finite
    values, rounded to 2 significant figures."""
    finite = np.asarray(values, float)[np.isfinite(values)]
    if not finite.size:
        return []
    lo, hi = np.percentile(finite, [10, 90])
    return [float(f"{v:.2g}") for v in np.linspace(lo, hi, count + 2)[1:-1]]
