"""Predictor interpolation (with linear extrapolation) and volume deformation.

The predictor lives on a regular grid of window centres. It is resampled separably
(tensor-product natural cubic spline, or linear) onto any tensor grid of points - the
voxels of the volume or the window centres of the next pass - and *linearly
extrapolated* beyond the outermost centres: clamping there makes multi-pass iteration
diverge in a velocity gradient (docs/design.md §7). A linear predictor cannot follow curvature
between vectors and stalls the iteration in a vortex (about 2x the error of the cubic
one on a Lamb-Oseen core, measured). Volumes are deformed symmetrically,
``a'(p) = a(p - d(p)/2)`` and ``b'(p) = b(p + d(p)/2)``, by cubic B-spline interpolation
(spline filter once, then ``map_coordinates(order=3, prefilter=False)``) or trilinearly.
Arrays are in volume order ``(z, y, x)``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.interpolate import CubicSpline

#: Zero margin (voxels) around a volume before spline filtering: samples that fall
#: outside the volume read empty space, and the spline boundary condition is far away.
MARGIN = 8


def cubic_weights(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Matrix ``(len(target), len(source))`` of natural cubic-spline interpolation weights.

    Beyond the outermost source nodes the spline continues *linearly* with its end
    slope. Fewer than three nodes fall back to :func:`linear_weights`.
    """
    source = np.asarray(source, float)
    target = np.asarray(target, float)
    if len(source) < 3:
        return linear_weights(source, target)
    spline = CubicSpline(source, np.eye(len(source)), bc_type="natural", axis=0)
    slope = spline.derivative()
    weights = spline(np.clip(target, source[0], source[-1]))
    for end, beyond in ((source[0], target < source[0]), (source[-1], target > source[-1])):
        step = (target[beyond] - end)[:, None]
        weights[beyond] = spline(end)[None, :] + step * slope(end)[None, :]
    return weights


def linear_weights(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Matrix ``(len(target), len(source))`` of 1-D linear interpolation weights.

    ``source`` must be increasing. Points beyond the first or last source node are
    extrapolated linearly from the two outermost nodes; a single node gives a constant.
    """
    source = np.asarray(source, float)
    target = np.asarray(target, float)
    weights = np.zeros((len(target), len(source)))
    if len(source) == 1:
        weights[:, 0] = 1.0
        return weights
    left = np.clip(np.searchsorted(source, target, side="right") - 1, 0, len(source) - 2)
    t = (target - source[left]) / (source[left + 1] - source[left])
    rows = np.arange(len(target))
    weights[rows, left] = 1.0 - t
    weights[rows, left + 1] = t
    return weights


def resample(field: np.ndarray, source: tuple[np.ndarray, ...],
             target: tuple[np.ndarray, ...], kind: str = "cubic",
             dtype=np.float64) -> np.ndarray:
    """Resample ``field`` ``(C, nz, ny, nx)`` from grid ``source`` onto grid ``target``.

    Parameters
    ----------
    field
        Components on the tensor grid ``source = (z, y, x)`` (each 1-D, increasing).
    source, target
        1-D coordinate arrays ``(z, y, x)`` of the input and output grids.
    kind
        ``"cubic"`` (natural cubic spline) or ``"linear"`` inside the source grid; both
        extrapolate linearly outside it.
    dtype
        Output dtype.

    Returns
    -------
    numpy.ndarray
        ``(C, len(tz), len(ty), len(tx))``.
    """
    out = np.asarray(field, dtype)
    for axis in (3, 2, 1):
        w = axis_weights(kind, source[axis - 1], target[axis - 1]).astype(dtype)
        out = np.moveaxis(np.tensordot(out, w, axes=([axis], [1])), -1, axis)
    return np.ascontiguousarray(out)


def axis_weights(kind: str, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The weight matrix ``(len(target), len(source))`` of one axis of :func:`resample`:
    :func:`cubic_weights` for ``kind="cubic"``, :func:`linear_weights` for ``"linear"``."""
    if kind not in ("cubic", "linear"):
        raise ValueError(f"predictor interpolation must be 'cubic' or 'linear', got {kind!r}")
    return (cubic_weights if kind == "cubic" else linear_weights)(source, target)


def prepare(vol: np.ndarray, order: int) -> np.ndarray:
    """Zero-pad a volume by :data:`MARGIN` and, for B-spline orders 3 and 5, filter it once."""
    padded = np.pad(np.asarray(vol, np.float32), MARGIN)
    if order in (3, 5):
        return ndimage.spline_filter(padded, order=order, output=np.float32, mode="mirror")
    if order == 1:
        return padded
    raise ValueError(f"deform_order must be 1 (trilinear), 3 (cubic B-spline) or 5 "
                     f"(quintic B-spline), got {order}")


def deform(coeffs: np.ndarray, displacement: np.ndarray, factor: float, order: int,
           slab: int = 8) -> np.ndarray:
    """Sample a prepared volume at ``p + factor * displacement(p)`` for every voxel ``p``.

    Parameters
    ----------
    coeffs
        Output of :func:`prepare` (padded; spline coefficients for ``order=3``).
    displacement
        ``(3, nz, ny, nx)`` dense displacement ``(dz, dy, dx)`` in voxels.
    factor
        ``-0.5`` for the first volume, ``+0.5`` for the second (symmetric deformation).
    order
        1 (trilinear), 3 (cubic B-spline) or 5 (quintic B-spline).
    slab
        z-planes per ``map_coordinates`` call (bounds the coordinate memory).

    Returns
    -------
    numpy.ndarray
        float32 volume of shape ``displacement.shape[1:]``.
    """
    shape = displacement.shape[1:]
    out = np.empty(shape, np.float32)
    base = [np.arange(n, dtype=np.float64) + MARGIN for n in shape]
    for z0 in range(0, shape[0], slab):
        z1 = min(z0 + slab, shape[0])
        grid = np.meshgrid(base[0][z0:z1], base[1], base[2], indexing="ij")
        coords = np.stack(grid) + factor * displacement[:, z0:z1]
        out[z0:z1] = ndimage.map_coordinates(coeffs, coords, order=order, mode="constant",
                                             cval=0.0, prefilter=False)
    return out
