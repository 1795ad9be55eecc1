"""The weighting model of docs/design.md §5 as plain NumPy tables, shared by every stage.

What a voxel's weight on a pixel depends on, apart from the kernels that sum it:

* :class:`ApertureGrid`: the plaid ``(u, v)`` sampling of the circular main-lens aperture
  (step 1 of the paper's weighting function);
* :class:`LensIndexMap` / :func:`lens_index_map`: array-plane millimetres to fractional
  microlens index (step 2);
* :func:`depth_coefficients`: per-depth affine coefficients of step 2 for a voxel grid,
  the table the projector kernels read (layout in ``kernels/projector.h``);
* :func:`lens_tables`: each lens's calibrated image centre, rounded and remainder
  (step 3);
* :func:`colour_stride`: the lens stride at which microlens images never share a pixel
  (the race-free forward scatter);
* :func:`check_depth_range` and :func:`check_field_of_view`: geometry that cannot image.

Nothing here touches a device. The NumPy reference (:mod:`plenocl.reference.weights`)
shares these definitions and evaluates the model voxel by voxel, for clarity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..grid import Grid
from ..optics.imaging import array_plane_positions
from ..optics.lattice import DEFAULT_SHEAR_TOL, lattice_fit, lattice_residual, rotation_matrix

#: Aperture samples per pixel footprint on the aperture (``p_px d / f_ml``), per axis.
DEFAULT_OVERSAMPLE = 1.25
__all__ = ["DEFAULT_OVERSAMPLE", "DEFAULT_SHEAR_TOL", "NO_LENS", "ApertureGrid", "LensIndexMap",
           "check_depth_range", "check_field_of_view", "colour_stride",
           "depth_coefficients", "lens_index_map", "lens_tables"]
#: Rounded-centre marker of a lens without a calibrated centre (PL_NO_LENS in projector.h).
NO_LENS = -(1 << 30)


@dataclass(frozen=True)
class ApertureGrid:
    """The plaid ``(u, v)`` sampling of the circular main-lens aperture (step 1).

    Sample ``(i, j)`` sits at ``(u, v) = R (i - c, j - c) step`` with ``c = (n - 1)/2``
    and ``R`` the rotation of the reconstruction frame (``rotation_deg``, the grid's; 0:
    the sensor's axes); only samples inside the aperture circle, ``|(i - c, j - c)| step
    <= radius``, are kept. In the frame's own coordinates the samples are the plain plaid
    grid ``(i - c, j - c) step``: a frame that follows the microlens rows samples the
    aperture along them too.
    """

    step: float
    n: int
    radius: float
    rotation_deg: float = 0.0

    @classmethod
    def for_camera(cls, camera: Camera, oversample: float = DEFAULT_OVERSAMPLE,
                   rotation_deg: float = 0.0) -> ApertureGrid:
        """The grid whose step is one pixel's aperture footprint over ``oversample``."""
        if not (math.isfinite(oversample) and oversample > 0):
            raise ValueError(f"oversample must be a positive number, got {oversample!r}")
        step = camera.pixel_pupil_footprint_mm / oversample
        radius = camera.exit_pupil_diameter_mm / 2
        k = int(math.floor(radius / step + 1e-9))
        # the outermost columns must hold a sample by the very test inside() applies
        while k > 0 and ((0 - k) * step) ** 2 > radius**2:
            k -= 1
        return cls(step=step, n=2 * k + 1, radius=radius, rotation_deg=float(rotation_deg))

    @property
    def center(self) -> float:
        """Index ``c`` of the optical axis."""
        return (self.n - 1) / 2

    def coords(self) -> np.ndarray:
        """Sample coordinates along one frame axis (mm)."""
        return (np.arange(self.n) - self.center) * self.step

    def inside(self) -> np.ndarray:
        """``(n, n)`` mask ``[i, j]`` of the samples inside the aperture circle."""
        c = self.coords()
        return c[:, None] ** 2 + c[None, :] ** 2 <= self.radius**2

    def column_ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """For each ``i``, the inclusive ``j`` range ``[lo, hi]`` inside the aperture."""
        mask = self.inside()  # a disc: each column's samples are contiguous, centre included
        if not mask.any(axis=1).all():
            raise ValueError("aperture grid has a column without samples; build it with "
                             "ApertureGrid.for_camera")
        lo = np.argmax(mask, axis=1)
        return lo, self.n - 1 - lo

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Integer ``(i, j)`` of the in-aperture samples, ``i`` major, ``j`` minor."""
        i, j = np.nonzero(self.inside())
        return i, j

    def sensor_uv(self) -> np.ndarray:
        """``(n_samples, 2)`` aperture coordinates ``(u, v)`` mm of the samples on the
        sensor's axes, ``R (i - c, j - c) step``."""
        i, j = self.samples()
        frame = np.column_stack([i - self.center, j - self.center]) * self.step
        return frame @ rotation_matrix(self.rotation_deg).T

    def pixels_per_step(self, camera: Camera) -> float:
        """Sensor pixels per sample step behind a microlens, ``step f_ml / (d p_px)``."""
        return self.step * camera.ml_focal_length_mm / (
            camera.exit_pupil_distance_mm * camera.pixel_pitch_mm)

    def pixel_offsets(self, camera: Camera) -> np.ndarray:
        """``(n_samples, 2)`` float32: where each sample lands behind a microlens, in
        pixels ``(col, row)`` from the lens's image centre, ``-(u, v) f_ml / (d p_px)``.

        Rounded as the kernels used to compute it (``-(b * dug)`` in float32) when the
        frame is the sensor's, so that table and arithmetic agree bit for bit.
        """
        i, j = self.samples()
        b = np.column_stack([i - self.center, j - self.center])
        if self.rotation_deg:
            b = b @ rotation_matrix(self.rotation_deg).T
        dug = np.float32(self.pixels_per_step(camera))
        return -(b.astype(np.float32) * dug)


@dataclass(frozen=True)
class LensIndexMap:
    """Affine map from array-plane ``(x, y)`` mm to fractional microlens index ``(kx, ky)``."""

    matrix: np.ndarray  # (2, 2): d(kx, ky) / d(x, y)
    offset: np.ndarray  # (2,)

    @property
    def axis_aligned(self) -> bool:
        """Whether ``kx`` depends on ``x`` only and ``ky`` on ``y`` only."""
        return self.matrix[0, 1] == 0.0 and self.matrix[1, 0] == 0.0

    def __call__(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Fractional lens indices of array-plane points."""
        m, o = self.matrix, self.offset
        x, y = np.asarray(x, float), np.asarray(y, float)
        return m[0, 0] * x + m[0, 1] * y + o[0], m[1, 0] * x + m[1, 1] * y + o[1]


def lens_index_map(camera: Camera, shear_tol: float = DEFAULT_SHEAR_TOL,
                   rotation_deg: float = 0.0) -> LensIndexMap:
    """Fit the affine lens layout to the (calibrated) centres and invert it.

    The array-plane position of lens ``k`` is ``x_k = c_k / (1 + f_ml/d)``
    (docs/design.md §2) with ``c_k`` its image centre in sensor mm; NaN centres are
    ignored. The map takes array-plane points in the coordinates of a frame rotated by
    ``rotation_deg`` about the optical axis (the reconstruction grid's). When the fitted
    layout, seen from that frame, drifts by at most ``shear_tol`` lenses across the whole
    array, its rotation/shear terms are dropped (about the array's centre) and the map is
    axis-aligned: the separable projector path applies. A frame that follows the lens
    rows (:func:`plenocl.optics.lattice.separable_rotation_deg`) makes a rotated array
    axis-aligned this way.
    """
    camera = camera.on_lens_lattice()  # a hexagonal array: its axial lattice (§5)
    cols, rows = camera.ml_count
    pos = array_plane_positions(camera, camera.microlens_centers)
    if rotation_deg:
        pos = pos @ rotation_matrix(rotation_deg)  # world -> frame: Rᵀ x, as row vectors
    fit = lattice_fit(pos)
    matrix = np.linalg.inv(fit[:2].T)
    offset = -matrix @ fit[2]
    drift_x = abs(matrix[0, 1] / matrix[1, 1]) * rows
    drift_y = abs(matrix[1, 0] / matrix[0, 0]) * cols
    if max(drift_x, drift_y) <= shear_tol:
        ok = np.isfinite(pos).all(axis=-1)
        centre = pos[ok].mean(axis=0)
        offset = offset + np.array([matrix[0, 1] * centre[1], matrix[1, 0] * centre[0]])
        matrix = np.diag(np.diag(matrix))
    return LensIndexMap(matrix=matrix, offset=offset)


# ---- projector tables -------------------------------------------------------------------
def depth_coefficients(camera: Camera, grid: Grid, lens_map: LensIndexMap,
                       aperture: ApertureGrid) -> np.ndarray:
    """Per-depth affine coefficients ``(nz, 16)`` float64 (layout: kernels/projector.h).

    Voxel ``(ix, iy)`` of depth ``iz`` seen through aperture sample ``(i, j)`` meets the
    array plane at lens index ``G (ix, iy) + o + H (i - c, j - c)``; the row also holds
    ``G⁻¹`` and the row sums of ``|G⁻¹|``.
    """
    z = grid.axis_centers("z")
    alpha = camera.alpha(z)
    mag = camera.image_distance_at(z) / (camera.object_distance_mm + z)  # X' = -mag x
    _, dy, dx = grid.spacing
    m = lens_map.matrix
    out = np.zeros((len(z), 16))
    for k in range(len(z)):
        scale = -mag[k] / alpha[k]
        g = m @ np.diag([scale * dx, scale * dy])
        o = m @ (scale * np.array([grid.x[0] + dx / 2, grid.y[0] + dy / 2])) + lens_map.offset
        h = (1 - 1 / alpha[k]) * aperture.step * m
        det = g[0, 0] * g[1, 1] - g[0, 1] * g[1, 0]
        ginv = np.array([[g[1, 1], -g[0, 1]], [-g[1, 0], g[0, 0]]]) / det
        out[k] = [*g.ravel(), *o, *h.ravel(), *ginv.ravel(), *np.abs(ginv).sum(axis=1)]
    return out


def lens_tables(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Per-lens centres as rounded pixel ``int2`` and remainder ``float2`` (flat, row-major;
    a lens without a centre has rounded centre :data:`NO_LENS`)."""
    centres = camera.microlens_centers.reshape(-1, 2)
    ok = np.isfinite(centres).all(axis=1)
    rounded = np.where(ok[:, None], np.round(np.nan_to_num(centres)), NO_LENS)
    frac = np.where(ok[:, None], np.nan_to_num(centres) - rounded, 0.0)
    return rounded.astype(np.int32), frac.astype(np.float32)


def colour_stride(camera: Camera, aperture: ApertureGrid, limit: int = 8) -> int:
    """Smallest lens stride ``cs`` such that lenses ``cs`` apart never share a pixel.

    Lens ``k`` writes pixels within ``E = c g + 1`` of its centre (``c g``: the outermost
    aperture sample behind it, in pixels); centres deviate from the fitted lattice by at
    most ``dev``. The forward kernel scatters one ``cs x cs`` colour class at a time.
    """
    fit = lattice_fit(camera.microlens_centers)
    dev = lattice_residual(camera.microlens_centers, fit)
    reach = float(np.abs(aperture.pixel_offsets(camera)).max()) + 1.0
    steps = [(a, b) for a in range(-2, 3) for b in range(-2, 3) if (a, b) != (0, 0)]
    for cs in range(2, limit + 1):
        sep = min(np.abs(fit[:2].T @ (cs * np.array(s))).max() for s in steps)
        if sep - 2 * dev > 2 * reach:
            return cs
    raise ValueError("microlens images overlap so much that no race-free lens colouring "
                     f"with stride <= {limit} exists; stop the main lens down")


# ---- geometry checks --------------------------------------------------------------------
def check_depth_range(camera: Camera, grid: Grid) -> None:
    """Fail when the grid reaches depths where the main lens forms no real image."""
    limit = camera.focal_length_mm - camera.object_distance_mm
    if grid.z[0] <= limit:
        raise ValueError(
            f"the grid's depth range z = {grid.z} mm reaches z <= f - s_o = {limit:.3f} mm, "
            "where the main lens forms no real image; move the volume's near face beyond "
            f"z = {limit:.3f} mm"
        )


def check_field_of_view(camera: Camera, grid: Grid, coef: np.ndarray,
                        aperture: ApertureGrid) -> None:
    """Fail when no voxel's light can reach any microlens (``coef``:
    :func:`depth_coefficients`)."""
    nz, ny, nx = grid.shape
    c = aperture.center
    corners = np.array([(ix, iy, bu, bv) for ix in (0, nx - 1) for iy in (0, ny - 1)
                        for bu in (-c, c) for bv in (-c, c)], float)
    g, o, h = coef[:, 0:4].reshape(-1, 2, 2), coef[:, 4:6], coef[:, 6:10].reshape(-1, 2, 2)
    k = (np.einsum("zab,nb->zna", g, corners[:, :2]) + o[:, None]
         + np.einsum("zab,nb->zna", h, corners[:, 2:]))
    cols, rows = camera.ml_count
    seen = ((k[..., 0].max(1) > -1) & (k[..., 0].min(1) < cols)
            & (k[..., 1].max(1) > -1) & (k[..., 1].min(1) < rows))
    if not seen.any():
        half = np.array(camera.ml_count) * camera.ml_pitch_mm / camera.magnification / 2
        raise ValueError(
            f"the grid (x = {grid.x}, y = {grid.y} mm) lies entirely outside the camera's "
            f"field of view (about x in ±{half[0]:.2f}, y in ±{half[1]:.2f} mm at z = 0); "
            "no voxel's light reaches the microlens array"
        )
