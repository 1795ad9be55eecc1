"""NumPy reference of the weighting function (paper §III.A, docs/design.md §5), written for clarity.

A voxel's column of the weight matrix, literally the paper's four steps:

1. sample the main-lens aperture on a plaid ``(u, v)`` grid a little finer than one
   pixel's footprint on the aperture (``p_px d / f_ml``), keeping samples inside the
   circular aperture (a hexagonal array: a rhombic grid along its lattice's two steps,
   docs/design.md §5.3);
2. each sample meets the microlens-array plane at ``x = u (1 - 1/α) + X'/α``; in
   microlens index units it falls between four microlens centres, which get the
   bilinear weights ``(1 - t_x)(1 - t_y) … t_x t_y`` (``lens_weights="extent"``: ``t``
   replaced by the share of a box as wide as the voxel, in lens units, centred on the
   point, that lies in the upper lens's cell);
3. behind each of those microlenses the sample's ``(u, v)`` lands at the sensor point
   ``c_k - u f_ml / d`` (``c_k``: that lens's calibrated image centre), between four
   pixel centres with bilinear weights ``(1 - t_u)(1 - t_v) … t_u t_v``;
4. the sixteen products accumulate onto pixels and are normalised so that the voxel's
   weights over *all* samples sum to one. Products landing off the sensor, on a missing
   (NaN) microlens or outside the array are lost, so a voxel's weights sum to at most 1.

Microlens index units come from an affine map fitted to the calibrated centres
(:func:`plenocl.projection.weighting.lens_index_map`); the aperture sampling and that map are shared
definitions, imported from :mod:`plenocl.projection.weighting`. The OpenCL projector
(``kernels/projector.cl``) evaluates the same model matrix-free; the tests compare the two.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..grid import Grid
from ..projection.weighting import (
    DEFAULT_OVERSAMPLE,
    DEFAULT_SHEAR_TOL,
    ApertureGrid,
    depth_coefficients,
    lens_index_map,
)

__all__ = ["DEFAULT_OVERSAMPLE", "DEFAULT_SHEAR_TOL", "ApertureGrid", "lens_index_map",
           "lens_pixels", "lit_lenses", "voxel_weights", "weight_matrix"]

def _bilinear_corners(f: np.ndarray):
    """Lower integer neighbour and fractional distance, as the paper's floor/ceil."""
    f0 = np.floor(f)
    return f0.astype(np.int64), f - f0


def _box_share(t: np.ndarray, width: float) -> np.ndarray:
    """The share of a box ``width`` lens units wide centred at ``k0 + t`` that lies in lens
    ``k0 + 1``'s cell ``[k0 + 1/2, k0 + 3/2]`` (``width`` at most 1; ``t`` itself at 1)."""
    return np.clip(0.5 + (t - 0.5) / width, 0.0, 1.0)


def voxel_weights(camera: Camera, grid: Grid, iz: int, iy: int, ix: int,
                  oversample: float = DEFAULT_OVERSAMPLE,
                  shear_tol: float = DEFAULT_SHEAR_TOL,
                  lens_weights: str = "extent") -> tuple[np.ndarray, np.ndarray]:
    """One voxel's weights: sorted flat pixel indices (int64) and weights (float64).

    Parameters
    ----------
    camera, grid
        The camera (its ``microlens_centers`` are used) and the voxel grid.
    iz, iy, ix
        The voxel, ``vol[iz, iy, ix]``.
    oversample
        Aperture samples per pixel footprint on the aperture, per axis.
    shear_tol
        See :func:`lens_index_map`.
    lens_weights
        ``"extent"`` (default: the voxel's width, as :class:`plenocl.Projector`'s
        default) or ``"paper"`` (bilinear).

    Returns
    -------
    indices, weights
        Pixels ``row * W + col`` with a non-zero weight, in increasing order.
    """
    camera = camera.on_lens_lattice()  # a hexagonal array: its axial lattice
    # Everything lateral below is in the grid's frame (rotated by grid.rotation_deg about
    # the optical axis); the main lens maps x -> X' isotropically, so the image point of
    # a frame point is in the frame too. Only step 3 needs the sensor's axes.
    centre = [grid.axis_centers("x")[ix], grid.axis_centers("y")[iy], grid.axis_centers("z")[iz]]
    xp, yp, sip = camera.image_points(centre)[0]
    alpha = sip / camera.exit_pupil_distance_mm  # = camera.alpha(z): sip is d' (image_points)
    # Step 1: aperture samples inside the circle, along the frame's axes: the plaid grid,
    # or along a hexagonal lattice's two steps (its lens map is triangular).
    lens_map = lens_index_map(camera, shear_tol, grid.rotation_deg)
    ap = ApertureGrid.for_lattice(camera, oversample, grid.rotation_deg,
                                  *lens_map.aperture_lattice())
    u, v = ap.frame_uv().T
    # Step 2: the array-plane point, in lens index units, and its four lenses.
    kxf, kyf = lens_map(u * (1 - 1 / alpha) + xp / alpha, v * (1 - 1 / alpha) + yp / alpha)
    u, v = ap.sensor_uv().T  # the same samples on the sensor's axes
    kx0, tx = _bilinear_corners(kxf)
    ky0, ty = _bilinear_corners(kyf)
    if lens_weights == "extent":  # the voxel's width in lens indices: |G|'s row sums
        g = depth_coefficients(camera, grid, lens_map, ap)[iz, 0:4].reshape(2, 2)
        width = np.minimum(np.abs(g).sum(axis=1), 1.0)
        tx, ty = _box_share(tx, width[0]), _box_share(ty, width[1])
    pix, wts = [], []
    for dkx in (0, 1):
        for dky in (0, 1):
            w_lens = (tx if dkx else 1 - tx) * (ty if dky else 1 - ty)
            p, w = _lens_to_pixels(camera, kx0 + dkx, ky0 + dky, u, v, w_lens)
            pix.append(p)
            wts.append(w)
    # Step 4: accumulate and normalise by the number of aperture samples.
    idx, inverse = np.unique(np.concatenate(pix), return_inverse=True)
    total = np.bincount(inverse, weights=np.concatenate(wts), minlength=len(idx)) / len(u)
    keep = total > 0
    return idx[keep], total[keep]


