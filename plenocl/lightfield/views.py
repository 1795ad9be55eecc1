"""The light field ``LF(x, y, u, v)`` of a raw plenoptic image, perspective views and
computational refocusing (docs/design.md §2 and §4, paper §II).

Coordinates
-----------
* Every pixel behind microlens ``k`` (the lens whose cell contains it: one image pitch
  square around ``c_k`` on the calibrated lattice, a hexagonal array's hexagon of points
  nearest ``c_k``; :mod:`plenocl.optics.ownership`) sits at offset ``δ`` (mm) from
  ``c_k`` and sees the aperture point ``u = -δ d / f_ml`` (same for ``v``; ``u`` on the
  exit pupil, ``d`` its distance from the array: ``s_i`` for a thin lens, docs/design.md
  §2); its spatial coordinate is the lens position on the array plane
  ``x_k = c_k / (1 + f_ml / d)`` (:func:`pixel_coordinates`).
* :class:`LightField` resamples the image onto one **plaid** ``(u, v)`` grid shared by
  all lenses (bilinear between the pixels behind the same lens, since the ``(u, v)``
  of a pixel differs slightly from lens to lens): ``views[iv, iu, ky, kx]``. The
  default step is one pixel's footprint on the aperture, ``p_px d / f_ml``; samples
  outside the circular aperture, off the sensor or behind a lens calibration missed
  are ``NaN``.
* A hexagonal array's views keep the lenses' offset indices ``[ky, kx]``: a view is a
  **staggered** image, its odd rows (1, 3, ...) ``odd_row_shift`` (±0.5) of a pitch along
  the row from the even ones and the rows ``pitch·√3/2`` apart. Lens ``(kx, ky)`` has
  the array-frame coordinates ``(a, b) = (kx + shift (ky mod 2), ky)``
  (:meth:`plenocl.camera.Camera.lens_lattice_coords`; a rectangular array: ``(kx,
  ky)``), and each lens sample's spatial position is that lens's on the lattice fitted
  in ``(a, b)`` (:func:`lens_positions_mm`).

Refocusing
----------
A ray from aperture point ``u`` through the image point ``X'`` meets the array plane
at ``x = u (1 - 1/α) + X'/α`` with ``α = d'/d`` (``d'``: the image point's distance from
the exit pupil; a thin lens: ``s_i'/s_i``). The refocused image is sampled at
the array plane on the microlens lattice: output pixel ``ξ`` (``(a, b)`` coordinates;
``supersample`` pixels per lens) collects, for every plaid sample ``(u, v)``, the light
field at ``ξ + (1 - 1/α) L⁻¹ (u, v)`` (quadratic B-spline weights of the three nearest
rows and, in each, of its three nearest lenses; ``L``: the lattice's ``(a, b)``-to-mm
map, so a rotated array is handled), i.e.
``E(ξ) = Σ LF(u (1 - 1/α) + ξ, u) / Σ w`` — the paper's ``x'/α`` written as ``ξ`` so that
every depth shares one field of view. Together with the bilinear ``(u, v)`` resampling
this is the paper's 4-D interpolation. ``E`` is the weighted *mean* over the samples
that exist (radiance-like: the same scale as a view; vignetted or missing samples do
not darken the image). An object point ``(X, Y, z)`` refocused at its own depth appears
at ``ξ = X'/α = -(s_i'/s_o') (d/d') X`` on the array plane (the main lens inverts it; a
thin lens: ``-(s_i/s_o') X``). A hexagonal array's refocused image is a plain
rectangular image of ``(a, b)``: its pixels are ``pitch / S`` wide and ``pitch·√3/2 / S``
tall on the array plane (:meth:`LightField.output_positions_mm`).

A point at depth ``z`` appears in the perspective view ``(u, v)`` at array-plane
position ``X'/α + (1 - 1/α) u``: its parallax is ``(1 - 1/α)`` mm per mm of ``u``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import pyopencl.array as cl_array

from ..camera import Camera
from ..camera.lattice import lattice_fit
from ..opencl.device import DeviceLike, get_queue
from ..opencl.program import KernelSet
from ..optics.imaging import array_plane_positions, array_plane_scale
from ..optics.ownership import lens_owner
from ..optics.rawimage import check_image


# ---- lattice --------------------------------------------------------------------------
def _centers(camera: Camera) -> np.ndarray:
    """The camera's microlens image centres (px), warning when they are not calibrated."""
    if not camera.calibrated:
        warnings.warn("the camera is not calibrated: using the nominal microlens centres of "
                      "its layout; run plenocl.calibrate(white_image, camera) for real data",
                      stacklevel=3)
    return np.asarray(camera.microlens_centers, dtype=np.float64)


