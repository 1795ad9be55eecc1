"""Which planes of a vector grid a figure shows, and what lies in them: planes are
vector planes (the nearest to the position asked for), never a cut between two rows
of vectors, which would leave half a sheet blank."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .data import AXES, VectorData, check_axis

#: For the axis normal to a plane: the plane's (horizontal, vertical) axes.
IN_PLANE = {"z": ("x", "y"), "y": ("x", "z"), "x": ("y", "z")}


def plane_indices(coord: np.ndarray, at: Sequence[float] | None = None,
                  count: int = 3, unit: str = "mm") -> list[int]:
    """Indices of the planes nearest to the positions ``at`` (in ``unit``), or ``count``
    planes spread evenly over the grid, inside its faces where it has more than
    ``count + 1`` (a face's vectors and derivatives are the least certain); a position
    outside the grid is refused with the range the grid spans."""
    coord = np.asarray(coord, float)
    if at is None:
        first, last = (1, len(coord) - 2) if len(coord) > count + 1 else (0, len(coord) - 1)
        return [int(i) for i in np.unique(np.linspace(first, last,
                                                      min(count, len(coord))).round())]
    lo, hi = float(coord.min()), float(coord.max())
    half = 0.5 * abs(float(coord[1] - coord[0])) if len(coord) > 1 else 0.0
    out = []
    for pos in at:
        if not lo - half <= float(pos) <= hi + half:
            raise ValueError(f"a plane at {pos:g} {unit} is outside the grid, which spans "
                             f"{lo:g} to {hi:g} {unit} along this axis; give --at within it")
        out.append(int(np.argmin(np.abs(coord - float(pos)))))
    return out


def take_plane(values: np.ndarray, axis: str, index: int) -> np.ndarray:
    """The 2-D slice ``(vertical, horizontal)`` of a ``(nz, ny, nx)`` array on the plane
    normal to ``axis`` at ``index`` (:data:`IN_PLANE` order)."""
    along = {"z": 0, "y": 1, "x": 2}[check_axis(axis)]
    return np.take(values, index, axis=along)


def in_plane_components(data: VectorData, axis: str, index: int):
    """The plane's coordinates and in-plane vector components:
    ``(h, v, comp_h, comp_v)``, the components ``(vertical, horizontal)`` arrays, NaN
    where not valid."""
    h_axis, v_axis = IN_PLANE[check_axis(axis)]
    vel = np.where(data.valid, data.velocity, np.nan)
    comps = [take_plane(vel[AXES.index(a)], axis, index) for a in (h_axis, v_axis)]
    return data.coordinate(h_axis), data.coordinate(v_axis), comps[0], comps[1]


def thinning_step(shape: Sequence[int], max_arrows: int, valid_count: int | None = None) -> int:
    """The smallest stride (one vector in ``step`` along every axis) that leaves at most
    ``max_arrows`` of the grid ``shape`` (of which ``valid_count`` are drawn)."""
    if max_arrows < 1:
        raise ValueError(f"max_arrows must be at least 1, got {max_arrows}")
    total = int(np.prod(shape))
    drawn = total if valid_count is None else int(valid_count)
    step = 1
    while drawn * np.prod([int(np.ceil(n / step)) for n in shape]) / total > max_arrows:
        step += 1
    return step


def reference_speed(magnitudes: np.ndarray) -> float:
    """A round reference arrow for a set of arrow lengths: 1, 2 or 5 times a power of
    ten near their 90th percentile."""
    finite = np.asarray(magnitudes, float)
    finite = finite[np.isfinite(finite) & (finite > 0)]
    if not finite.size:
        return 1.0
    p90 = float(np.percentile(finite, 90))
    exp = np.floor(np.log10(p90))
    return float(min((m * 10**exp for m in (1, 2, 5, 10)), key=lambda r: abs(np.log(r / p90))))
