"""Reconstruction of a particle volume from one plenoptic image (DESIGN §6).

Methods (all multiplicative, non-negative, on the device):

``"mlem"`` (default)
    Multiplicative EM, ``E ← E (Wᵀ r / s)^μ``: each voxel moves by the arithmetic mean of
    the ratios ``r = I / P`` of the pixels it reaches. It keeps in-focus particles,
    which light a single microlens, where geometric-mean updates lose them.
``"smart"``
    Simultaneous MART, ``E ← E exp(μ Wᵀ log r / s)``: the geometric mean.
``"mart"``
    The paper's MART, ``E_j ← E_j Π_i r_i^(μ w_ij)``, in block-sequential order: pixels
    are grouped by sub-aperture view (``mart_blocks`` interleaved groups of the pixel's
    offset behind its microlens), and each block updates the volume with a fresh
    projection. One block per pixel is the sequential original.

``s_j = Σ_i w_ij`` is the fraction of a voxel's light that reaches the sensor. The
image is scaled to a maximum of 1 inside the solver (dynamic range) and the volume
scaled back. Options (:class:`ReconstructionSettings`, validated once): MLOS first
guess, pixel threshold, zero-pixel masking, active slices, cropping, dark-microlens
skipping, early stop; a progress callback.

The solver needs of a projector only the operator contract
(:class:`plenocl.operator.ProjectionOperator`).
"""

from __future__ import annotations

import functools
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pyopencl.array as cla

from .lattice import lattice_cells, lattice_fit
from .operator import ProjectionOperator
from .program import KernelSet

METHODS = ("mlem", "smart", "mart")
#: n per axis of MART's view blocks (n² blocks; 32 covers one block per view of 32 px lenses)
MAX_MART_BLOCKS = 32
#: Defaults per method: (iterations, relaxation). MART's are the paper's synthetic case.
DEFAULTS = {"mlem": (30, 1.0), "smart": (30, 1.0), "mart": (15, 0.7)}
_KERNELS = ("ratio", "update_mlem", "update_exp", "mlos", "mask_dark", "prepare_image",
            "partial_sums", "row_extent")
#: Work-items of the partial-sum reduction (the host adds their results in float64).
_SUM_ITEMS = 1024
#: Largest image value accepted: the volume (in image units) must stay finite in float32.
FLOAT32_LIMIT = 1e30
#: Crop when the non-zero voxels' bounding box holds at most this fraction of the grid.
CROP_BELOW = 0.8


@dataclass
class ReconstructionInfo:
    """What a reconstruction did: iterations, residual history, time, masking."""

    method: str
    iterations: int = 0
    residuals: list[float] = field(default_factory=list)
    converged: bool = False
    seconds: float = 0.0
    active_fraction: float = 1.0
    active_slices: list[int] = field(default_factory=list)
    cropped_shape: tuple[int, int, int] | None = None
    lit_lens_fraction: float = 1.0


@dataclass(frozen=True)
class ReconstructionSettings:
    """Every option of a reconstruction, validated once (see :func:`reconstruct` for
    their meaning). ``iterations`` and ``relax`` left at ``None`` take the method's
    defaults (:data:`DEFAULTS`); the stored object holds the resolved values."""

    method: str = "mlem"
    iterations: int | None = None
    relax: float | None = None
    start: str | np.ndarray = field(default="uniform", compare=False)
    threshold: float = 0.0
    mask_fraction: float | None = None
    min_sensitivity: float = 0.5
    skip_empty: bool = True
    crop: bool = True
    skip_dark: bool = True
    tol: float | None = None
    mart_blocks: int = 2

    def __post_init__(self) -> None:
        it_default, mu_default = DEFAULTS.get(self.method, (0, 1.0))
        if self.iterations is None:
            object.__setattr__(self, "iterations", it_default)
        if self.relax is None:
            object.__setattr__(self, "relax", mu_default)
        _check_options(self)

    @property
    def n_blocks(self) -> int:
        """Update blocks per iteration: MART's ``mart_blocks²`` views, else 1."""
        return self.mart_blocks**2 if self.method == "mart" and self.mart_blocks > 1 else 1


