"""The device side of a reconstruction: :class:`Solver` (buffers, element-wise kernels,
starts, masking, cropping) and one update function per method (:data:`UPDATES`).

The solver needs of a projector only the operator contract
(:class:`plenocl.reconstruction.operator.ProjectionOperator`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import numpy as np
import pyopencl.array as cla

from ..opencl.arrays import copy_inside, copy_slabbed, fill, upload
from ..opencl.program import KernelSet
from .operator import PlannedOperator, ProjectionOperator
from .schedule import SupportStart
from .supersample import LateralBinning

_KERNELS = ("ratio", "update_mlem", "update_exp", "mlos", "mask_dark", "prepare_image",
            "partial_sums", "row_extent", "slice_extent", "add_into")
T = TypeVar("T")
#: Work-items of the partial-sum reduction (the host adds their results in float64).
_SUM_ITEMS = 1024
#: The literal methods' ratio floor (kernels/solver.cl PL_RATIO_MIN: log -13.8).
RATIO_MIN = 1e-6
#: Crop when the non-zero voxels' bounding box holds at most this fraction of the grid.
CROP_BELOW = 0.8


def check_start_volume(start: np.ndarray, shape: tuple[int, int, int]) -> None:
    """Refuse a first guess that is not a volume of the grid's ``shape`` of real, finite,
    non-negative numbers."""
    if start.shape != shape:
        raise ValueError(f"start volume has shape {start.shape}, expected the grid's "
                         f"{shape} (nz, ny, nx)")
    if start.dtype.kind not in "biuf":
        raise ValueError(f"start volume must hold real numbers, got {start.dtype}")
    if not np.all(np.isfinite(start)) or start.min() < 0:
        raise ValueError("start volume must be finite and non-negative")


def _start_volume(start: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """A first guess (a user's, a coarse run's support), checked
    (:func:`check_start_volume`), as float32."""
    check_start_volume(start, shape)
    return start.astype(np.float32)


def extent_box(extent: np.ndarray) -> tuple[slice, slice, slice] | None:
    """The bounding box of the non-zero voxels from :meth:`Solver.slice_extent` (``None``
    when all are zero); :func:`nonzero_box` is its NumPy twin."""
    lit = extent[:, 1] >= 0
    if not lit.any():
        return None
    z, e = np.flatnonzero(lit), extent[lit]
    return (slice(int(z[0]), int(z[-1]) + 1), slice(int(e[:, 0].min()), int(e[:, 1].max()) + 1),
            slice(int(e[:, 2].min()), int(e[:, 3].max()) + 1))


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


#: Warn when more than this fraction of the grid's voxels send too little light to a
#: camera's sensor to be reconstructed (the grid reaches beyond its field of view).
OUTSIDE_WARN = 0.25

class Solver:
    """Device buffers and kernels of a reconstruction with one projector.

    Volumes live on the device as the projector's list of depth slabs; element-wise
    kernels run slab by slab. A solver can crop itself to the illuminated part of its
    grid (:meth:`crop`); it then remembers where its grid sits in the full one.

    Parameters
    ----------
    projector
        Any :class:`plenocl.reconstruction.operator.ProjectionOperator`
        (a :class:`plenocl.Projector`).
    min_sensitivity
        Voxels with a sensitivity at or below it stay 0.
    lit
        Bool per microlens (see :meth:`plenocl.Projector.lit_lenses`): the iterations
        project onto and from these lenses only (dark-microlens skipping); ``None``:
        every lens.
    box
        Where the projector's grid sits in the full grid (``None``: it is the full grid).
    observed
        Bool per pixel ``(rows, cols)``: ``False`` where the image holds no data (an
        unrendered row, a masked defect): those pixels are left out of the updates and
        the sensitivity is ``Aᵀ observed`` (MLEM and SMART of the observed pixels alone;
        a voxel whose light falls mostly on pixels without data is not constrained and
        stays 0, as below ``min_sensitivity``). ``None``: every pixel is data.
    """

    def __init__(self, projector: ProjectionOperator, min_sensitivity: float = 0.0,
                 lit: np.ndarray | None = None,
                 box: tuple[slice, slice, slice] | None = None,
                 observed: np.ndarray | None = None) -> None:
        self.proj, self.lit, self.box = projector, lit, box
        self.observed = observed
        self.lenses = None if lit is None else projector.lens_set(lit)
        self.smin = np.float32(max(min_sensitivity, 1e-12))
        self.queue = projector.queue
        self._kept: dict[str, object] = {}
        self._k = KernelSet(self.queue, "solver.cl", _KERNELS, looping=["partial_sums"])
        self.n_pix = projector.camera.pixels[0] * projector.camera.pixels[1]
        self._no_blocks = cla.zeros(self.queue, 1, np.int32)
        seen = np.ones(1, np.float32) if observed is None else observed.astype(np.float32)
        self._observed = upload(self.queue, seen.ravel())
        self._use_observed = np.int32(observed is not None)
        # A^T 1, kept by the projector; with pixels without data, A^T observed
        self.sens = (projector.sensitivity() if observed is None else
                     projector.back_device(self._observed.reshape(observed.shape)))

    def unseen_fraction(self) -> float:
        """The fraction of the grid's voxels whose sensitivity is at or below
        :attr:`smin`: too little of their light reaches the sensor to reconstruct them
        (the grid beyond the camera's field of view; read on the host)."""
        dark = sum(int((s.get() <= self.smin).sum()) for s in self.sens)
        return dark / self.proj.grid.size

    @functools.cached_property
    def binning(self) -> LateralBinning:
        """The lateral binning and spreading kernels on this solver's queue, fetched once
        (a sub-voxel run's start and its binned result)."""
        return LateralBinning(self.queue)

    def kept(self, name: str, make: Callable[[], T]) -> T:
        """The device buffer ``name`` this solver keeps from one iteration to the next,
        ``make()`` at its first use: each iteration's projection, ratio and back
        projection write over the previous one's (the in-order queue runs the earlier
        kernels that read it first). A buffer made and freed every iteration costs a
        CPU device a page fault per 4 KiB at its first touch, and a GPU driver an
        allocation and a free (docs/design.md §7.5)."""
        if name not in self._kept:
            self._kept[name] = make()
        return self._kept[name]

    def release_kept(self) -> None:
        """Let go of the buffers :meth:`kept` holds (the run's iterations are over, or
        the solver is cropped): a solver kept for its volume or its sensitivity then
        holds no projection, ratio or back projection beside it."""
        self._kept.clear()

    def _run(self, name: str, n: int, *args) -> None:
        """An element-wise kernel over ``n`` items (``n`` is its last argument)."""
        self._k.launch(name, (n,), *args, np.int32(n))

    def update_voxels(self, name: str, vol, b, *scalars, sens=None) -> None:
        """Run a voxel kernel ``name(vol, b, sens, *scalars, n)`` on every slab, with this
        solver's sensitivity or ``sens`` (device slabs like ``vol``: several cameras')."""
        for v, bb, s in zip(vol, b, self.sens if sens is None else sens):
            self._run(name, v.size, v, bb, s, *scalars)

    def add_into(self, out, vol) -> None:
        """``out += vol`` slab by slab (device slabs of one plan), on the device."""
        for o, v in zip(out, vol, strict=True):
            self._run("add_into", o.size, o, v)

    def slice_extent(self, vol) -> np.ndarray:
        """Each depth slice's extent ``(nz, 4)`` int32: its first and last row ``y`` with a
        non-zero voxel and the first and last non-zero ``x`` over them (``(ny, -1, nx,
        -1)`` for an empty slice), computed on the device (each row's extent, then each
        slice's): only ``nz x 4`` values come back."""
        parts = []
        for v in vol:
            nz, ny, nx = v.shape
            rows = self._k.array((nz * ny, 2), np.int32)
            out = self._k.array((nz, 4), np.int32)
            self._k.launch("row_extent", (nz * ny,), v, np.int32(nx), rows, np.int32(nz * ny))
            self._k.launch("slice_extent", (nz,), rows, np.int32(ny), np.int32(nx), out,
                           np.int32(nz))
            parts.append(out.get())
        return np.concatenate(parts)

    def total(self, a, b=None) -> float:
        """``Σ a``, or ``Σ (a - b)²`` when ``b`` is given, reduced on the device."""
        out = self._k.array(_SUM_ITEMS)
        chunk = -(-a.size // _SUM_ITEMS) if self._k.is_cpu else 0
        self._k.launch("partial_sums", (_SUM_ITEMS,), a, a if b is None else b,
                       np.int32(b is not None), np.int32(chunk), out, np.int32(a.size))
        return float(out.get().astype(np.float64).sum())

    def ratio(self, img, proj, threshold: float, log_mode: bool, blocks=None, block=-1,
              floor: float = RATIO_MIN, out=None):
        """``I / max(P, eps)`` on the device, or ``log(max(ratio, floor))`` (``log_mode``),
        restricted to one block; into ``out`` (an image like ``img``; ``None``: a new
        one)."""
        out = cla.empty_like(img) if out is None else out
        block_of = blocks if blocks is not None else self._no_blocks
        self._run("ratio", self.n_pix, img, proj, block_of, np.int32(block),
                  np.float32(threshold), np.int32(log_mode), np.float32(floor),
                  self._observed, self._use_observed, out)
        return out

    def _dark_and_log(self, img, threshold: float, floor: float):
        dark, logimg = cla.empty_like(img), cla.empty_like(img)
        self._run("prepare_image", self.n_pix, img, np.float32(threshold), np.float32(floor),
                  self._observed, self._use_observed, dark, logimg)
        return dark, logimg

    def start(self, img, kind, threshold: float, scale: float = 1.0):
        """First guess: ``"uniform"`` (scaled to the image's total), ``"mlos"``, or a
        volume array in image units (divided by ``scale``, the image's scaling)."""
        if isinstance(kind, np.ndarray):
            return self.proj.volume_to_device(_start_volume(kind, self.proj.grid.shape) / scale)
        vol = self.proj.empty_volume()
        if kind == "uniform":
            # the projection of a volume of ones carries 1ᵀ A 1 = Σ sensitivity
            total = sum(self.total(s) for s in self.sens)
            for v in vol:
                fill(v, self.total(img) / max(total, 1e-30))
        elif kind == "mlos":
            _, logimg = self._dark_and_log(img, threshold, max(threshold, 1e-6))
            self.update_voxels("mlos", vol, self.proj.back_device(logimg), self.smin)
        else:
            raise ValueError(f"start must be 'uniform', 'mlos' or a volume array, got {kind!r}")
        return vol

    def spread_start(self, coarse, factor: int, scale: float = 1.0):
        """First guess from a volume in image units on the grid ``factor`` times coarser
        laterally (a coarse run's support, a start given on a supersampled
        reconstruction's grid): each voxel shared by its ``factor x factor`` sub-voxels,
        on the device (:func:`plenocl.reconstruction.supersample.spread_lateral`).
        ``coarse``: a host volume, or a coarse run's
        :class:`~plenocl.reconstruction.schedule.SupportStart`, found again on the
        device from the coarse volume kept there (nothing crosses) where it has it."""
        nz, ny, nx = self.proj.grid.shape
        shape = (nz, ny // factor, nx // factor)
        vol = self.proj.empty_volume()
        if isinstance(coarse, SupportStart) and coarse.on_device is not None:
            if coarse.on_device.shape != shape:
                raise ValueError(f"a coarse support of shape {coarse.on_device.shape} does "
                                 f"not spread by {factor} onto the grid {(nz, ny, nx)}")
            self.binning.spread_support(coarse.on_device, coarse.floor, coarse.level, factor,
                                        vol, 1.0 / scale)
            return vol
        if isinstance(coarse, SupportStart):
            coarse = coarse.flat()
        coarse = _start_volume(np.asarray(coarse), shape)
        self.binning.spread_into(coarse, factor, vol, 1.0 / scale)
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

        ``extent`` is ``vol``'s :meth:`slice_extent`. Returns ``(solver, vol, extent)``: a
        solver on the cropped projector (with :attr:`box` in full-grid indices) and the
        volume and extent on it, or ``self`` and the inputs when nothing is cropped.
        """
        local = extent_box(extent)
        size = int(np.prod(self.proj.grid.shape))
        if local is None or np.prod([s.stop - s.start for s in local]) > below * size:
            return self, vol, extent
        box = local if self.box is None else tuple(
            slice(b.start + s.start, b.start + s.stop) for b, s in zip(self.box, local))
        self.release_kept()  # the iterations go on with the cropped solver's
        sub = Solver(self.proj.cropped(local), float(self.smin), self.lit, box,
                     self.observed)
        if isinstance(self.proj, PlannedOperator):
            new_vol = self.proj.volume_box(vol, local, sub.proj)  # on the device
        else:  # an operator without a plan of its slabs: through the host
            new_vol = sub.proj.volume_to_device(
                np.ascontiguousarray(self.proj.volume_to_host(vol)[local]))
        return sub, new_vol, sub.slice_extent(new_vol)

    def placed_on(self, vol, proj: PlannedOperator) -> list[cla.Array]:
        """This solver's device volume on the full grid of ``proj`` (the grid it was
        cropped from, or the same grid held in other slabs), in ``proj``'s slabs: zeros
        outside :attr:`box`, copied on the device (nothing crosses to the host)."""
        if not isinstance(self.proj, PlannedOperator):
            raise TypeError(f"{type(self.proj).__name__} keeps no plan of its slabs: "
                            "bring the volume through the host (volume_to_host)")
        out = [fill(v, 0.0) for v in proj.empty_volume()]
        corner = (0, 0, 0) if self.box is None else tuple(s.start for s in self.box)
        slabs = [vol] if isinstance(vol, cla.Array) else list(vol)
        return copy_slabbed(out, proj.plan.slabs, corner, slabs, self.proj.plan.slabs,
                            (0, 0, 0), tuple(self.proj.grid.shape))

    def volume_to_host(self, vol, full_shape: tuple[int, int, int]) -> np.ndarray:
        """The host volume on the full grid of shape ``full_shape`` (0 outside :attr:`box`)."""
        if self.box is None:
            return self.proj.volume_to_host(vol)
        full = np.zeros(full_shape, np.float32)
        full[self.box] = self.proj.volume_to_host(vol)
        return full

    def binned_to_host(self, vol, factor: int, shape: tuple[int, int, int],
                       scale: float = 1.0) -> np.ndarray:
        """The volume summed over ``factor x factor`` lateral blocks on the device, times
        ``scale``, as a host volume on the full binned grid of shape ``shape`` (0 outside
        :attr:`box`): only the binned volume crosses to the host
        (:meth:`binned_to_device`)."""
        return self.binned_to_device(vol, factor, shape, scale).get()

    def binned_to_device(self, vol, factor: int, shape: tuple[int, int, int],
                         scale: float = 1.0) -> cla.Array:
        """:meth:`binned_to_host`'s volume as one float32 device array of ``shape`` (the
        next stage reads it there; ``factor`` 1: the volume itself, times ``scale``).

        A crop box need not start on a block boundary: the blocks it cuts are summed
        over the sub-voxels inside it (the others are 0 in the full fine grid).
        """
        if self.box is None:
            corner, offset = (0, 0, 0), (0, 0)
        else:
            z, y, x = self.box
            (y0, oy), (x0, ox) = divmod(y.start, factor), divmod(x.start, factor)
            corner, offset = (z.start, y0, x0), (oy, ox)
        parts = self.binning.binned(vol, factor, offset, scale)
        if self.box is None and len(parts) == 1:
            return parts[0]
        full = fill(cla.empty(self.queue, shape, np.float32), 0.0)
        z0 = corner[0]
        for part in parts:
            copy_inside(full, part, (z0, corner[1], corner[2]))
            z0 += part.shape[0]
        return full


# ---- one iteration per method ---------------------------------------------------------
def _simultaneous(solver: Solver, vol, img, active, relax: float, threshold: float,
                  log_ratio: bool, floor: float = RATIO_MIN) -> float:
    """One simultaneous update from one forward and one back projection; returns
    ``‖P - I‖`` before it."""
    fwd, back = solver.projections(log_ratio)
    proj = fwd(vol, out=_kept_image(solver, "projection", img), active=active)
    resid = solver.total(proj, img) ** 0.5
    ratio = solver.ratio(img, proj, threshold, log_ratio, floor=floor,
                         out=_kept_image(solver, "ratio", img))
    b = back(ratio, out=_kept_volume(solver), active=active, support=vol)
    if log_ratio:
        solver.update_voxels("update_exp", vol, b, np.float32(relax), solver.smin, np.int32(1))
    else:
        solver.update_voxels("update_mlem", vol, b, np.float32(relax), solver.smin)
    return resid


def update_mlem(solver: Solver, vol, img, active, relax: float, threshold: float,
                blocks=None, n_blocks: int = 1, ratio_floor: float | None = None) -> float:
    """MLEM: ``E ← E (Aᵀ r / s)^μ``; returns ``‖P - I‖`` before the update."""
    return _simultaneous(solver, vol, img, active, relax, threshold, log_ratio=False)


def update_smart(solver: Solver, vol, img, active, relax: float, threshold: float,
                 blocks=None, n_blocks: int = 1, ratio_floor: float | None = None) -> float:
    """SMART: ``E ← E exp(μ Aᵀ log r / s)`` (``r`` floored at ``ratio_floor``); returns
    ``‖P - I‖`` before the update."""
    return _simultaneous(solver, vol, img, active, relax, threshold, log_ratio=True,
                         floor=RATIO_MIN if ratio_floor is None else ratio_floor)


def update_mart(solver: Solver, vol, img, active, relax: float, threshold: float,
                blocks=None, n_blocks: int = 1, ratio_floor: float | None = None,
                sens=None) -> float:
    """Block MART: one multiplicative update per block of views, each with a fresh
    projection (``r`` floored at ``ratio_floor``); returns ``‖P - I‖`` before the first
    block. ``sens``: the sensitivity whose voxels at or below ``min_sensitivity`` stay 0
    (``None``: the solver's; several cameras: their sum)."""
    floor = RATIO_MIN if ratio_floor is None else ratio_floor
    fwd, back = solver.projections(log_ratio=True)
    proj = fwd(vol, out=_kept_image(solver, "projection", img), active=active)
    resid = solver.total(proj, img) ** 0.5
    for blk in range(n_blocks):
        if blk:
            proj = fwd(vol, out=proj, active=active)
        lr = solver.ratio(img, proj, threshold, True, blocks, -1 if blocks is None else blk,
                          floor, out=_kept_image(solver, "ratio", img))
        b = back(lr, out=_kept_volume(solver), active=active, support=vol)
        solver.update_voxels("update_exp", vol, b, np.float32(relax), solver.smin,
                             np.int32(0), sens=sens)
    return resid


def _kept_image(solver: Solver, name: str, img):
    """The solver's kept device image ``name``, shaped like the image ``img``."""
    return solver.kept(name, lambda: cla.empty_like(img))


def _kept_volume(solver: Solver):
    """The solver's kept device slabs of a back projection."""
    return solver.kept("back projection", solver.proj.empty_volume)


#: The update of each method, chosen once per reconstruction.
UPDATES = {"mlem": update_mlem, "smart": update_smart, "mart": update_mart}