def lens_lattice(camera: Camera, centers: np.ndarray | None = None) -> np.ndarray:
    """Affine least-squares map from the lenses' array-frame coordinates ``(a, b) = (kx +
    shift (ky mod 2), ky)`` to image-centre pixels (a rectangular array: ``(kx, ky)``,
    :func:`plenocl.camera.lattice.lattice_fit` of the camera's or the given centres).

    Parameters
    ----------
    camera
        The camera (calibrated centres; ``NaN`` entries are ignored).
    centers
        Optional ``(rows, cols, 2)`` centres to use instead of the camera's.

    Returns
    -------
    numpy.ndarray
        ``(3, 2)`` matrix ``M`` with ``(col, row) = [a, b, 1] @ M``.
    """
    centers = camera.microlens_centers if centers is None else centers
    # affine in the array-frame (a, b) (a rectangular array: (kx, ky) itself)
    return lattice_fit(centers, camera.lens_lattice_coords())


def lens_index_to_mm(camera: Camera) -> np.ndarray:
    """``(2, 2)`` matrix ``L``: array-plane mm per unit of the array-frame coordinates
    ``(a, b)`` (columns; a rectangular array: per unit of lens index ``kx``, ``ky``; a
    hexagonal one: ``a = kx + shift (ky mod 2)`` along the rows, ``b = ky`` across them,
    ``pitch`` and ``pitch·√3/2`` long unrotated)."""
    model = lens_lattice(camera)
    return model[:2].T * camera.pixel_pitch_mm * array_plane_scale(camera)


def lens_positions_mm(camera: Camera, centers: np.ndarray | None = None) -> np.ndarray:
    """``(rows, cols, 2)`` array-plane ``(x, y)`` mm of every lens on the fitted lattice:
    the spatial coordinates of the light field's samples ``views[:, :, ky, kx]`` (a
    hexagonal array's odd rows shifted along the row, :func:`lens_lattice`)."""
    model = lens_lattice(camera, centers)
    return array_plane_positions(camera, camera.lens_lattice_coords() @ model[:2] + model[2])


# ---- per-pixel coordinates ----------------------------------------------------------------
@dataclass(frozen=True)
class PixelCoordinates:
    """The two-plane coordinates of every sensor pixel, ``(H, W)`` arrays.

    Attributes
    ----------
    kx, ky
        Microlens behind which the pixel lies (``-1``: none).
    x_mm, y_mm
        That microlens's position on the array plane (mm).
    u_mm, v_mm
        Aperture (exit-pupil) coordinates the pixel sees (mm), ``u = -δ d / f_ml``.
    valid
        The lens has a calibrated centre and ``(u, v)`` lies inside the aperture.
    """

    kx: np.ndarray
    ky: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    u_mm: np.ndarray
    v_mm: np.ndarray
    valid: np.ndarray


def pixel_coordinates(camera: Camera) -> PixelCoordinates:
    """Per-pixel ``(x, y, u, v)`` from the calibrated centres and the optics (docs/design.md §2).

    Parameters
    ----------
    camera
        A calibrated camera (uncalibrated: the nominal centres, with a warning).

    Returns
    -------
    PixelCoordinates
        Lens index, array-plane position and aperture coordinates of each pixel.
    """
    centers = _centers(camera)
    cols, rows = camera.ml_count
    w, h = camera.pixels
    owner = lens_owner(camera, centers)
    inside = owner >= 0
    kx, ky = np.where(inside, owner % cols, -1), np.where(inside, owner // cols, -1)
    pix = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h)), -1)
    c_px = centers[np.clip(ky, 0, rows - 1), np.clip(kx, 0, cols - 1)]
    c_mm = camera.px_to_mm(c_px)
    uv = camera.aperture_u_of_offset(camera.px_to_mm(pix) - c_mm)
    xy = array_plane_positions(camera, c_px)
    radius = camera.exit_pupil_diameter_mm / 2
    valid = inside & np.isfinite(c_px).all(-1) & (np.hypot(uv[..., 0], uv[..., 1]) <= radius)
    nan = np.where(inside[..., None] & np.isfinite(c_px), 1.0, np.nan)
    xy, uv = xy * nan, uv * nan
    return PixelCoordinates(kx, ky, xy[..., 0], xy[..., 1], uv[..., 0], uv[..., 1], valid)