def _check_options(s: ReconstructionSettings) -> None:
    if not np.isfinite(s.threshold):
        raise ValueError(f"threshold must be a finite number (image units), got {s.threshold!r}")
    if int(s.mart_blocks) != s.mart_blocks or not 1 <= s.mart_blocks <= MAX_MART_BLOCKS:
        raise ValueError(f"mart_blocks must be an integer from 1 to {MAX_MART_BLOCKS} "
                         f"(n x n blocks of views), got {s.mart_blocks!r}")
    if s.method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {s.method!r}")
    if int(s.iterations) != s.iterations or s.iterations < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {s.iterations!r}")
    if not (np.isfinite(s.relax) and 0 < s.relax <= 1):
        raise ValueError(f"relax (μ) must satisfy 0 < μ <= 1, got {s.relax!r}")
    if s.mask_fraction is not None and not 0 <= s.mask_fraction <= 1:
        raise ValueError(f"mask_fraction must be in [0, 1] or None, got {s.mask_fraction!r}")
    if not 0 <= s.min_sensitivity < 1:
        raise ValueError(f"min_sensitivity must be in [0, 1), got {s.min_sensitivity!r}")


def prepare_image(image, camera) -> tuple[np.ndarray, float]:
    """Validate a raw image against the camera; return it as float32 scaled to max 1,
    and the scale. Integer and float16 input is accepted."""
    img = np.asarray(image)
    expected = (camera.pixels[1], camera.pixels[0])
    if img.shape != expected:
        raise ValueError(f"image shape {img.shape} does not match the camera's sensor "
                         f"{expected} (rows, columns); check the camera file")
    if img.dtype == bool or not np.issubdtype(img.dtype, np.number):
        raise ValueError(f"image must be numeric (uint8, uint16, float), got {img.dtype}")
    if np.iscomplexobj(img):
        raise TypeError("image must hold real numbers, not complex; pass the intensity "
                        "(e.g. np.abs(image) ** 2)")
    img = img.astype(np.float64)
    if not np.all(np.isfinite(img)):
        raise ValueError("image contains NaN or Inf; replace bad pixels (e.g. by 0) first")
    if img.min() < 0:
        raise ValueError("image has negative pixels; subtract the background with clipping, "
                         "e.g. np.clip(image - background, 0, None)")
    scale = float(img.max())
    if scale > FLOAT32_LIMIT:
        raise ValueError(f"image maximum {scale:.3g} is beyond the float32 range plenocl "
                         f"reconstructs in (up to {FLOAT32_LIMIT:.0e}); rescale the image")
    if scale == 0:
        return img.astype(np.float32), 0.0
    return (img / scale).astype(np.float32), scale


def subtract_background(image) -> tuple[np.ndarray, float]:
    """Remove a camera's dark level and estimate its noise, robustly.

    At PIV seeding densities most pixels see no particle, so the median is the
    background and the median absolute deviation the noise. Returns the float32 image
    ``max(I - median, 0)`` and the noise standard deviation (a sensible ``threshold`` for
    :func:`reconstruct` is 3 to 5 times it).
    """
    img = np.asarray(image, dtype=np.float64)
    med = float(np.median(img))
    sigma = 1.4826 * float(np.median(np.abs(img - med)))
    return np.clip(img - med, 0, None).astype(np.float32), sigma


def _start_volume(start: np.ndarray, grid) -> np.ndarray:
    """A user-supplied first guess, checked: the grid's shape, finite, non-negative."""
    if start.shape != grid.shape:
        raise ValueError(f"start volume has shape {start.shape}, expected the grid's "
                         f"{grid.shape} (nz, ny, nx)")
    if not np.all(np.isfinite(start)) or start.min() < 0:
        raise ValueError("start volume must be finite and non-negative")
    return start.astype(np.float32)


