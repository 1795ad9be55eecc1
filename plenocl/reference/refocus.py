"""NumPy reference of the refocusing kernel (``kernels/lightfield.cl``), written for clarity.

Shift-and-add over the sub-aperture views, each sampled between microlenses with the
quadratic B-spline weights of the 3 x 3 nearest lenses (the same smoothing at every
sub-lens phase, so no plane is favoured); samples that are ``NaN`` or off the array carry
no weight and the sum is normalised by the weight that remains (docs/design.md §4). A
hexagonal array's views are staggered: lens ``(kx, ky)`` sits at ``kx + row_shift (ky mod
2)`` along its row, and each row's weights are taken from its own lens positions.
"""

from __future__ import annotations

import numpy as np

from ..lightfield import output_lens_coordinates

__all__ = ["output_lens_coordinates", "refocus_views"]


def refocus_views(views: np.ndarray, shifts: np.ndarray, supersample: int = 1,
                  row_shift: float = 0.0) -> np.ndarray:
    """Refocus a light field stored as sub-aperture views.

    Parameters
    ----------
    views
        ``(nuv, ny, nx)`` light-field samples: view ``n`` holds plaid sample ``(u_n, v_n)``
        of every microlens; ``NaN`` where the sample does not exist.
    shifts
        ``(planes, nuv, 2)`` shift of each view in lens units ``(da, db)`` of the array's
        frame, ``(1 - 1/α) L⁻¹ (u_n, v_n)``.
    supersample
        Output pixels per microlens along each axis.
    row_shift
        Where the odd rows' lenses sit along the row (lenses): 0 for a rectangular
        array, the odd rows' shift (±0.5) for a hexagonal one.

    Returns
    -------
    numpy.ndarray
        ``(planes, ny * S, nx * S)`` float64 refocused images (0 where nothing is seen).
    """
    views = np.asarray(views, dtype=np.float64)
    shifts = np.asarray(shifts, dtype=np.float64).reshape(-1, views.shape[0], 2)
    nuv, ny, nx = views.shape
    kx, ky = output_lens_coordinates(nx, ny, supersample)
    out = np.zeros((len(shifts), len(ky), len(kx)))
    for p, plane_shifts in enumerate(shifts):
        acc = np.zeros((len(ky), len(kx)))
        wsum = np.zeros_like(acc)
        for n in range(nuv):
            x = kx[None, :] + plane_shifts[n, 0]
            y = ky[:, None] + plane_shifts[n, 1]
            _bspline_accumulate(views[n], x, y, acc, wsum, row_shift)
        out[p] = np.divide(acc, wsum, out=np.zeros_like(acc), where=wsum > 0)
    return out


def _bspline_weights(d: np.ndarray) -> list[np.ndarray]:
    """Quadratic B-spline weights of the nodes -1, 0, +1 around the nearest node, for
    offsets ``d`` in [-0.5, 0.5] from it."""
    return [0.5 * (0.5 - d) ** 2, 0.75 - d**2, 0.5 * (0.5 + d) ** 2]


def _bspline_accumulate(view: np.ndarray, x: np.ndarray, y: np.ndarray,
                        acc: np.ndarray, wsum: np.ndarray, row_shift: float = 0.0) -> None:
    """Add the 3 x 3 quadratic B-spline taps of ``view`` at ``(x, y)`` that exist to
    ``acc``/``wsum``: the three rows nearest ``y``, in each the three lenses nearest ``x``
    (an odd row's lenses sit ``row_shift`` along it)."""
    ny, nx = view.shape
    x, y = np.broadcast_arrays(x, y)
    cy = np.floor(y + 0.5).astype(np.int64)
    wy = _bspline_weights(y - cy)
    for b in range(3):
        yi = cy + b - 1
        x_row = x - row_shift * (yi % 2)
        cx = np.floor(x_row + 0.5).astype(np.int64)
        wx = _bspline_weights(x_row - cx)
        for a in range(3):
            xi, w = cx + a - 1, wx[a] * wy[b]
            inside = (xi >= 0) & (yi >= 0) & (xi < nx) & (yi < ny)
            value = view[np.clip(yi, 0, ny - 1), np.clip(xi, 0, nx - 1)]
            ok = inside & np.isfinite(value) & (w > 0)
            acc += np.where(ok, w * np.where(ok, value, 0.0), 0.0)
            wsum += np.where(ok, w, 0.0)
