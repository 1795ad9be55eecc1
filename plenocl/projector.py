"""Matrix-free forward and back projection with the plenoptic weighting function.

The weight matrix of DESIGN §5 (paper §III.A) is never stored. A voxel's weight on a
pixel is a sum over aperture samples ``s`` and microlenses ``k`` of two bilinear
factors: ``S[k, s; voxel]`` (step 2, where the sample meets the array plane, in lens
index units) and ``P[pixel; k, s]`` (step 3, where that sample lands behind lens ``k``,
from the lens's own calibrated centre). The kernels apply the two factors in turn
through a light-field buffer ``L[ky, s, kx]``:

* forward ``image = P (S vol)`` and back ``vol = Sᵀ (Pᵀ image)``, exact transposes;
* with an axis-aligned microlens array (ideal or calibrated centres whose fitted layout
  has no rotation) ``S`` factorises per axis and costs a few vectorisable row updates
  per light-field row and depth; a rotated array uses a general (slower) path;
* every kernel is a gather or a race-free scatter: results are deterministic.

Memory is the volume, the image and scratch buffers bounded by ``scratch_bytes``
(light field and per-axis intermediates, processed in chunks of aperture columns and
depth slices). A volume larger than the device's largest allocation is held as depth
slabs. See ``kernels/projector.cl`` for the kernels and
:mod:`plenocl.reference.weights` for the plain NumPy model.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from .camera import Camera
from .device import DeviceLike, check_fits, device_info, get_queue
from .grid import Grid
from .lenses import LensSet, lens_reach, lens_set, lit_lenses
from .program import build_program, fetch_kernels
from .reference.weights import (
    DEFAULT_OVERSAMPLE,
    DEFAULT_SHEAR_TOL,
    ApertureGrid,
    LensIndexMap,
    lens_index_map,
)

_NO_LENS = -(1 << 30)  # PL_NO_LENS in kernels/projector.h
_KERNELS = ("fwd_x", "fwd_y", "fwd_gen", "fwd_pix", "back_pix", "back_y", "back_x",
            "back_gen", "voxel_footprint", "fwd_direct", "back_direct", "back_y_scatter")
METHODS = ("factorised", "direct")
#: Bounds of the automatic scratch size (each of the light-field and intermediate buffers).
SCRATCH_MIN_BYTES, SCRATCH_MAX_BYTES = 2 * 2**20, 32 * 2**20

VolumeLike = cl_array.Array | Sequence[cl_array.Array]
i32, f32 = np.int32, np.float32


@dataclass(frozen=True)
class Plan:
    """How the work is split: volume slabs, aperture-column chunks, depth chunks."""

    slabs: tuple[tuple[int, int], ...]    # [z0, z1) of each volume buffer
    columns: tuple[tuple[int, int], ...]  # [i0, i1) aperture columns per light-field chunk
    zchunk: int                           # depth slices per intermediate (T) chunk
    scratch_bytes: int                    # bytes of the light-field + T scratch buffers


# ---- host-side tables -------------------------------------------------------------------
def depth_coefficients(camera: Camera, grid: Grid, lens_map: LensIndexMap,
                       aperture: ApertureGrid) -> np.ndarray:
    """Per-depth affine coefficients ``(nz, 16)`` float64 (layout: kernels/projector.h).

    Voxel ``(ix, iy)`` of depth ``iz`` seen through aperture sample ``(i, j)`` meets the
    array plane at lens index ``G (ix, iy) + o + H (i - c, j - c)``.
    """
    z = grid.axis_centers("z")
    sip = camera.image_distance_at(z)
    alpha = sip / camera.image_distance_mm
    mag = sip / (camera.object_distance_mm + z)  # X' = -mag x
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
    """Per-lens centres as rounded pixel ``int2`` and remainder ``float2`` (NaN: missing)."""
    centres = camera.microlens_centers.reshape(-1, 2)
    ok = np.isfinite(centres).all(axis=1)
    rounded = np.where(ok[:, None], np.round(np.nan_to_num(centres)), _NO_LENS)
    frac = np.where(ok[:, None], np.nan_to_num(centres) - rounded, 0.0)
    return rounded.astype(np.int32), frac.astype(np.float32)


def colour_stride(camera: Camera, aperture: ApertureGrid, limit: int = 8) -> int:
    """Smallest lens stride ``cs`` such that lenses ``cs`` apart never share a pixel.

    Lens ``k`` writes pixels within ``E = c g + 1`` of its centre (``c g``: the outermost
    aperture sample behind it, in pixels); centres deviate from the fitted lattice by at
    most ``dev``. The forward kernel scatters one ``cs x cs`` colour class at a time.
    """
    cols, rows = camera.ml_count
    ky, kx = np.mgrid[0:rows, 0:cols]
    c = camera.microlens_centers
    ok = np.isfinite(c).all(axis=-1)
    design = np.column_stack([kx[ok], ky[ok], np.ones(ok.sum())])
    fit, *_ = np.linalg.lstsq(design, c[ok], rcond=None)
    dev = np.abs(design @ fit - c[ok]).max()
    reach = aperture.center * aperture.step * camera.ml_focal_length_mm / (
        camera.image_distance_mm * camera.pixel_pitch_mm) + 1.0
    steps = [(a, b) for a in range(-2, 3) for b in range(-2, 3) if (a, b) != (0, 0)]
    for cs in range(2, limit + 1):
        sep = min(np.abs(fit[:2].T @ (cs * np.array(s))).max() for s in steps)
        if sep - 2 * dev > 2 * reach:
            return cs
    raise ValueError("microlens images overlap so much that no race-free lens colouring "
                     f"with stride <= {limit} exists; stop the main lens down")


def _check_grid(camera: Camera, grid: Grid) -> None:
    """Depth range the camera can image."""
    limit = camera.focal_length_mm - camera.object_distance_mm
    if grid.z[0] <= limit:
        raise ValueError(
            f"the grid's depth range z = {grid.z} mm reaches z <= f - s_o = {limit:.3f} mm, "
            "where the main lens forms no real image; move the volume's near face beyond "
            f"z = {limit:.3f} mm"
        )


def _check_field_of_view(camera: Camera, grid: Grid, coef: np.ndarray,
                         aperture: ApertureGrid) -> None:
    """Fail when no voxel's light can reach any microlens."""
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