def extent_box(extent: np.ndarray) -> tuple[slice, slice, slice] | None:
    """The bounding box of the non-zero voxels from :meth:`Solver.row_extent` (``None``
    when all are zero); :func:`nonzero_box` is its NumPy twin."""
    lit = extent[..., 1] >= 0
    if not lit.any():
        return None
    z, y = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
    x0, x1 = int(extent[..., 0][lit].min()), int(extent[..., 1][lit].max())
    return slice(int(z[0]), int(z[-1]) + 1), slice(int(y[0]), int(y[-1]) + 1), slice(x0, x1 + 1)


def nonzero_box(vol: np.ndarray) -> tuple[slice, slice, slice] | None:
    """The bounding box of a volume's non-zero voxels (``None`` when all are zero)."""
    nonzero = vol != 0
    box = []
    for axis in range(vol.ndim):
        hit = np.flatnonzero(nonzero.any(axis=tuple(a for a in range(vol.ndim) if a != axis)))
        if not len(hit):
            return None
        box.append(slice(int(hit[0]), int(hit[-1]) + 1))
    return tuple(box)


def view_blocks(camera, n_per_axis: int) -> np.ndarray:
    """Block id (int32) of every pixel: interleaved groups of sub-aperture views.

    A pixel's view is its offset (rounded, in pixels) from the image centre of the
    microlens it lies behind: the lens of its lattice cell (:func:`lattice_cells`; beyond
    the array, the nearest edge lens; a lens without a calibrated centre counts at its
    fitted lattice position). Views are grouped by ``(offset_x mod n, offset_y mod n)``.
    Vectorised over the sensor from the lattice fit; the NumPy reference
    (:func:`plenocl.reference.reconstruct.view_blocks`) searches the nearest centre per
    pixel instead, and agrees except at cell borders of perturbed arrays.
    """
    cols, rows = camera.ml_count
    w, h = camera.pixels
    model = lattice_fit(camera.microlens_centers)
    kx, ky = lattice_cells(model, w, h)
    np.clip(kx, 0, cols - 1, out=kx)
    np.clip(ky, 0, rows - 1, out=ky)
    centres = np.asarray(camera.microlens_centers, dtype=np.float64)
    kxs, kys = np.meshgrid(np.arange(cols), np.arange(rows))
    fitted = np.stack([kxs, kys, np.ones((rows, cols))], -1) @ model
    centres = np.where(np.isfinite(centres), centres, fitted)
    off_x = np.rint(np.arange(w)[None, :] - centres[..., 0][ky, kx]).astype(np.int64) % n_per_axis
    off_y = np.rint(np.arange(h)[:, None] - centres[..., 1][ky, kx]).astype(np.int64) % n_per_axis
    return (off_x + n_per_axis * off_y).astype(np.int32)


#: MART's device block ids per projector and block count, made once (a projector
#: reconstructing many images sets them up once).
_BLOCKS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def device_view_blocks(projector: ProjectionOperator, n_per_axis: int) -> cla.Array:
    """:func:`view_blocks` of the projector's camera on its queue, cached per projector."""
    per_projector = _BLOCKS.setdefault(projector, {})
    if n_per_axis not in per_projector:
        per_projector[n_per_axis] = cla.to_device(projector.queue,
                                                  view_blocks(projector.camera, n_per_axis))
    return per_projector[n_per_axis]