def _lens_to_pixels(camera: Camera, kx, ky, u, v, w_lens):
    """Step 3: pixels and weights of the samples behind lenses ``(kx, ky)``."""
    cols, rows = camera.ml_count
    width, height = camera.pixels
    inside = (kx >= 0) & (kx < cols) & (ky >= 0) & (ky < rows)
    centre = camera.microlens_centers[np.clip(ky, 0, rows - 1), np.clip(kx, 0, cols - 1)]
    inside &= np.isfinite(centre).all(axis=-1)
    g = camera.ml_focal_length_mm / (camera.exit_pupil_distance_mm * camera.pixel_pitch_mm)
    c0, tu = _bilinear_corners(np.where(inside, centre[:, 0] - u * g, 0.0))
    r0, tv = _bilinear_corners(np.where(inside, centre[:, 1] - v * g, 0.0))
    pix, wts = [], []
    for dc in (0, 1):
        for dr in (0, 1):
            col, row = c0 + dc, r0 + dr
            w = w_lens * (tu if dc else 1 - tu) * (tv if dr else 1 - tv)
            ok = inside & (col >= 0) & (col < width) & (row >= 0) & (row < height) & (w > 0)
            pix.append(row[ok] * width + col[ok])
            wts.append(w[ok])
    return np.concatenate(pix), np.concatenate(wts)


def lens_pixels(camera: Camera, kx: int, ky: int,
                oversample: float = DEFAULT_OVERSAMPLE) -> np.ndarray:
    """Flat pixel indices (sorted int64) that lens ``(kx, ky)``'s aperture samples reach
    with a positive weight (step 3 for every sample, lens weight 1)."""
    ap = ApertureGrid.for_camera(camera, oversample)
    i, j = ap.samples()
    u, v = (i - ap.center) * ap.step, (j - ap.center) * ap.step
    k = np.ones(len(u), np.int64)
    pix, _ = _lens_to_pixels(camera, kx * k, ky * k, u, v, np.ones(len(u)))
    return np.unique(pix)


def lit_lenses(camera: Camera, image: np.ndarray, threshold: float = 0.0,
               oversample: float = DEFAULT_OVERSAMPLE) -> np.ndarray:
    """Bool per lens (flat, row-major): does a pixel it reaches exceed ``threshold``?

    The exact set; :meth:`plenocl.Projector.lit_lenses` returns a superset of it.
    """
    cols, rows = camera.ml_count
    flat = np.asarray(image).ravel() > threshold
    return np.array([flat[lens_pixels(camera, kx, ky, oversample)].any()
                     for ky in range(rows) for kx in range(cols)], bool)


def weight_matrix(camera: Camera, grid: Grid, oversample: float = DEFAULT_OVERSAMPLE,
                  shear_tol: float = DEFAULT_SHEAR_TOL) -> np.ndarray:
    """The dense weight matrix ``(H * W, nz * ny * nx)`` (float64) for tiny cases.

    Column ``j`` is voxel ``j`` of ``vol.ravel()``; ``image.ravel() = A @ vol.ravel()``.
    """
    width, height = camera.pixels
    n_pix = width * height
    if n_pix * grid.size > 2e8:
        raise ValueError(f"a dense {n_pix} x {grid.size} matrix is too large; this reference "
                         "builder is for tiny cameras and grids")
    a = np.zeros((n_pix, grid.size))
    for col, (iz, iy, ix) in enumerate(np.ndindex(*grid.shape)):
        idx, w = voxel_weights(camera, grid, iz, iy, ix, oversample, shear_tol)
        a[idx, col] = w
    return a