def make_plan(grid: Grid, camera: Camera, aperture: ApertureGrid, nkxp: int,
              max_alloc: int, scratch_bytes: int, method: str) -> Plan:
    """Split the volume into slabs and the light field into column chunks that fit."""
    nz, ny, nx = grid.shape
    width, height = camera.pixels
    if 4 * width * height > max_alloc:
        raise MemoryError(f"the {width} x {height} image needs {4 * width * height} bytes but "
                          f"the device allocates at most {max_alloc} bytes per buffer")
    slice_bytes = 4 * ny * nx
    if slice_bytes > max_alloc:
        raise MemoryError(f"one {ny} x {nx} depth slice needs {slice_bytes} bytes but the "
                          f"device allocates at most {max_alloc} bytes per buffer")
    depth = max(1, max_alloc // slice_bytes)
    slabs = tuple((z, min(z + depth, nz)) for z in range(0, nz, depth))
    if method == "direct":
        return Plan(slabs, ((0, aperture.n),), 1, 0)
    budget = min(max_alloc, scratch_bytes)
    lo, hi = aperture.column_ranges()
    row = 4 * camera.ml_count[1] * nkxp  # one sample's light-field plane
    t_row = 4 * ny * nkxp                # one (depth, column) intermediate
    columns = _column_chunks((hi - lo + 1) * row, t_row, budget)
    widest = max(b - a for a, b in columns)
    zchunk = max(1, min(nz, budget // (widest * t_row)))
    l_bytes = max((hi[a:b] - lo[a:b] + 1).sum() * row for a, b in columns)
    return Plan(slabs, tuple(columns), zchunk, int(l_bytes + zchunk * widest * t_row))


def _column_chunks(column_bytes: np.ndarray, t_row: int, budget: int) -> list[tuple[int, int]]:
    """Consecutive aperture columns whose light field (and one T slice) fit ``budget``."""
    if column_bytes.max() > budget or t_row > budget:
        raise MemoryError(f"one aperture column of the light field needs "
                          f"{max(column_bytes.max(), t_row)} bytes but at most {budget} bytes "
                          "may be allocated per buffer")
    columns, start, size = [], 0, 0
    for i, need in enumerate(column_bytes):
        if size + need > budget or (i - start + 1) * t_row > budget:
            columns.append((start, i))
            start, size = i, 0
        size += need
    columns.append((start, len(column_bytes)))
    return columns


class Projector:
    """Forward and back projection between a voxel grid and a plenoptic raw image.

    Parameters
    ----------
    camera
        The camera; its ``microlens_centers`` (calibrated or ideal) are used per lens.
    grid
        The reconstruction volume.
    queue
        A ``pyopencl.CommandQueue`` or anything :func:`plenocl.device.get_queue` accepts.
    oversample
        Aperture samples per pixel footprint on the aperture (``p_px s_i / f_ml``), per
        axis. Integer values sample the pixels evenly (2 correlates best with ray
        tracing) at a cost that grows with its square.
    shear_tol
        Rotation of the fitted lens layout, in lenses across the array, below which the
        separable fast path is used (see :func:`plenocl.reference.weights.lens_index_map`).
    method
        ``"factorised"`` (default) or ``"direct"`` (16 products per sample per voxel,
        forward by atomic scatter; the unfactorised baseline for benchmarks).
    max_alloc_bytes
        Largest single buffer; the device's limit when ``None``. Smaller values force
        depth slabs and smaller chunks (for tests).
    scratch_bytes
        Upper bound of each of the two scratch buffers (light-field chunk, per-axis
        intermediates). By default the larger of the volume and the image, clamped to
        2-32 MiB: larger chunks barely change the speed.
    vector_width, segment
        Explicit vector width of the row kernels (``PL_VW``) and vectors per work-item;
        by default 8 and a whole light-field row on CPUs (the row stays in cache), 1 and 1
        on other devices (coalesced access).

    Attributes
    ----------
    path
        ``"separable"`` or ``"general"`` (rotated array): which factorised kernels run.
    plan
        The slabs and chunks (:class:`Plan`).
    """

    def __init__(self, camera: Camera, grid: Grid, queue: DeviceLike = None, *,
                 oversample: float = DEFAULT_OVERSAMPLE, shear_tol: float = DEFAULT_SHEAR_TOL,
                 method: str = "factorised", max_alloc_bytes: int | None = None,
                 scratch_bytes: int | None = None, vector_width: int | None = None,
                 segment: int | None = None) -> None:
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        _check_grid(camera, grid)
        self.camera, self.grid, self.method = camera, grid, method
        self._options = dict(oversample=oversample, shear_tol=shear_tol, method=method,
                             max_alloc_bytes=max_alloc_bytes, scratch_bytes=scratch_bytes,
                             vector_width=vector_width, segment=segment)
        self.queue = get_queue(queue)
        self.aperture = ApertureGrid.for_camera(camera, oversample)
        self.lens_map = lens_index_map(camera, shear_tol)
        self.path = "separable" if self.lens_map.axis_aligned else "general"
        self.coef = depth_coefficients(camera, grid, self.lens_map, self.aperture)
        _check_field_of_view(camera, grid, self.coef, self.aperture)
        info = device_info(self.queue)
        self._layout(info, vector_width, segment)
        max_alloc = int(min(max_alloc_bytes or info.max_alloc_bytes, info.max_alloc_bytes))
        if scratch_bytes is None:
            scratch_bytes = int(np.clip(max(grid.nbytes, 4 * camera.pixels[0] * camera.pixels[1]),
                                        SCRATCH_MIN_BYTES, SCRATCH_MAX_BYTES))
        self.plan = make_plan(grid, camera, self.aperture, self.nkxp, max_alloc, scratch_bytes,
                              method)
        self.colour_stride = colour_stride(camera, self.aperture)
        self.lens_reach = lens_reach(self.aperture.center, float(self._dug))
        width, height = camera.pixels
        check_fits(self.queue, grid.nbytes + 4 * width * height + self.plan.scratch_bytes
                   + 16 * camera.ml_count[0] * camera.ml_count[1],
                   f"projecting a {grid.shape} grid onto the {width} x {height} sensor")
        program = build_program(self.queue.context, "projector.cl", [f"-DPL_VW={self.vw}"])
        self._k = fetch_kernels(program, _KERNELS)
        self._upload_tables()

    def _layout(self, info, vector_width: int | None, segment: int | None) -> None:
        """Vector width, padded row length and row segments for the device type."""
        self._cpu = cpu = "CPU" in info.type.upper()
        self.vw = int(vector_width or (8 if cpu else 1))
        if self.vw not in (1, 4, 8, 16):
            raise ValueError(f"vector_width must be 1, 4, 8 or 16, got {self.vw}")
        self.nkxp = -(-self.camera.ml_count[0] // self.vw) * self.vw
        self.seg = int(segment or (self.nkxp // self.vw if cpu else 1))
        if (self.nkxp // self.vw) % self.seg:
            raise ValueError(f"segment must divide the {self.nkxp // self.vw} vectors of a row")
        self.nseg = self.nkxp // self.vw // self.seg

    # ---- set-up -----------------------------------------------------------------------
    def _upload_tables(self) -> None:
        i, j = self.aperture.samples()
        lo, hi = self.aperture.column_ranges()
        rnd, frac = lens_tables(self.camera)
        q = self.queue
        self.n_samples = len(i)
        self._col_lo = lo
        self._col_off = np.concatenate([[0], np.cumsum(hi - lo + 1)[:-1]])
        self._d = {
            "coef": cl_array.to_device(q, self.coef.astype(np.float32)),
            "ij": cl_array.to_device(q, np.column_stack([i, j]).astype(np.int32)),
            "col_lo": cl_array.to_device(q, lo.astype(np.int32)),
            "col_off": cl_array.to_device(q, self._col_off.astype(np.int32)),
            "rnd": cl_array.to_device(q, rnd),
            "frac": cl_array.to_device(q, frac),
        }
        self._scratch: dict[str, cl_array.Array] = {}
        self._sensitivity: list[cl_array.Array] | None = None
        self._rnd = rnd
        self._present = rnd[:, 0] != _NO_LENS  # lenses with a centre
        self.all_lenses = self.lens_set(self._present)

    def _buffer(self, name: str, n: int) -> cl_array.Array:
        """A scratch buffer of at least ``n`` floats, kept between calls."""
        buf = self._scratch.get(name)
        if buf is None or buf.size < n:
            buf = self._scratch[name] = cl_array.empty(self.queue, max(n, 1), np.float32)
        return buf

    @property
    def shape(self) -> tuple[int, int, int]:
        """Volume shape ``(nz, ny, nx)``."""
        return self.grid.shape

    @property
    def image_shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)``."""
        return self.camera.pixels[1], self.camera.pixels[0]

    @property
    def _scale(self) -> np.float32:
        return f32(1.0 / self.n_samples)

    def _sample_range(self, i0: int, i1: int) -> tuple[int, int]:
        lo, off = self._col_lo, self._col_off
        end = off[i1 - 1] + (self.aperture.n - 1 - 2 * lo[i1 - 1]) + 1
        return int(off[i0]), int(end)

    # ---- host API ---------------------------------------------------------------------
    def forward(self, vol: np.ndarray) -> np.ndarray:
        """Project a volume ``(nz, ny, nx)`` onto the sensor: an image ``(H, W)`` float32."""
        slabs = self.volume_to_device(vol)
        return self.forward_device(slabs).get()

    def back(self, image: np.ndarray) -> np.ndarray:
        """Back-project an image ``(H, W)``: a volume ``(nz, ny, nx)`` float32 (``Aᵀ image``)."""
        img = _checked(image, self.image_shape, "image")
        return self.volume_to_host(self.back_device(cl_array.to_device(self.queue, img)))

    def volume_to_device(self, vol: np.ndarray) -> list[cl_array.Array]:
        """Checked float32 copy of a host volume as device slabs (see ``plan.slabs``)."""
        vol = _checked(vol, self.shape, "volume")
        return [cl_array.to_device(self.queue, vol[a:b]) for a, b in self.plan.slabs]

    def volume_to_host(self, slabs: VolumeLike) -> np.ndarray:
        """Gather device slabs into one host volume."""
        return np.concatenate([s.get() for s in self._as_slabs(slabs)], axis=0)

    def empty_volume(self) -> list[cl_array.Array]:
        """Uninitialised device slabs for a volume."""
        _, ny, nx = self.shape
        return [cl_array.empty(self.queue, (b - a, ny, nx), np.float32)
                for a, b in self.plan.slabs]

    def empty_image(self) -> cl_array.Array:
        """An uninitialised device image."""
        return cl_array.empty(self.queue, self.image_shape, np.float32)

    def sensitivity(self) -> list[cl_array.Array]:
        """``Aᵀ 1`` as device slabs: the fraction of each voxel's light that reaches the
        sensor. Computed on the first call and kept (one volume of device memory), so
        that reconstructing many images with one projector back-projects it once. The
        slabs are shared: do not write to them."""
        if self._sensitivity is None:
            ones = self.empty_image()
            ones.fill(1.0)
            self._sensitivity = self.back_device(ones)
        return self._sensitivity

    # ---- dark-microlens skipping ------------------------------------------------------
    def lit_lenses(self, image: np.ndarray, threshold: float = 0.0) -> np.ndarray:
        """Bool per lens (flat, row-major): does any pixel it can reach exceed
        ``threshold``? Missing lenses are never lit (see :mod:`plenocl.lenses`)."""
        img = _checked(image, self.image_shape, "image")
        if not np.isfinite(threshold):
            raise ValueError(f"threshold must be a finite number, got {threshold}")
        return lit_lenses(img, self._rnd, self.lens_reach, threshold) & self._present

    def lens_set(self, lit: np.ndarray) -> LensSet:
        """The :class:`plenocl.lenses.LensSet` of the lenses flagged in ``lit`` (for the
        ``lenses`` argument of :meth:`forward_device` and :meth:`back_device`)."""
        lit = np.asarray(lit, bool).ravel()
        if lit.size == self._rnd.shape[0]:
            lit = lit & self._present
        return lens_set(self.queue, lit, self.camera.ml_count, self.colour_stride)

    def _lenses(self, lenses: LensSet | None) -> LensSet:
        if lenses is None:
            return self.all_lenses
        if lenses.lit.size != self._rnd.shape[0]:
            raise ValueError(f"the lens set has {lenses.lit.size} lenses, the camera "
                             f"{self._rnd.shape[0]}")
        return lenses

    # ---- device API -------------------------------------------------------------------
    def forward_device(self, vol: VolumeLike, out: cl_array.Array | None = None,
                       active: np.ndarray | None = None, lenses: LensSet | None = None
                       ) -> cl_array.Array:
        """Forward projection of device slabs (or one device volume) into ``out``.

        Nothing is copied to the host; operations are enqueued on ``self.queue``.
        ``active`` (bool per depth slice) skips slices known to be zero. ``lenses`` (a
        :meth:`lens_set`) projects onto those microlenses only: the image is exact at
        every pixel they alone can reach (all lit pixels, for :meth:`lit_lenses`) and 0
        behind the others.
        """
        slabs = self._as_slabs(vol)
        active = self._active(active)
        lenses = self._lenses(lenses)
        out = self.empty_image() if out is None else out
        _check_device(out, self.image_shape, "out")
        if self.method == "direct":
            out.fill(0.0)
            for (z0, _), slab in zip(self.plan.slabs, slabs, strict=True):
                self._direct("fwd_direct", slab, out, z0)
            return out
        out.fill(0.0)
        if not active.any() or not lenses.count:
            return out
        for i0, i1 in self.plan.columns:
            light = self._fill_light_field(slabs, i0, i1, active, lenses)
            self._light_to_image(light, out, i0, i1, lenses)
        return out

    def back_device(self, image: cl_array.Array, out: VolumeLike | None = None,
                    active: np.ndarray | None = None, lenses: LensSet | None = None
                    ) -> list[cl_array.Array]:
        """Back projection of a device image into device slabs (returned).

        ``active`` (bool per depth slice) computes only those slices; the others are 0.
        ``lenses`` (a :meth:`lens_set`) reads only the pixels of those microlenses: exact
        for an image that is zero behind every other lens (a ratio image of the lit
        lenses).
        """
        _check_device(image, self.image_shape, "image")
        slabs = self.empty_volume() if out is None else self._as_slabs(out)
        active = self._active(active)
        lenses = self._lenses(lenses)
        for (z0, z1), slab in zip(self.plan.slabs, slabs, strict=True):
            for a, b in _runs(~active[z0:z1]):
                slab[a:b].fill(0.0)
        if self.method == "direct":
            for (z0, _), slab in zip(self.plan.slabs, slabs, strict=True):
                self._direct("back_direct", image, slab, z0)
            return slabs
        for n, (i0, i1) in enumerate(self.plan.columns):
            light = self._image_to_light(image, i0, i1, lenses)
            for (z0, z1), slab in zip(self.plan.slabs, slabs, strict=True):
                self._light_to_slab(light, slab, z0, z1, i0, i1, n > 0, active, lenses)
        return slabs

    def _active(self, active: np.ndarray | None) -> np.ndarray:
        """The per-slice activity mask (all slices when ``None``)."""
        if active is None:
            return np.ones(self.shape[0], bool)
        active = np.asarray(active, bool)
        if active.shape != (self.shape[0],):
            raise ValueError(f"active must be one bool per depth slice ({self.shape[0]}), "
                             f"got shape {active.shape}")
        return active

    def _zchunks(self, z0: int, z1: int, active: np.ndarray):
        """``(zc, nzc)`` chunks of consecutive active slices in ``[z0, z1)``."""
        for a, b in _runs(active[z0:z1]):
            for zc in range(z0 + a, z0 + b, self.plan.zchunk):
                yield zc, min(self.plan.zchunk, z0 + b - zc)

    def _as_slabs(self, vol: VolumeLike) -> list[cl_array.Array]:
        slabs = [vol] if isinstance(vol, cl_array.Array) else list(vol)
        if len(slabs) != len(self.plan.slabs):
            raise ValueError(f"expected {len(self.plan.slabs)} device slab(s) of depths "
                             f"{self.plan.slabs}, got {len(slabs)}")
        _, ny, nx = self.shape
        for (a, b), s in zip(self.plan.slabs, slabs, strict=True):
            _check_device(s, (b - a, ny, nx), f"volume slab z[{a}:{b}]")
        return slabs

    # ---- factorised stages -------------------------------------------------------------
    def _run(self, name: str, gsize: tuple[int, ...], *args, local=None) -> cl.Event:
        """Enqueue kernel ``name`` (buffers given as arrays or ``cl.Buffer``).

        On CPUs each work-item is a long loop and work-groups default to one item, so
        PoCL spreads them over all cores.
        """
        args = [a.data if isinstance(a, cl_array.Array) else a for a in args]
        if local is None and self._cpu:
            local = (1,) * len(gsize)
        return self._k[name](self.queue, gsize, local, *args)

    def _lens_args(self) -> tuple:
        """``nkx, nky, nkxp`` as kernel scalars."""
        cols, rows = self.camera.ml_count
        return i32(cols), i32(rows), i32(self.nkxp)

    def _fill_light_field(self, slabs, i0: int, i1: int, active: np.ndarray,
                          lenses: LensSet) -> cl_array.Array:
        """``L[s] = S vol`` for the samples of aperture columns ``[i0, i1)`` (at least one
        slice is active)."""
        s0, s1 = self._sample_range(i0, i1)
        nky, nic, ic = self.camera.ml_count[1], i1 - i0, self._ic
        _, ny, nx = self.shape
        light = self._buffer("L", (s1 - s0) * nky * self.nkxp)
        first = True
        for (z0, z1), slab in zip(self.plan.slabs, slabs, strict=True):
            for zc, nzc in self._zchunks(z0, z1, active):
                acc = i32(not first)
                nkx, _, nkxp = self._lens_args()
                first = False
                if self.path == "general":
                    self._run("fwd_gen", (s1 - s0,), slab, light, self._d["coef"], self._d["ij"],
                              i32(nx), i32(ny), nkx, i32(nky), nkxp, i32(z0), i32(zc), i32(nzc),
                              i32(s0), i32(s1 - s0), ic, acc)
                    continue
                t_buf = self._buffer("T", nzc * nic * ny * self.nkxp)
                self._run("fwd_x", (ny, nzc * nic), slab, t_buf, self._d["coef"], i32(nx),
                          i32(ny), nkx, nkxp, i32(z0), i32(zc), i32(i0), i32(nic), ic)
                self._run("fwd_y", (self.nseg, nky, nic), t_buf, light, self._d["coef"],
                          self._d["col_lo"], self._d["col_off"], lenses.rows, i32(ny), nkxp,
                          i32(self.seg), i32(self.aperture.n), i32(zc), i32(nzc), i32(i0),
                          i32(nic), i32(s0), i32(s1 - s0), ic, acc)
        return light

    def _light_to_image(self, light: cl_array.Array, out: cl_array.Array, i0: int, i1: int,
                        lenses: LensSet) -> None:
        """``image += P L`` for the listed lenses, one race-free colour class at a time."""
        s0, s1 = self._sample_range(i0, i1)
        nkx, _, nkxp = self._lens_args()
        for a, b in zip(lenses.offsets[:-1], lenses.offsets[1:], strict=True):
            if b > a:
                self._run("fwd_pix", (b - a,), light, out, lenses.ids, i32(a), self._d["rnd"],
                          self._d["frac"], self._d["ij"], *self._pixel_args(), nkx, nkxp,
                          i32(s0), i32(s1 - s0), self._ic, self._dug, self._scale)

    def _pixel_args(self) -> tuple:
        width, height = self.camera.pixels
        return i32(width), i32(height)

    @property
    def _ic(self) -> np.float32:
        return f32(self.aperture.center)

    @property
    def _dug(self) -> np.float32:
        """Sensor pixels per aperture-sample step behind a lens, ``du f_ml / (s_i p_px)``."""
        cam = self.camera
        return f32(self.aperture.step * cam.ml_focal_length_mm
                   / (cam.image_distance_mm * cam.pixel_pitch_mm))

    def _image_to_light(self, image: cl_array.Array, i0: int, i1: int, lenses: LensSet
                        ) -> cl_array.Array:
        """``L = Pᵀ image`` for the samples of aperture columns ``[i0, i1)`` (0 at the
        unlisted lenses)."""
        s0, s1 = self._sample_range(i0, i1)
        nkx, nky, nkxp = self._lens_args()
        n = (s1 - s0) * nky * self.nkxp
        light = self._buffer("L", n)
        light[:n].fill(0.0)
        if lenses.count:
            sps = (s1 - s0) if self._cpu else 1  # samples per work-item
            self._run("back_pix", (lenses.count, -(-(s1 - s0) // sps)), image, light,
                      lenses.ids, self._d["rnd"], self._d["frac"], self._d["ij"],
                      *self._pixel_args(), nkx, nkxp, i32(s0), i32(s1 - s0), i32(sps),
                      self._ic, self._dug, self._scale)
        return light

    def _light_to_slab(self, light, slab, z0: int, z1: int, i0: int, i1: int,
                       accumulate: bool, active: np.ndarray, lenses: LensSet) -> None:
        """``slab (+)= Sᵀ L`` for aperture columns ``[i0, i1)``, active slices only."""
        s0, s1 = self._sample_range(i0, i1)
        nkx, nky, nkxp = self._lens_args()
        _, ny, nx = self.shape
        nic, ic, acc = i1 - i0, self._ic, i32(accumulate)
        for zc, nzc in self._zchunks(z0, z1, active):
            if self.path == "general":
                self._run("back_gen", (ny, nzc), light, slab, self._d["coef"], self._d["ij"],
                          i32(nx), i32(ny), nkx, nky, nkxp, i32(z0), i32(zc), i32(s0),
                          i32(s1 - s0), ic, acc)
                continue
            t_buf = self._buffer("T", nzc * nic * ny * self.nkxp)
            self._run("back_y", (self.nseg, ny, nic), light, t_buf, self._d["coef"],
                      self._d["col_lo"], self._d["col_off"], lenses.rows, i32(ny), nky, nkxp,
                      i32(self.seg), i32(self.aperture.n), i32(zc), i32(nzc), i32(i0), i32(nic),
                      i32(s0), i32(s1 - s0), ic)
            self._run("back_x", (ny, nzc), t_buf, slab, self._d["coef"], i32(nx), i32(ny), nkx,
                      nkxp, i32(z0), i32(zc), i32(i0), i32(nic), ic, acc)

    # ---- direct path and single columns -------------------------------------------------
    def _direct(self, name: str, src: cl_array.Array, dst: cl_array.Array, z0: int) -> None:
        _, ny, nx = self.shape
        nkx, nky, _ = self._lens_args()
        depth = (src if name == "fwd_direct" else dst).shape[0]
        self._run(name, (nx, ny, depth), src, dst, self._d["coef"], self._d["ij"],
                  self._d["rnd"], self._d["frac"], i32(nx), i32(ny), nkx, nky,
                  *self._pixel_args(), i32(z0), i32(self.n_samples), self._ic, self._dug,
                  self._scale)

    def footprint_entries(self, voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw products of voxels ``(N, 3)`` as ``(iz, iy, ix)``: pixel indices and weights.

        Returns arrays ``(N, n_samples * 16)``; lost products have index -1 and weight 0.
        Duplicated pixels are not merged (see :meth:`voxel_weights`).
        """
        vox = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        nz, ny, nx = self.shape
        if ((vox < 0) | (vox >= np.array([nz, ny, nx]))).any():
            raise IndexError(f"voxel indices must lie in the grid of shape {self.shape}")
        packed = np.zeros((len(vox), 4), np.int32)
        packed[:, :3] = vox[:, ::-1]
        nkx, nky, _ = self._lens_args()
        ns = self.n_samples
        idx = cl_array.empty(self.queue, (len(vox), ns * 16), np.int32)
        wts = cl_array.empty(self.queue, (len(vox), ns * 16), np.float32)
        self._run("voxel_footprint", (ns, len(vox)), cl_array.to_device(self.queue, packed), idx,
                  wts, self._d["coef"], self._d["ij"], self._d["rnd"], self._d["frac"], nkx, nky,
                  *self._pixel_args(), i32(ns), self._ic, self._dug, self._scale)
        return idx.get(), wts.get()

    def cropped(self, box: tuple[slice, slice, slice]) -> Projector:
        """A projector for the sub-grid ``vol[box]`` (same camera, queue and options).

        Weights depend only on each voxel's centre, so the sub-projector's are the full
        projector's for those voxels (up to float32 rounding of the recomputed tables).
        A sensitivity already computed here is cropped and kept by the sub-projector
        instead of being back-projected again.
        """
        (z, y, x), g = box, self.grid
        if not all(0 <= s.start < s.stop <= n and s.step in (None, 1)
                   for s, n in zip(box, g.shape, strict=True)):
            raise ValueError(f"box must be a non-empty, unit-step sub-box of the grid "
                             f"{g.shape} (slices z, y, x), got {box}")
        dz, dy, dx = g.spacing
        sub = Grid((z.stop - z.start, y.stop - y.start, x.stop - x.start),
                   x=(g.x[0] + x.start * dx, g.x[0] + x.stop * dx),
                   y=(g.y[0] + y.start * dy, g.y[0] + y.stop * dy),
                   z=(g.z[0] + z.start * dz, g.z[0] + z.stop * dz))
        out = Projector(self.camera, sub, self.queue, **self._options)
        if self._sensitivity is not None:
            host = np.ascontiguousarray(self.volume_to_host(self._sensitivity)[box])
            out._sensitivity = out.volume_to_device(host)
        return out

    def voxel_weights(self, iz: int, iy: int, ix: int) -> tuple[np.ndarray, np.ndarray]:
        """One voxel's column of the weight matrix, computed by a kernel.

        Returns
        -------
        indices : numpy.ndarray of int64
            Flat pixel indices ``row * W + col``, sorted, with a positive weight.
        weights : numpy.ndarray of float32
            The weights (they sum to 1 when all the voxel's light reaches the sensor).
        """
        idx, wts = self.footprint_entries(np.array([[iz, iy, ix]]))
        keep = idx[0] >= 0
        pix, inverse = np.unique(idx[0][keep].astype(np.int64), return_inverse=True)
        total = np.bincount(inverse, weights=wts[0][keep].astype(np.float64),
                            minlength=len(pix))
        nonzero = total > 0
        return pix[nonzero], total[nonzero].astype(np.float32)


# ---- checks -----------------------------------------------------------------------------
def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[a, b)`` ranges of consecutive ``True`` entries of a 1-D bool array."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask, np.int8), [0]]))
    return list(zip(np.nonzero(edges == 1)[0].tolist(), np.nonzero(edges == -1)[0].tolist()))



def _checked(arr, shape: tuple[int, ...], what: str) -> np.ndarray:
    """``arr`` as C-contiguous float32 with ``shape``, finite, else a clear error."""
    a = np.asarray(arr)
    if a.shape != tuple(shape):
        raise ValueError(f"{what} has shape {a.shape}, expected {tuple(shape)}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)
            or a.dtype == bool):
        raise TypeError(f"{what} must hold real numbers, got dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    bad = ~np.isfinite(a)
    if bad.any():
        raise ValueError(f"{what} contains {int(bad.sum())} NaN or Inf value(s) (first at "
                         f"index {tuple(int(v) for v in np.argwhere(bad)[0])}); the projector "
                         "needs finite input")
    return a


def _check_device(arr: cl_array.Array, shape: tuple[int, ...], what: str) -> None:
    if not isinstance(arr, cl_array.Array):
        raise TypeError(f"{what} must be a pyopencl.array.Array, got {type(arr).__name__}")
    if arr.shape != tuple(shape) or arr.dtype != np.float32 or not arr.flags.c_contiguous:
        raise ValueError(f"{what} must be a C-contiguous float32 device array of shape "
                         f"{tuple(shape)}, got {arr.dtype} {arr.shape}")