class Solver:
    """Device buffers and kernels of a reconstruction with one projector.

    Volumes live on the device as the projector's list of depth slabs; element-wise
    kernels run slab by slab. A solver can crop itself to the illuminated part of its
    grid (:meth:`crop`); it then remembers where its grid sits in the full one.

    Parameters
    ----------
    projector
        Any :class:`plenocl.operator.ProjectionOperator` (a :class:`plenocl.Projector`).
    min_sensitivity
        Voxels with a sensitivity at or below it stay 0.
    lit
        Bool per microlens (see :meth:`plenocl.Projector.lit_lenses`): the iterations
        project onto and from these lenses only (dark-microlens skipping); ``None``:
        every lens.
    box
        Where the projector's grid sits in the full grid (``None``: it is the full grid).
    """

    def __init__(self, projector: ProjectionOperator, min_sensitivity: float = 0.0,
                 lit: np.ndarray | None = None,
                 box: tuple[slice, slice, slice] | None = None) -> None:
        self.proj, self.lit, self.box = projector, lit, box
        self.lenses = None if lit is None else projector.lens_set(lit)
        self.smin = np.float32(max(min_sensitivity, 1e-12))
        self.queue = projector.queue
        self._k = KernelSet(self.queue, "reconstruct.cl", _KERNELS, looping=["partial_sums"])
        self.n_pix = projector.camera.pixels[0] * projector.camera.pixels[1]
        self.sens = projector.sensitivity()  # computed once per projector
        self._no_blocks = cla.zeros(self.queue, 1, np.int32)

    def _run(self, name: str, n: int, *args) -> None:
        """An element-wise kernel over ``n`` items (``n`` is its last argument)."""
        self._k.launch(name, (n,), *args, np.int32(n))

    def update_voxels(self, name: str, vol, b, *scalars) -> None:
        """Run a voxel kernel ``name(vol, b, sens, *scalars, n)`` on every slab."""
        for v, bb, s in zip(vol, b, self.sens):
            self._run(name, v.size, v, bb, s, *scalars)

    def row_extent(self, vol) -> np.ndarray:
        """First and last non-zero ``x`` of every row ``(nz, ny, 2)`` int32, computed on
        the device (``(nx, -1)`` for an empty row)."""
        parts = []
        for v in vol:
            nz, ny, nx = v.shape
            out = self._k.array((nz, ny, 2), np.int32)
            self._k.launch("row_extent", (nz * ny,), v, np.int32(nx), out, np.int32(nz * ny))
            parts.append(out.get())
        return np.concatenate(parts)

    def total(self, a, b=None) -> float:
        """``Σ a``, or ``Σ (a - b)²`` when ``b`` is given, reduced on the device."""
        out = self._k.array(_SUM_ITEMS)
        chunk = -(-a.size // _SUM_ITEMS) if self._k.is_cpu else 0
        self._k.launch("partial_sums", (_SUM_ITEMS,), a, a if b is None else b,
                       np.int32(b is not None), np.int32(chunk), out, np.int32(a.size))
        return float(out.get().astype(np.float64).sum())

    def ratio(self, img, proj, threshold: float, log_mode: bool, blocks=None, block=-1):
        """``I / max(P, eps)`` (or its log) on the device, restricted to one block."""
        out = cla.empty_like(img)
        block_of = blocks if blocks is not None else self._no_blocks
        self._run("ratio", self.n_pix, img, proj, block_of, np.int32(block),
                  np.float32(threshold), np.int32(log_mode), out)
        return out

    def _dark_and_log(self, img, threshold: float, floor: float):
        dark, logimg = cla.empty_like(img), cla.empty_like(img)
        self._run("prepare_image", self.n_pix, img, np.float32(threshold), np.float32(floor),
                  dark, logimg)
        return dark, logimg

    def start(self, img, kind, threshold: float, scale: float = 1.0):
        """First guess: ``"uniform"`` (scaled to the image's total), ``"mlos"``, or a
        volume array in image units (divided by ``scale``, the image's scaling)."""
        if isinstance(kind, np.ndarray):
            return self.proj.volume_to_device(_start_volume(kind, self.proj.grid) / scale)
        vol = self.proj.empty_volume()
        if kind == "uniform":
            # the projection of a volume of ones carries 1ᵀ A 1 = Σ sensitivity
            total = sum(self.total(s) for s in self.sens)
            for v in vol:
                v.fill(self.total(img) / max(total, 1e-30))
        elif kind == "mlos":
            _, logimg = self._dark_and_log(img, threshold, max(threshold, 1e-6))
            self.update_voxels("mlos", vol, self.proj.back_device(logimg), self.smin)
        else:
            raise ValueError(f"start must be 'uniform', 'mlos' or a volume array, got {kind!r}")
        return vol

    def mask(self, vol, img, threshold: float, fraction: float) -> None:
        """Zero the voxels sending more than ``fraction`` of their light to dark pixels."""
        dark, _ = self._dark_and_log(img, threshold, 1e-6)
        self.update_voxels("mask_dark", vol, self.proj.back_device(dark), np.float32(fraction))

    def projections(self, log_ratio: bool):
        """The forward and back projections of an iteration: onto the lit lenses only
        when the solver skips dark ones, and back from them too unless the ratio is a log
        (a log ratio is not 0 at a dark pixel, so it is back-projected from every lens)."""
        fwd, back = self.proj.forward_device, self.proj.back_device
        if self.lenses is not None:
            fwd = functools.partial(fwd, lenses=self.lenses)
            if not log_ratio:
                back = functools.partial(back, lenses=self.lenses)
        return fwd, back

    def crop(self, vol, extent: np.ndarray, below: float = CROP_BELOW):
        """Continue on the bounding box of the non-zero voxels when it holds at most
        ``below`` of the current grid.

        ``extent`` is ``vol``'s :meth:`row_extent`. Returns ``(solver, vol, extent)``: a
        solver on the cropped projector (with :attr:`box` in full-grid indices) and the
        volume and extent on it, or ``self`` and the inputs when nothing is cropped.
        """
        local = extent_box(extent)
        size = int(np.prod(self.proj.grid.shape))
        if local is None or np.prod([s.stop - s.start for s in local]) > below * size:
            return self, vol, extent
        host = np.ascontiguousarray(self.proj.volume_to_host(vol)[local])
        box = local if self.box is None else tuple(
            slice(b.start + s.start, b.start + s.stop) for b, s in zip(self.box, local))
        sub = Solver(self.proj.cropped(local), float(self.smin), self.lit, box)
        new_vol = sub.proj.volume_to_device(host)
        return sub, new_vol, sub.row_extent(new_vol)

    def volume_to_host(self, vol, full_shape: tuple[int, int, int]) -> np.ndarray:
        """The host volume on the full grid of shape ``full_shape`` (0 outside :attr:`box`)."""
        if self.box is None:
            return self.proj.volume_to_host(vol)
        full = np.zeros(full_shape, np.float32)
        full[self.box] = self.proj.volume_to_host(vol)
        return full


# ---- one iteration per method ---------------------------------------------------------
def _simultaneous(solver: Solver, vol, img, active, relax: float, threshold: float,
                  log_ratio: bool) -> float:
    """One simultaneous update from one forward and one back projection; returns
    ``‖P - I‖`` before it."""
    fwd, back = solver.projections(log_ratio)
    proj = fwd(vol, active=active)
    resid = solver.total(proj, img) ** 0.5
    b = back(solver.ratio(img, proj, threshold, log_ratio), active=active)
    if log_ratio:
        solver.update_voxels("update_exp", vol, b, np.float32(relax), solver.smin, np.int32(1))
    else:
        solver.update_voxels("update_mlem", vol, b, np.float32(relax), solver.smin)
    return resid


def update_mlem(solver: Solver, vol, img, active, relax: float, threshold: float,
                blocks=None, n_blocks: int = 1) -> float:
    """MLEM: ``E ← E (Aᵀ r / s)^μ``; returns ``‖P - I‖`` before the update."""
    return _simultaneous(solver, vol, img, active, relax, threshold, log_ratio=False)


def update_smart(solver: Solver, vol, img, active, relax: float, threshold: float,
                 blocks=None, n_blocks: int = 1) -> float:
    """SMART: ``E ← E exp(μ Aᵀ log r / s)``; returns ``‖P - I‖`` before the update."""
    return _simultaneous(solver, vol, img, active, relax, threshold, log_ratio=True)


def update_mart(solver: Solver, vol, img, active, relax: float, threshold: float,
                blocks=None, n_blocks: int = 1) -> float:
    """Block MART: one multiplicative update per block of views, each with a fresh
    projection; returns ``‖P - I‖`` before the first block."""
    fwd, back = solver.projections(log_ratio=True)
    proj = fwd(vol, active=active)
    resid = solver.total(proj, img) ** 0.5
    for blk in range(n_blocks):
        if blk:
            proj = fwd(vol, out=proj, active=active)
        lr = solver.ratio(img, proj, threshold, True, blocks, -1 if blocks is None else blk)
        solver.update_voxels("update_exp", vol, back(lr, active=active), np.float32(relax),
                         solver.smin, np.int32(0))
    return resid


#: The update of each method, chosen once per reconstruction.
UPDATES = {"mlem": update_mlem, "smart": update_smart, "mart": update_mart}


def _iterate(solver: Solver, vol, img, settings: ReconstructionSettings,
             info: ReconstructionInfo, step: Callable, callback, norm: float) -> np.ndarray:
    """The iterations of :func:`reconstruct`; returns the host volume on the full grid."""
    full_shape = solver.proj.grid.shape
    for it in range(settings.iterations):
        cropping = settings.crop and it >= 1
        extent = solver.row_extent(vol) if settings.skip_empty or cropping else None
        if cropping:
            solver, vol, extent = solver.crop(vol, extent)
            info.cropped_shape = solver.proj.grid.shape if solver.box else None
        active = (extent[..., 1] >= 0).any(axis=1) if settings.skip_empty else None
        if active is not None:
            info.active_slices.append(int(active.sum()))
        resid = step(solver, vol, img, active) / norm
        info.residuals.append(resid)
        info.iterations = it + 1
        if callback is not None and callback(it + 1, resid) is False:
            break
        tol = settings.tol
        if tol is not None and it and abs(info.residuals[-2] - resid) < tol * resid:
            info.converged = True
            break
    return solver.volume_to_host(vol, full_shape)


def reconstruct(image, projector: ProjectionOperator, method: str = "mlem",
                iterations: int | None = None, relax: float | None = None, *,
                start="uniform", threshold: float = 0.0, mask_fraction: float | None = None,
                min_sensitivity: float = 0.5, skip_empty: bool = True, crop: bool = True,
                skip_dark: bool = True, tol: float | None = None, mart_blocks: int = 2,
                callback: Callable[[int, float], bool | None] | None = None,
                return_info: bool = False):
    """Reconstruct a particle volume from one raw plenoptic image.

    Parameters
    ----------
    image
        Raw image ``(rows, cols)`` matching the projector's camera; uint8, uint16 or float;
        finite and non-negative.
    projector
        A :class:`plenocl.Projector` for the camera and grid (its queue runs the solver),
        or any :class:`plenocl.operator.ProjectionOperator`.
    method
        ``"mlem"`` (default), ``"smart"`` or ``"mart"`` (see the module documentation).
    iterations, relax
        Iterations and relaxation ``0 < μ <= 1``; defaults per method in :data:`DEFAULTS`
        (MART: the paper's 15 at μ = 0.7).
    start
        ``"uniform"`` (constant, scaled so its projection carries the image's intensity),
        ``"mlos"`` (weighted geometric mean of the pixels each voxel reaches), or a volume
        ``(nz, ny, nx)`` in image units: a previous frame's reconstruction, or an
        upsampled coarse one (its zero voxels stay zero).
    threshold
        Pixels at or below ``threshold`` (same units as ``image``) count as dark (zero).
    mask_fraction
        Zero-pixel masking: voxels sending more than this fraction of their light onto
        dark pixels start at zero and stay there (``0``: any dark pixel; ``None``: off).
    min_sensitivity
        Voxels that send no more than this fraction of their light to the sensor (at the
        edges of the field of view) are not reconstructed: the image barely constrains
        them, and light from particles outside the grid would pile up in them.
    skip_empty
        Active-slice compaction: before every iteration, depth slices with no non-zero
        voxel (after masking, or emptied by the updates) are left out of both
        projections. Exact: multiplicative updates never revive a zero voxel.
    crop
        Automatic cropping to the illuminated region: after every iteration, when
        the non-zero voxels fill a bounding box of at most 80 % of the current grid, the
        remaining iterations run on that box (active-voxel compaction between iterations;
        exact up to float32 rounding; ``info.cropped_shape``).
    skip_dark
        Dark-microlens skipping: the iterations project only onto the microlenses that
        see a pixel above ``threshold`` (``info.lit_lens_fraction``), and MLEM
        back-projects only from them. Exact: no ratio depends on the projection at a
        dark pixel, and MLEM's ratio is 0 there (the log ratios of SMART and MART are
        not, so they back-project from every lens). The residuals are then taken over
        the lit lenses' pixels.
    tol
        Stop early when the relative residual changes by less than ``tol``.
    mart_blocks
        MART only: ``n`` gives ``n²`` interleaved blocks of sub-aperture views.
    callback
        Called as ``callback(iteration, residual)`` after each iteration; returning
        ``False`` stops the reconstruction.
    return_info
        Also return a :class:`ReconstructionInfo`.

    Returns
    -------
    numpy.ndarray
        float32 volume ``(nz, ny, nx)`` in the image's intensity units; never NaN or Inf.
    """
    settings = ReconstructionSettings(
        method=method, iterations=iterations, relax=relax, start=start, threshold=threshold,
        mask_fraction=mask_fraction, min_sensitivity=min_sensitivity, skip_empty=skip_empty,
        crop=crop, skip_dark=skip_dark, tol=tol, mart_blocks=mart_blocks)
    vol, info = run_reconstruction(image, projector, settings, callback)
    return (vol, info) if return_info else vol


def run_reconstruction(image, projector: ProjectionOperator, settings: ReconstructionSettings,
                       callback: Callable[[int, float], bool | None] | None = None
                       ) -> tuple[np.ndarray, ReconstructionInfo]:
    """:func:`reconstruct` with its options as one :class:`ReconstructionSettings`;
    returns the volume and its :class:`ReconstructionInfo`."""
    t0 = time.perf_counter()
    img_np, scale = prepare_image(image, projector.camera)
    info = ReconstructionInfo(settings.method)
    if scale == 0:
        return np.zeros(projector.grid.shape, np.float32), info
    thr = float(settings.threshold) / scale
    lit = None
    if settings.skip_dark:
        lit = projector.lit_lenses(img_np, thr)
        info.lit_lens_fraction = float(lit.mean())
    solver = Solver(projector, settings.min_sensitivity, lit)
    img = cla.to_device(solver.queue, img_np)
    vol = solver.start(img, settings.start, thr, scale)
    if settings.mask_fraction is not None:
        solver.mask(vol, img, thr, settings.mask_fraction)
    blocks = device_view_blocks(projector, settings.mart_blocks) if settings.n_blocks > 1 else None
    step = functools.partial(UPDATES[settings.method], relax=settings.relax, threshold=thr,
                             blocks=blocks, n_blocks=settings.n_blocks)
    vol = _iterate(solver, vol, img, settings, info, step, callback,
                   float(np.linalg.norm(img_np)))
    out = vol * np.float32(scale)
    info.active_fraction = float(np.count_nonzero(out)) / out.size
    info.seconds = time.perf_counter() - t0
    return out, info