def plaid_uv(camera: Camera, step_mm: float | None = None) -> np.ndarray:
    """Symmetric plaid aperture samples ``(n,)`` mm covering the aperture diameter.

    Parameters
    ----------
    camera
        The camera (aperture diameter, pixel footprint).
    step_mm
        Sample spacing on the aperture; default one pixel's footprint ``p_px d/f_ml``.
    """
    step = camera.pixel_pupil_footprint_mm if step_mm is None else float(step_mm)
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"the (u, v) step must be a positive number of mm, got {step_mm!r}")
    half = int(math.floor(camera.exit_pupil_diameter_mm / 2 / step + 1e-9))
    return np.arange(-half, half + 1) * step


# ---- the light field ------------------------------------------------------------------
def resample_light_field(image, camera: Camera, u: np.ndarray, v: np.ndarray,
                         centers: np.ndarray) -> np.ndarray:
    """Sample the raw image at every lens's pixel positions of the plaid ``(u, v)`` grid.

    Sample ``(u, v)`` of lens ``k`` lies at ``c_k - (u, v) f_ml / d`` on the sensor; it is
    interpolated bilinearly from the pixels *behind lens k* only (taps on a neighbour's
    pixels are dropped and the weights renormalised), so the rim of one microlens image
    never borrows light from the next.

    Returns
    -------
    numpy.ndarray
        ``(nv, nu, rows, cols)`` float32; ``NaN`` outside the aperture, off the sensor or
        where a centre is ``NaN``.
    """
    image = np.asarray(image, np.float32)
    owner = lens_owner(camera, centers)
    rows, cols = centers.shape[:2]
    lens_id = np.arange(rows * cols, dtype=np.int32).reshape(rows, cols)
    scale = camera.ml_focal_length_mm / camera.exit_pupil_distance_mm / camera.pixel_pitch_mm
    aperture = np.hypot(u[None, :], v[:, None]) <= camera.exit_pupil_diameter_mm / 2 + 1e-9
    out = np.full((len(v), len(u), rows, cols), np.nan, np.float32)
    for iv in range(len(v)):  # one plaid row at a time bounds the memory
        col = centers[None, ..., 0] - scale * u[:, None, None]
        row = np.broadcast_to(centers[None, ..., 1] - scale * v[iv], col.shape)
        out[iv] = _owned_bilinear(image, owner, col, row, lens_id)
    out[~aperture] = np.nan
    return out


