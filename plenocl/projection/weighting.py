"""The weighting model of docs/design.md §5 as plain NumPy tables, shared by every stage.

What a voxel's weight on a pixel depends on, apart from the kernels that sum it:

* :class:`ApertureGrid`: the sampling of the circular main-lens aperture (step 1 of the
  paper's weighting function): the paper's plaid ``(u, v)`` grid, or a hexagonal
  lattice's rhombic grid along its two steps;
* :class:`LensIndexMap` / :func:`lens_index_map`: array-plane millimetres to fractional
  microlens index (step 2);
* :func:`depth_coefficients`: per-depth affine coefficients of step 2 for a voxel grid,
  the table the projector kernels read (layout in ``kernels/projector.h``);
* :func:`lens_tables`: each lens's calibrated image centre, rounded and remainder
  (step 3);
* :func:`colour_stride`: the lens stride at which microlens images never share a pixel
  (the race-free forward scatter);
* :func:`check_field_of_view`: a grid whose light reaches no lens (the depths and field
  of view the camera resolves are checked before, :mod:`plenocl.optics.depthrange`).

Nothing here touches a device. The NumPy reference (:mod:`plenocl.reference.weights`)
shares these definitions and evaluates the model voxel by voxel, for clarity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..camera.lattice import DEFAULT_SHEAR_TOL, lattice_fit, lattice_residual, rotation_matrix
from ..grid import Grid
from ..optics.imaging import array_plane_positions
from ..options import is_number

#: Aperture samples per pixel footprint on the aperture (``p_px d / f_ml``), per axis.
DEFAULT_OVERSAMPLE = 1.25
#: The fewest aperture samples across its diameter :meth:`ApertureGrid.for_lattice`
#: takes (fewer: a pinhole; the 12 x 10-lens test camera's volume at 0.1, 1.7 samples
#: across, correlated 0.36 with the default's).
MIN_ACROSS = 3
__all__ = ["DEFAULT_OVERSAMPLE", "DEFAULT_SHEAR_TOL", "NO_LENS", "ApertureGrid", "LensIndexMap",
           "check_field_of_view", "colour_stride",
           "depth_coefficients", "lens_index_map", "lens_tables"]
#: Rounded-centre marker of a lens without a calibrated centre (PL_NO_LENS in projector.h).
NO_LENS = -(1 << 30)


@dataclass(frozen=True)
class ApertureGrid:
    """The ``(u, v)`` sampling of the circular main-lens aperture (step 1).

    Sample ``(i, j)`` sits at ``(u, v) = R (a + shear b, squeeze b) step`` with ``(a, b)
    = (i - c, j - c)``, ``c = (n - 1)/2`` and ``R`` the rotation of the reconstruction
    frame (``rotation_deg``, the grid's; 0: the sensor's axes); only samples inside the
    aperture circle are kept. The paper's plaid grid is ``shear = 0, squeeze = 1`` (the
    default); a hexagonal array's lens lattice takes the rhombic grid along its own two
    lattice steps (:meth:`for_lattice`, docs/design.md §5.3), whose samples move the
    light by whole steps along one lens index each, as the plaid grid does for a
    rectangular array. In the frame's own coordinates the samples are ``(a + shear b,
    squeeze b) step``: a frame that follows the microlens rows samples the aperture
    along them too.
    """

    step: float
    n: int
    radius: float
    rotation_deg: float = 0.0
    shear: float = 0.0
    squeeze: float = 1.0

    @classmethod
    def for_camera(cls, camera: Camera, oversample: float = DEFAULT_OVERSAMPLE,
                   rotation_deg: float = 0.0) -> ApertureGrid:
        """The plaid grid whose step is one pixel's aperture footprint over ``oversample``."""
        return cls.for_lattice(camera, oversample, rotation_deg)

    @classmethod
    def for_lattice(cls, camera: Camera, oversample: float = DEFAULT_OVERSAMPLE,
                    rotation_deg: float = 0.0, shear: float = 0.0,
                    squeeze: float = 1.0) -> ApertureGrid:
        """The grid of step one pixel's aperture footprint over ``oversample`` along the
        lattice steps ``(1, 0)`` and ``(shear, squeeze)``; ``n`` covers the aperture's
        extent along both indices: the outermost columns or rows hold samples."""
        if not (is_number(oversample) and math.isfinite(oversample) and oversample > 0):
            raise ValueError(f"oversample must be a positive number, got {oversample!r}")
        if not (math.isfinite(shear) and math.isfinite(squeeze) and squeeze > 0):
            raise ValueError("the aperture lattice needs a finite shear and a positive "
                             f"squeeze, got {shear!r}, {squeeze!r}")
        step = camera.pixel_pupil_footprint_mm / oversample
        radius = camera.exit_pupil_diameter_mm / 2
        if 2 * radius / step < MIN_ACROSS:
            least = MIN_ACROSS * camera.pixel_pupil_footprint_mm / (2 * radius)
            raise ValueError(
                f"oversample={oversample:g} samples the aperture {2 * radius / step:.1f} "
                f"times across, fewer than {MIN_ACROSS}: a pinhole, not the camera's "
                f"aperture (its weights lose the defocus that gives depth); give at least "
                f"{least:.2g} (the default {DEFAULT_OVERSAMPLE} samples it "
                f"{2 * radius * DEFAULT_OVERSAMPLE / camera.pixel_pupil_footprint_mm:.0f} "
                "times)")
        reach = max(math.hypot(1.0, shear / squeeze), 1.0 / squeeze)  # |a|, |b| extents
        k = int(math.floor(radius / step * reach + 1e-9))
        probe = cls(step=step, n=2 * k + 1, radius=radius, shear=shear, squeeze=squeeze)
        # the outermost columns (or, on a rhombic grid, rows) must hold a sample by the very
        # test inside() applies; a rhombic grid may then have empty outer columns
        while k > 0 and not (probe.inside()[0].any() or probe.inside()[:, 0].any()):
            k -= 1
            probe = cls(step=step, n=2 * k + 1, radius=radius, shear=shear, squeeze=squeeze)
        return cls(step=step, n=2 * k + 1, radius=radius, rotation_deg=float(rotation_deg),
                   shear=float(shear), squeeze=float(squeeze))

    @property
    def center(self) -> float:
        """Index ``c`` of the optical axis."""
        return (self.n - 1) / 2

    @property
    def basis(self) -> np.ndarray:
        """``(2, 2)`` frame offset (in steps) per unit of ``(a, b)``, as columns."""
        return np.array([[1.0, self.shear], [0.0, self.squeeze]])

    def _frame_points(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``(..., 2)`` frame coordinates (mm) of index offsets ``(a, b)``."""
        a, b = np.broadcast_arrays(a, b)
        return np.stack([a + self.shear * b, self.squeeze * b], -1) * self.step

    def inside(self) -> np.ndarray:
        """``(n, n)`` mask ``[i, j]`` of the samples inside the aperture circle."""
        c = np.arange(self.n) - self.center
        p = self._frame_points(c[:, None], c[None, :])
        return (p**2).sum(-1) <= self.radius**2

    def column_ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """For each ``i``, the inclusive ``j`` range ``[lo, hi]`` inside the aperture
        (a disc: each column's samples are contiguous; a rhombic grid's outer columns may
        hold none, ``hi < lo``)."""
        mask = self.inside()
        some = mask.any(axis=1)
        if self.shear == 0 and not some.all():
            raise ValueError("aperture grid has a column without samples; build it with "
                             "ApertureGrid.for_camera")
        lo = np.where(some, np.argmax(mask, axis=1), self.n)
        hi = np.where(some, self.n - 1 - np.argmax(mask[:, ::-1], axis=1), self.n - 1)
        return lo, hi

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Integer ``(i, j)`` of the in-aperture samples, ``i`` major, ``j`` minor."""
        i, j = np.nonzero(self.inside())
        return i, j

    def frame_uv(self) -> np.ndarray:
        """``(n_samples, 2)`` aperture coordinates (mm) of the samples in the frame."""
        i, j = self.samples()
        return self._frame_points(i - self.center, j - self.center)

    def sensor_uv(self) -> np.ndarray:
        """``(n_samples, 2)`` aperture coordinates ``(u, v)`` mm of the samples on the
        sensor's axes."""
        return self.frame_uv() @ rotation_matrix(self.rotation_deg).T

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
        if self.shear or self.squeeze != 1:
            b = b @ self.basis.T
        if self.rotation_deg:
            b = b @ rotation_matrix(self.rotation_deg).T
        dug = np.float32(self.pixels_per_step(camera))
        return -(b.astype(np.float32) * dug)


@dataclass(frozen=True)
class LensIndexMap:
    """Affine map from array-plane ``(x, y)`` mm to fractional microlens index ``(kx, ky)``."""

    matrix: np.ndarray  # (2, 2): d(kx, ky) / d(x, y)
    offset: np.ndarray  # (2,)
    #: A hexagonal array's axial lattice: the aperture samples step along the lattice's
    #: own two steps (rows squeezed); a rectangular array's keep the pixel's step in ``y``.
    lattice_steps: bool = False

    @property
    def axis_aligned(self) -> bool:
        """Whether ``kx`` depends on ``x`` only and ``ky`` on ``y`` only."""
        return self.matrix[0, 1] == 0.0 and self.matrix[1, 0] == 0.0

    @property
    def triangular(self) -> bool:
        """Whether ``ky`` depends on ``y`` only (``kx`` may lean across the rows: a
        hexagonal array's lattice, docs/design.md §5.3, or a rectangular array whose
        columns are not quite square to its rows, §5.4)."""
        return self.matrix[1, 0] == 0.0

    def aperture_lattice(self) -> tuple[float, float]:
        """``(shear, squeeze)`` of the aperture samples (:meth:`ApertureGrid.for_lattice`)
        along which ``kx`` moves with the sample column only: ``(0, 1)``, the plaid grid,
        for an axis-aligned map; for a triangular one the columns lean with the lattice:
        a hexagonal array's own two steps, ``(-m01/m11, m00/m11)`` (equal whole steps of
        ``kx`` and ``ky``), a leaning rectangular array's ``(-m01/m00, 1)``."""
        if self.axis_aligned or not self.triangular:
            return 0.0, 1.0
        m = self.matrix
        if self.lattice_steps:
            return float(-m[0, 1] / m[1, 1]), float(m[0, 0] / m[1, 1])
        return float(-m[0, 1] / m[0, 0]), 1.0

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
    rows (:func:`plenocl.camera.lattice.separable_rotation_deg`) makes a rotated array
    axis-aligned this way. Where only the rows are level (the row index drifts by at most
    ``shear_tol``) but the columns lean, only the row index's drift is dropped and the
    map is triangular: separable with the rhombic aperture samples of
    :meth:`LensIndexMap.aperture_lattice`. That is a hexagonal array's axial lattice in
    its rows' frame, and a calibrated rectangular array whose columns are not quite
    square to its rows (a real array: 0.005° off is a drift of 0.002 lenses across 20
    rows; docs/design.md §5.4), so no real calibration falls to the general path.
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
    if drift_y <= shear_tol:  # the rows are level in this frame
        ok = np.isfinite(pos).all(axis=-1)
        centre = pos[ok].mean(axis=0)
        keep = np.array([[1.0, float(drift_x > shear_tol)], [0.0, 1.0]])
        drop = matrix * (1 - keep)  # the terms dropped, about the array's centre
        offset = offset + drop @ centre
        matrix = np.where(keep > 0, matrix, 0.0)
    return LensIndexMap(matrix=matrix, offset=offset, lattice_steps=camera.layout.is_view)


# ---- projector tables -------------------------------------------------------------------
def depth_coefficients(camera: Camera, grid: Grid, lens_map: LensIndexMap,
                       aperture: ApertureGrid) -> np.ndarray:
    """Per-depth affine coefficients ``(nz, 16)`` float64 (layout: kernels/projector.h).

    Voxel ``(ix, iy)`` of depth ``iz`` seen through aperture sample ``(i, j)`` meets the
    array plane at lens index ``G (ix, iy) + o + H (i - c, j - c)``; the row also holds
    ``G⁻¹`` and the row sums of ``|G⁻¹|``. A rhombic aperture grid's ``H`` is diagonal by
    construction (:meth:`LensIndexMap.aperture_lattice`); its rounding residue is set to 0.
    """
    z = grid.axis_centers("z")
    alpha = camera.alpha(z)
    mag = camera.image_distance_at(z) / (camera.object_distance_mm + z)  # X' = -mag x
    _, dy, dx = grid.spacing
    m = lens_map.matrix
    m_ap = m @ aperture.basis  # lens index per aperture step along each sample index
    if aperture.shear:
        if abs(m_ap[0, 1]) > 1e-9 * abs(m_ap[0, 0]):
            raise ValueError("the rhombic aperture grid does not belong to this lens map: "
                             "build it with ApertureGrid.for_lattice(..., "
                             "*lens_map.aperture_lattice())")
        m_ap[0, 1] = 0.0
    out = np.zeros((len(z), 16))
    for k in range(len(z)):
        scale = -mag[k] / alpha[k]
        g = m @ np.diag([scale * dx, scale * dy])
        o = m @ (scale * np.array([grid.x[0] + dx / 2, grid.y[0] + dy / 2])) + lens_map.offset
        h = (1 - 1 / alpha[k]) * aperture.step * m_ap
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
        mid = camera.field_centre_mm()
        raise ValueError(
            f"the grid (x = {grid.x}, y = {grid.y} mm) lies entirely outside the camera's "
            f"field of view (about x in {mid[0]:.2f} ± {half[0]:.2f}, y in {mid[1]:.2f} ± "
            f"{half[1]:.2f} mm at z = 0); "
            "no voxel's light reaches the microlens array"
        )