def _owned_bilinear(image, owner, col, row, lens_id) -> np.ndarray:
    """Bilinear samples at ``(col, row)`` using only the pixels owned by ``lens_id``."""
    h, w = image.shape
    known = np.isfinite(col) & np.isfinite(row)
    col, row = np.where(known, col, -10.0), np.where(known, row, -10.0)
    c0, r0 = np.floor(col).astype(np.int64), np.floor(row).astype(np.int64)
    tx, ty = col - c0, row - r0
    acc = np.zeros(col.shape)
    wsum = np.zeros(col.shape)
    for dc, dr, wt in ((0, 0, (1 - tx) * (1 - ty)), (1, 0, tx * (1 - ty)),
                       (0, 1, (1 - tx) * ty), (1, 1, tx * ty)):
        ci, ri = c0 + dc, r0 + dr
        on = (ci >= 0) & (ri >= 0) & (ci < w) & (ri < h)
        ci, ri = np.clip(ci, 0, w - 1), np.clip(ri, 0, h - 1)
        ok = on & known & (owner[ri, ci] == lens_id) & (wt > 0)
        acc += np.where(ok, wt * image[ri, ci], 0.0)
        wsum += np.where(ok, wt, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(wsum > 0, acc / wsum, np.nan).astype(np.float32)


class LightField:
    """The 4-D light field of one raw plenoptic image on a plaid ``(u, v)`` grid.

    Parameters
    ----------
    raw_image
        ``(H, W)`` raw sensor image (any numeric dtype).
    camera
        A calibrated camera (:func:`plenocl.calibrate`); an uncalibrated one uses its
        nominal centres, with a warning. Rectangular or hexagonal microlens arrays.
    uv_step_mm
        Plaid spacing on the aperture (default: one pixel's footprint ``p_px d/f_ml``).
    queue
        OpenCL queue, context, device or name for refocusing (default: chosen at first use).

    Attributes
    ----------
    u, v
        ``(nu,)``, ``(nv,)`` aperture coordinates (mm) of the plaid samples.
    views
        ``(nv, nu, rows, cols)`` float32 samples (``NaN``: none), the sub-aperture views,
        indexed by the lenses' ``(ky, kx)``; a hexagonal array's are staggered images
        (module notes; :func:`lens_positions_mm` gives each sample's position).
    """

    def __init__(self, raw_image, camera: Camera, *, uv_step_mm: float | None = None,
                 queue: DeviceLike = None) -> None:
        camera.layout.require_array("the light field takes the hexagonal camera itself, not "
                                    "its axial view (Camera.on_lens_lattice, the projector's)")
        self.camera = camera
        image = check_image(raw_image, camera, np.float32)
        self.centers = _centers(camera)
        self.u = plaid_uv(camera, uv_step_mm)
        self.v = self.u.copy()
        self.views = resample_light_field(image, camera, self.u, self.v, self.centers)
        self._lens_to_mm = lens_index_to_mm(camera)
        self._queue_arg = queue

    @property
    def views(self) -> np.ndarray:
        """``(nv, nu, rows, cols)`` float32 sub-aperture views (``NaN``: no sample)."""
        return self._views

    @views.setter
    def views(self, value: np.ndarray) -> None:
        """Replace the views (e.g. after editing them); the device copy is made anew."""
        value = np.asarray(value, dtype=np.float32)
        if value.ndim != 4:
            raise ValueError(f"views must be (nv, nu, rows, cols), got shape {value.shape}")
        self._views = value
        self._device = {}

    @property
    def lf(self) -> np.ndarray:
        """The light field indexed ``[ky, kx, iv, iu]`` (a view of :attr:`views`)."""
        return self.views.transpose(2, 3, 0, 1)

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of microlenses: the size of a view."""
        return self.views.shape[2], self.views.shape[3]

    def view(self, u_mm: float = 0.0, v_mm: float = 0.0) -> np.ndarray:
        """The perspective (sub-aperture) view nearest aperture point ``(u, v)`` mm.

        Returns
        -------
        numpy.ndarray
            ``(rows, cols)`` float32, one value per microlens (``NaN``: no sample).
        """
        radius = self.camera.exit_pupil_diameter_mm / 2
        if not math.hypot(u_mm, v_mm) <= radius:
            raise ValueError(f"(u, v) = ({u_mm}, {v_mm}) mm lies outside the aperture of "
                             f"radius {radius:.3f} mm")
        iu, iv = np.abs(self.u - u_mm).argmin(), np.abs(self.v - v_mm).argmin()
        return self.views[iv, iu]

    # ---- refocusing ------------------------------------------------------------------
    def shifts(self, alpha) -> np.ndarray:
        """Per-view shifts ``(planes, nv*nu, 2)`` in lens units ``(a, b)`` for refocus ``α``.

        ``(1 - 1/α) L⁻¹ (u, v)``: where the ray through aperture sample ``(u, v)`` and
        output point ``ξ`` meets the array plane, relative to ``ξ``.
        """
        alpha = np.atleast_1d(np.asarray(alpha, dtype=np.float64))
        if not (np.all(np.isfinite(alpha)) and np.all(alpha > 0)):
            raise ValueError(f"alpha must be positive and finite, got {alpha}")
        uu, vv = np.meshgrid(self.u, self.v)
        per_mm = np.linalg.solve(self._lens_to_mm, np.stack([uu.ravel(), vv.ravel()]))
        return (1.0 - 1.0 / alpha)[:, None, None] * per_mm.T[None]

    def output_lens_coordinates(self, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Array-frame lens coordinates ``(a, b)`` (1-D each) of refocused-image pixel
        centres (a rectangular array: lens indices ``(kx, ky)``)."""
        rows, cols = self.shape
        return output_lens_coordinates(cols, rows, _supersample(supersample))

    def output_positions_mm(self, supersample: int = 1) -> np.ndarray:
        """Array-plane ``(x, y)`` mm ``(H', W', 2)`` of the refocused-image pixel centres."""
        kx, ky = self.output_lens_coordinates(supersample)
        model = lens_lattice(self.camera, self.centers)
        px = np.stack(np.meshgrid(kx, ky), -1) @ model[:2] + model[2]
        return array_plane_positions(self.camera, px)

    def refocus(self, alpha: float | None = None, z_mm: float | None = None, *,
                supersample: int = 1) -> np.ndarray:
        """The image refocused at ``α = d'/d`` (a thin lens: ``s_i'/s_i``) or at object
        depth ``z_mm``.

        Parameters
        ----------
        alpha, z_mm
            Exactly one: the refocus parameter, or the depth (mm, +z away from the
            camera) whose ``α`` is used. ``α = 1`` (``z = 0``) is the nominal focal plane.
        supersample
            Output pixels per microlens along each axis.

        Returns
        -------
        numpy.ndarray
            ``(rows * S, cols * S)`` float32 on the microlens lattice (see module notes).
        """
        if (alpha is None) == (z_mm is None):
            raise ValueError("give exactly one of alpha= or z_mm=")
        if np.ndim(z_mm if alpha is None else alpha):
            raise ValueError(f"refocus takes one depth (alpha= or z_mm=, a number), got "
                             f"{z_mm if alpha is None else alpha!r}; refocus each depth in "
                             "turn (LightField.focal_stack for several)")
        a = float(self.camera.alpha(z_mm)) if alpha is None else float(alpha)
        return self.shift_and_add(self.shifts([a]), supersample)[0]

    def focal_stack(self, z_list, *, supersample: int = 1) -> np.ndarray:
        """Images refocused at each depth of ``z_list`` (mm), ``(nz, rows * S, cols * S)``."""
        z = np.atleast_1d(np.asarray(z_list, dtype=np.float64))
        if z.ndim != 1 or len(z) == 0:
            raise ValueError("z_list must be a non-empty list of depths in mm")
        return self.shift_and_add(self.shifts(self.camera.alpha(z)), supersample)

    def shift_and_add(self, shifts: np.ndarray, supersample: int = 1) -> np.ndarray:
        """Refocused images for explicit per-view shifts, computed by the refocus kernel.

        Parameters
        ----------
        shifts
            ``(planes, nv * nu, 2)`` shifts in lens units ``(a, b)`` of each view (flattened
            ``[iv, iu]``), as :meth:`shifts` returns them.
        supersample
            Output pixels per microlens along each axis.

        Returns
        -------
        numpy.ndarray
            ``(planes, rows * S, cols * S)`` float32: per output pixel, the weighted mean
            of the views' bilinear samples that exist.
        """
        s = _supersample(supersample)
        k, views, used = self._device_state()
        shifts = np.ascontiguousarray(np.asarray(shifts)[:, used], dtype=np.float32)
        rows, cols = self.shape
        planes, nuv = shifts.shape[:2]
        out_w, out_h = cols * s, rows * s
        out = k.array((planes, out_h, out_w))
        out.fill(np.float32(np.nan))
        k.launch("refocus", (out_w, out_h, planes), views, k.to_device(shifts), np.int32(nuv),
                 np.int32(cols), np.int32(rows), np.int32(out_w), np.int32(out_h),
                 np.float32(1.0 / s), np.float32(self.camera.odd_row_shift), out)
        return out.get()

    def _device_state(self) -> tuple[KernelSet, cl_array.Array, np.ndarray]:
        """The refocus kernel, the non-empty views on the device and their indices, made
        once.

        The device copy is ``(value * valid, valid)`` pairs with a one-lens border of
        zeros, the layout ``kernels/lightfield.cl`` interpolates without branches; a
        hexagonal array's kernel is its ``STAGGERED`` variant.
        """
        if not self._device:
            staggered = [f"-DPL_STAGGERED={int(self.camera.layout.staggered)}"]
            kernels = KernelSet(get_queue(self._queue_arg), "lightfield.cl", ["refocus"],
                                options=staggered)
            flat = self.views.reshape(-1, *self.shape)
            used = np.flatnonzero(np.isfinite(flat).any(axis=(1, 2)))
            if len(used) == 0:
                used = np.arange(1)
            valid = np.isfinite(flat[used])
            pairs = np.zeros((len(used), self.shape[0] + 2, self.shape[1] + 2, 2), np.float32)
            pairs[:, 1:-1, 1:-1, 0] = np.where(valid, flat[used], 0.0)
            pairs[:, 1:-1, 1:-1, 1] = valid
            self._device = {"kernels": kernels, "views": kernels.to_device(pairs), "used": used}
        d = self._device
        return d["kernels"], d["views"], d["used"]


def output_lens_coordinates(nx: int, ny: int, supersample: int = 1
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Lens coordinates ``(a, b)`` (a rectangular array: ``(kx, ky)``) of the output pixel
    centres, 1-D each.

    Output pixel ``j`` of ``nx * supersample`` sits at ``(j + 0.5) / S - 0.5``: with
    ``S = 1`` one output pixel per microlens, at its centre.
    """
    s = int(supersample)
    return ((np.arange(nx * s) + 0.5) / s - 0.5, (np.arange(ny * s) + 0.5) / s - 0.5)


def _supersample(value) -> int:
    if int(value) != value or not 1 <= int(value) <= 16:
        raise ValueError(f"supersample must be an integer from 1 to 16, got {value!r}")
    return int(value)
