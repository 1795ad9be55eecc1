"""Matrix-free forward and back projection with the plenoptic weighting function.

The weight matrix of docs/design.md §5 (paper §III.A) is never stored. A voxel's weight on a
pixel is a sum over aperture samples ``s`` and microlenses ``k`` of two bilinear
factors: ``S[k, s; voxel]`` (step 2, where the sample meets the array plane, in lens
index units) and ``P[pixel; k, s]`` (step 3, where that sample lands behind lens ``k``,
from the lens's own calibrated centre). The kernels apply the two factors in turn
through a light-field buffer ``L[ky, s, kx]``:

* forward ``image = P (S vol)`` and back ``vol = Sᵀ (Pᵀ image)``, exact transposes;
* with an axis-aligned microlens array (ideal or calibrated centres whose fitted layout
  has no rotation in the grid's frame), or a hexagonal array's leaning lattice in its
  rows' frame (a triangular lens map, the aperture sampled along the lattice's steps,
  docs/design.md §5.3), ``S`` factorises per axis and costs a few vectorisable row
  updates per light-field row and depth; a grid across the lens rows is projected
  through the rows' frame and resampled, or with ``general="exact"`` on a general
  (slower) path;
* every kernel is a gather or a race-free scatter: results are deterministic (the
  optional ``back="atomic"`` scatter of the separable back projection excepted).

Memory is the volume, the image and scratch buffers bounded by ``scratch_bytes``
(light field and per-axis intermediates, processed in chunks of aperture columns and
depth slices; :mod:`plenocl.projection.plan`). A volume larger than the device's largest allocation
is held as depth slabs. The tables the kernels read come from the device-free
:class:`plenocl.projection.model.WeightingModel` (built on :mod:`plenocl.projection.weighting`);
``kernels/projector.cl`` holds the kernels and :mod:`plenocl.reference.weights` the plain
NumPy model. The projector implements :class:`plenocl.reconstruction.operator.ProjectionOperator`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pyopencl.array as cl_array

from ..camera import Camera
from ..camera.lattice import separable_rotation_deg
from ..grid import Grid
from ..opencl import pool
from ..opencl.arrays import copy_slabbed, fill, upload
from ..opencl.device import DeviceLike, check_fits, device_info, get_queue, is_cpu
from ..opencl.program import KernelSet
from ..optics.depthrange import check_grid
from ..options import is_integer, is_number
from .extent import PlaneExtent, lens_spans, whole_columns
from .factorised import FactorisedStages
from .lenses import LensSet, lens_set, lit_lenses, lit_lenses_on_device
from .model import WeightingModel, warn_general_path
from .plan import Plan, SampleColumns, make_plan, runs
from .posed import PoseResampler, one_slab, posed_frame_grid
from .resample import FrameResampler, frame_grid
from .weighting import DEFAULT_OVERSAMPLE, DEFAULT_SHEAR_TOL, ApertureGrid, LensIndexMap

_KERNELS = ("fwd_x", "fwd_x_row", "fwd_y", "fwd_gen", "fwd_gen_gather", "fwd_pix", "back_pix",
            "back_y", "back_x", "back_x_row", "back_gen", "voxel_footprint", "fwd_direct",
            "back_direct", "back_y_scatter")
#: Kernels with one work-item per output element (the driver picks their work-groups).
_ELEMENTWISE = ("fwd_gen_gather", "fwd_x", "back_x")
METHODS = ("factorised", "direct")
#: How a grid across a rotated array's lens rows is projected: through the lens-row
#: frame and a bilinear resampling (fast, :mod:`plenocl.projection.resample`), or by the
#: general kernels.
GENERAL_MODES = ("resample", "exact")
#: How an aperture sample's light is shared between the two lenses around the point where
#: it meets the array (``lens_weights``): the paper's bilinear weights, or the share of
#: the voxel's own extent in each lens's cell (issue 47; the same for a voxel a lens wide).
LENS_WEIGHTS = ("paper", "extent")
#: The default lens weights: the voxel's extent (docs/design.md §6.4, issue 47: more
#: particles recovered and a smaller depth error than the paper's at the same cost).
DEFAULT_LENS_WEIGHTS = "extent"
#: Back projections of the separable path: a deterministic gather, or a float-atomic scatter.
BACK_MODES = ("gather", "atomic")
#: Bounds of the automatic scratch size (each of the light-field and intermediate buffers):
#: at most 256 MiB, and at most 1/SCRATCH_MEMORY_SHARE of the device's memory. At the
#: paper's size one chunk then holds every aperture column, so the lens-column kernels
#: read each voxel row once per projection (32 MiB: three chunks, 3-8 % slower on
#: sub-voxels; ``benchmarks/projector.py``, scratch section).
SCRATCH_MIN_BYTES, SCRATCH_MAX_BYTES = 2 * 2**20, 256 * 2**20
SCRATCH_MEMORY_SHARE = 16

VolumeLike = cl_array.Array | Sequence[cl_array.Array]
i32, f32 = np.int32, np.float32


def _check_sizes(shear_tol, max_alloc_bytes, scratch_bytes) -> None:
    """``shear_tol`` a finite number (lenses; a negative one sends every array to the
    general path, no term dropped), the byte bounds positive integers or None: named,
    before a plan or a warning misreads them."""
    if not (is_number(shear_tol) and np.isfinite(shear_tol)):
        raise ValueError(f"shear_tol must be a finite number (lenses of drift the separable "
                         f"kernels allow; negative: the general path always), got "
                         f"{shear_tol!r}")
    for name, value in (("max_alloc_bytes", max_alloc_bytes),
                        ("scratch_bytes", scratch_bytes)):
        if value is not None and not (is_integer(value) and value > 0):
            raise ValueError(f"{name} must be a positive whole number of bytes or None "
                             f"(the device's rule), got {value!r}")


class Projector(FactorisedStages):
    """Forward and back projection between a voxel grid and a plenoptic raw image.

    Parameters
    ----------
    camera, grid
        The camera (its calibrated or ideal ``microlens_centers``) and the volume: the
        :class:`~plenocl.projection.model.WeightingModel` is built from them.
    queue
        A ``pyopencl.CommandQueue`` or anything :func:`plenocl.opencl.device.get_queue` accepts.
    oversample
        Aperture samples per pixel footprint on the aperture (``p_px d / f_ml``, ``d``:
        the exit pupil's distance from the array), per axis. Integer values sample the
        pixels evenly (2 correlates best with ray tracing) at a cost that grows with its
        square.
    shear_tol
        Rotation of the fitted lens layout, in lenses across the array, below which the
        separable fast path is used (see :func:`plenocl.projection.weighting.lens_index_map`).
    method
        ``"factorised"`` (default) or ``"direct"`` (16 products per sample per voxel,
        forward by atomic scatter; the unfactorised baseline for benchmarks).
    back
        ``"gather"`` (default: every output element summed by one work-item in a fixed
        order, so results are bit-for-bit repeatable) or ``"atomic"``: the separable
        path's lens-row stage scatters each light-field row into the intermediate with
        float atomic adds. The atomic order of summation varies from run to run (results
        differ in the last bits); which is faster depends on the device
        (``benchmarks/projector.py``). The general path and the direct method always
        gather.
    max_alloc_bytes
        Largest single buffer; the device's limit when ``None``. Smaller values force
        depth slabs and smaller chunks (for tests).
    scratch_bytes
        Upper bound of each of the two scratch buffers (light-field chunk, per-axis
        intermediates). By default the larger of the volume and the image, clamped to
        2-32 MiB: larger chunks barely change the speed.
    gather_forward
        Run the kernels with one work-item per output element: the general path's
        forward light field by a gather (``fwd_gen_gather``) instead of one work-item per
        aperture sample scattering every voxel (``fwd_gen``), and the separable path's
        lens-column stage one T element (``fwd_x``) and one voxel (``back_x``) per
        work-item instead of one row (``fwd_x_row``, ``back_x_row``). Both give the same
        result bit for bit; by default GPUs gather (thousands of work-items, coalesced)
        and CPUs take the row forms (a row stays in cache; the forward skips zero voxels).
    vector_width, segment
        Explicit vector width of the row kernels (``PL_VW``) and vectors per work-item;
        by default on CPUs :func:`cpu_vector_width` (16 where the device's native float
        vectors hold 16, as AVX-512's do; else 8) and a whole light-field row (the row
        stays in cache), 1 and 1 on other devices (coalesced access).
    model
        A prebuilt :class:`plenocl.projection.model.WeightingModel` of this camera and
        grid (its ``oversample`` and ``shear_tol`` then win over the keywords); built
        here when ``None``.
    general
        A grid across a rotated array's lens rows (its axes turned against them, e.g. the
        sensor's): ``"resample"`` (default) projects it through a separable projector on
        a grid along the lens rows with a bilinear resampling between the two
        (:attr:`frame`, :mod:`plenocl.projection.resample`, docs/design.md §5.1; about the
        speed of the lens-row grid itself); ``"exact"`` evaluates the weighting function
        per voxel on the general kernels (about 12x slower at the paper's size).
    frame
        The lens-row frame's projector to resample through (its grid shares this grid's
        depth planes and covers it laterally); built when ``None`` and needed.
    lens_weights
        ``"extent"`` (default, :data:`DEFAULT_LENS_WEIGHTS`): the share of the voxel's
        lateral extent, projected through the sample onto the array, in each lens's cell
        (the paper's weights for a voxel one lens wide, narrower for a sub-voxel;
        ``benchmarks/weights.py``, docs/design.md §6.4); ``"paper"``: the paper's
        bilinear weights between the two lenses around the point where an aperture
        sample meets the array, whatever the voxel's size.

    Attributes
    ----------
    model
        The device-free weighting model (:class:`plenocl.projection.model.WeightingModel`):
        aperture samples, lens map, coefficients, lens tables, colouring.
    path
        ``"separable"``, ``"general"`` (a grid across a rotated array's lens rows on the
        general kernels) or ``"resampled"`` (through :attr:`frame`).
    frame
        The lens-row frame's separable :class:`Projector` of a resampled grid (``None``
        otherwise); :meth:`volume_to_frame` and :meth:`volume_from_frame` move volumes
        between the two grids, and a reconstruction runs on it (docs/design.md §5.1).
    resampler
        Its :class:`plenocl.projection.resample.FrameResampler` (``S`` and ``Sᵀ`` on device
        slabs); set with :attr:`frame`.
    plan
        The slabs and chunks (:class:`Plan`).
    """

    def __init__(self, camera: Camera, grid: Grid, queue: DeviceLike = None, *,
                 oversample: float = DEFAULT_OVERSAMPLE, shear_tol: float = DEFAULT_SHEAR_TOL,
                 method: str = "factorised", back: str = "gather",
                 max_alloc_bytes: int | None = None, scratch_bytes: int | None = None,
                 vector_width: int | None = None, segment: int | None = None,
                 gather_forward: bool | None = None, general: str = "resample",
                 model: WeightingModel | None = None, frame: Projector | None = None,
                 lens_weights: str = DEFAULT_LENS_WEIGHTS) -> None:
        if not isinstance(camera, Camera) or not isinstance(grid, Grid):
            raise TypeError(f"Projector(camera, grid) takes a plenocl.Camera and a "
                            f"plenocl.Grid, got {type(camera).__name__} and "
                            f"{type(grid).__name__}: read files with "
                            "plenocl.Camera.from_toml(path) and plenocl.Grid.from_toml(path)")
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if back not in BACK_MODES:
            raise ValueError(f"back must be one of {BACK_MODES}, got {back!r}")
        if general not in GENERAL_MODES:
            raise ValueError(f"general must be one of {GENERAL_MODES}, got {general!r}")
        if lens_weights not in LENS_WEIGHTS:
            raise ValueError(f"lens_weights must be one of {LENS_WEIGHTS}, got "
                             f"{lens_weights!r}")
        _check_sizes(shear_tol, max_alloc_bytes, scratch_bytes)
        self._options = dict(oversample=oversample, shear_tol=shear_tol,
                             method=method, back=back, max_alloc_bytes=max_alloc_bytes,
                             scratch_bytes=scratch_bytes, vector_width=vector_width,
                             segment=segment, gather_forward=gather_forward,
                             general=general, lens_weights=lens_weights)
        self.queue = get_queue(queue)
        self.resampler: FrameResampler | PoseResampler | None = None
        self.pose = camera.pose
        self.method, self.back_mode, self.lens_weights = method, back, lens_weights
        model, frame = self._model_and_frame(camera, grid, model, frame)
        # a hexagonal array's lenses on its axial lattice (Camera.on_lens_lattice; a
        # posed camera's view keeps its pose, a rectangular array is itself)
        camera = model.camera if self.pose is None else camera.on_lens_lattice()
        self.camera, self.grid, self.model, self.frame = camera, grid, model, frame
        self._options.update(oversample=model.oversample, shear_tol=model.shear_tol)
        self._variants: dict[tuple, Projector] = {}
        self._lit_kernels: KernelSet | None = None
        self._lit_centres: cl_array.Array | None = None
        self._layout(vector_width, segment)
        self.plan = self._make_plan(max_alloc_bytes, scratch_bytes)
        if self.pose is not None:
            one_slab(self.plan.slabs)
            one_slab(self.frame.plan.slabs)
        width, height = camera.pixels
        check_fits(self.queue, grid.nbytes + 4 * width * height + self.plan.scratch_bytes
                   + 16 * camera.ml_count[0] * camera.ml_count[1],
                   f"projecting a {grid.shape} grid onto the {width} x {height} sensor")
        # every projector kernel but the element ones (_ELEMENTWISE) loops over a row, a
        # sample's plane or a lens's samples
        self._k = self._kernel_set(extent=False)
        self._k_extent: KernelSet | None = None  # built by the first extent()
        self.gather_forward = (not self._k.is_cpu) if gather_forward is None else gather_forward
        self._upload_tables()

    def _model_and_frame(self, camera: Camera, grid: Grid, model: WeightingModel | None,
                         frame: Projector | None
                         ) -> tuple[WeightingModel, Projector | None]:
        """The weighting model and the frame projected through: a posed camera's frame
        grid (:meth:`_posed_frame`, its model the frame's), a grid across the lens rows'
        frame (:meth:`_frame_projector`), or the grid itself (``None``)."""
        if self.pose is not None:  # a world grid: through the camera's own frame (.posed)
            frame = self._posed_frame(camera, grid, frame, model)
            return frame.model, frame
        opts = self._options
        if model is None:
            model = WeightingModel(camera, grid, opts["oversample"], opts["shear_tol"],
                                   warn=False)
        elif camera not in (model.camera, model.source_camera) or model.grid != grid:
            raise ValueError("the weighting model belongs to another camera or grid")
        self.camera, self.grid, self.model = model.camera, grid, model
        opts.update(oversample=model.oversample, shear_tol=model.shear_tol)
        return model, self._frame_projector(frame) if model.path == "general" else None

    def _posed_frame(self, camera: Camera, grid: Grid, frame: Projector | None,
                     model: WeightingModel | None) -> Projector:
        """The separable projector of the posed camera's frame grid
        (:func:`.posed.posed_frame_grid`, ``frame`` when given) through which the world
        ``grid`` is projected, and its :class:`.posed.PoseResampler`."""
        if model is not None or self._options["method"] == "direct":
            raise ValueError("a posed camera's grid is projected through the camera's own "
                             "frame: it takes neither a prebuilt weighting model nor the "
                             "direct method")
        check_grid(camera, grid)
        own = camera.with_pose(None)
        if frame is None:
            angle = separable_rotation_deg(own.on_lens_lattice().microlens_centers,
                                           self._options["shear_tol"])
            frame = Projector(own, posed_frame_grid(grid, camera, angle), self.queue,
                              **{**self._options, "general": "exact"})
        if frame.path != "separable":
            raise ValueError(f"the posed camera's frame grid {frame.grid} does not project "
                             "on the separable path; build it along the lens rows "
                             "(posed_frame_grid)")
        check_fits(self.queue, 2 * grid.nbytes + 3 * frame.grid.nbytes,
                   f"resampling the world grid {grid.shape} onto the posed camera's frame "
                   f"grid {frame.grid.shape}")
        self.resampler = PoseResampler(self.queue, grid, frame.grid, camera.pose)
        self._frame_slabs: dict[str, list[cl_array.Array]] = {}
        # the frame's planes are 0 beyond the tilted grid's band: projected inside it only
        self._frame_extent = frame.extent(self.resampler.frame_columns)
        return frame

    def _frame_projector(self, frame: Projector | None) -> Projector | None:
        """The lens-row frame's separable projector through which this grid is projected
        (``frame``, or built on :func:`.resample.frame_grid`; ``None``, with the general
        path's warning, when no frame makes the array separable). ``None`` without a
        warning when the options ask for the general kernels (``general="exact"``) or the
        direct method."""
        opts = self._options
        if opts["general"] == "exact" or self.method == "direct":
            return None
        if frame is None:
            angle = separable_rotation_deg(self.camera.microlens_centers, opts["shear_tol"])
            frame = Projector(self.camera, frame_grid(self.grid, angle), self.queue,
                              **{**opts, "general": "exact"})
        if frame.path != "separable":
            warn_general_path(self.camera, self.grid)
            return None
        self.resampler = FrameResampler(self.queue, self.grid, frame.grid)
        self._frame_slabs: dict[str, list[cl_array.Array]] = {}
        self._frame_extent = None  # a lateral turn: the frame's planes are the grid's
        check_fits(self.queue, 3 * frame.grid.nbytes, f"resampling the {self.grid.shape} "
                   f"grid onto the {frame.grid.shape} grid of the lens rows")
        return frame

    # ---- the weighting model's tables, as the model holds them ----------------------------
    @property
    def aperture(self) -> ApertureGrid:
        """The aperture samples (:attr:`WeightingModel.aperture`)."""
        return self.model.aperture

    @property
    def lens_map(self) -> LensIndexMap:
        """Array-plane mm to fractional lens index (:attr:`WeightingModel.lens_map`)."""
        return self.model.lens_map

    @property
    def path(self) -> str:
        """``"separable"``, ``"general"`` (a grid across the array's lens rows, general
        kernels) or ``"resampled"`` (such a grid projected through the lens-row frame)."""
        if self.pose is not None:
            return "posed"
        return "resampled" if self.frame is not None else self.model.path

    @property
    def coef(self) -> np.ndarray:
        """Per-depth coefficients (:attr:`WeightingModel.coef`)."""
        return self.model.coef

    @property
    def colour_stride(self) -> int:
        """Lens stride of the race-free forward scatter."""
        return self.model.colour_stride

    @property
    def lens_reach(self) -> int:
        """Half-width (pixels) of the patch a lens's samples touch."""
        return self.model.lens_reach

    def _make_plan(self, max_alloc_bytes: int | None, scratch_bytes: int | None) -> Plan:
        """The slabs and chunks on this device (:func:`plenocl.projection.plan.make_plan`)."""
        info = device_info(self.queue)
        max_alloc = int(min(max_alloc_bytes or info.max_alloc_bytes, info.max_alloc_bytes))
        if scratch_bytes is None:
            pixels = self.camera.pixels[0] * self.camera.pixels[1]
            top = min(SCRATCH_MAX_BYTES, info.global_mem_bytes // SCRATCH_MEMORY_SHARE)
            scratch_bytes = int(np.clip(max(self.grid.nbytes, 4 * pixels),
                                        SCRATCH_MIN_BYTES, max(top, SCRATCH_MIN_BYTES)))
        return make_plan(self.grid, self.camera, self.aperture, self.nkxp, max_alloc,
                         scratch_bytes, self.method)

    def _layout(self, vector_width: int | None, segment: int | None) -> None:
        """Vector width, padded row length and row segments for the device type."""
        cpu = is_cpu(self.queue.device)
        self.vw = int(vector_width or (cpu_vector_width(self.queue.device) if cpu else 1))
        if self.vw not in (1, 4, 8, 16):
            raise ValueError(f"vector_width must be 1, 4, 8 or 16, got {self.vw}")
        self.nkxp = -(-self.camera.ml_count[0] // self.vw) * self.vw
        self.seg = int(segment or (self.nkxp // self.vw if cpu else 1))
        if (self.nkxp // self.vw) % self.seg:
            raise ValueError(f"segment must divide the {self.nkxp // self.vw} vectors of a row")
        self.nseg = self.nkxp // self.vw // self.seg
        # a CPU's whole-row back_y work-items cover every aperture column of a chunk
        # (PL_BACK_ALLCOLS: weights computed once for all columns, L rows reused in L1)
        self.back_allcols = cpu and self.nseg == 1

    # ---- set-up -----------------------------------------------------------------------
    def _upload_tables(self) -> None:
        i, j = self.aperture.samples()
        lo, hi = self.aperture.column_ranges()
        rnd, frac = self.model.lens_tables
        q = self.queue
        self.n_samples = len(i)
        self._columns = SampleColumns.of(self.aperture)
        self._d = {
            "coef": upload(q, self.coef.astype(np.float32)),
            "ij": upload(q, np.column_stack([i, j]).astype(np.int32)),
            "px": upload(q, self.model.pixel_offsets),
            "col_lo": upload(q, lo.astype(np.int32)),
            "col_hi": upload(q, hi.astype(np.int32)),
            "col_off": upload(q, self._columns.offset.astype(np.int32)),
            "rnd": upload(q, rnd),
            "frac": upload(q, frac),
        }
        self._scratch: dict[str, cl_array.Array] = {}
        self._sensitivity: list[cl_array.Array] | None = None
        self.all_lenses = self.lens_set(self.model.present)
        nz, _, nx = self.shape
        whole = np.tile(np.array([0, self.nkxp // self.vw]), (nz, len(lo), 1))
        self.whole_extent = PlaneExtent.upload(q, whole_columns(nz, nx), whole)

    def _kernel_set(self, extent: bool) -> KernelSet:
        """The projector's kernels; with ``extent`` the separable ones keep to a
        :class:`PlaneExtent` (``PL_EXTENT``: without it they take whole rows, unread)."""
        return KernelSet(self.queue, "projector.cl", _KERNELS,
                         [f"-DPL_VW={self.vw}", f"-DPL_BACK_ALLCOLS={int(self.back_allcols)}",
                          f"-DPL_LENS_EXTENT={int(self.lens_weights == 'extent')}",
                          f"-DPL_EXTENT={int(extent)}",
                          f"-DPL_SCALAR_ROWS={int(self.vw == 1 and self.seg == 1)}"],
                         looping=[k for k in _KERNELS if k not in _ELEMENTWISE])

    def _kernels(self, extent: PlaneExtent) -> KernelSet:
        """The kernel set that runs ``extent`` (the plain one for the whole extent)."""
        if extent is self.whole_extent:
            return self._k
        if self._k_extent is None:
            self._k_extent = self._kernel_set(extent=True)
        return self._k_extent

    def extent(self, columns: np.ndarray) -> PlaneExtent:
        """The :class:`plenocl.projection.extent.PlaneExtent` of a volume that is 0 beyond
        each plane's voxel columns ``columns`` (``(nz, 2)``, ``[x0, x1)``), for the
        ``extent`` argument of :meth:`forward_device` and :meth:`back_device`."""
        nz, ny, nx = self.shape
        columns = np.asarray(columns, np.int64)
        if columns.shape != (nz, 2) or np.any(columns < 0) or np.any(columns > nx):
            raise ValueError(f"columns must be ({nz}, 2) voxel column ranges within "
                             f"[0, {nx}], got shape {columns.shape}")
        bu = np.arange(len(self._columns.lo)) - self.aperture.center
        spans = lens_spans(self.coef, columns, bu, ny, self.camera.ml_count[0], self.vw)
        return PlaneExtent.upload(self.queue, columns, spans)

    def _buffer(self, name: str, n: int) -> cl_array.Array:
        """A scratch buffer of at least ``n`` floats, kept between calls."""
        buf = self._scratch.get(name)
        if buf is None or buf.size < n:
            buf = self._scratch[name] = pool.made(
                self.queue, lambda: cl_array.empty(self.queue, max(n, 1), np.float32))
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

    def device_bytes(self) -> int:
        """Device bytes the projector holds itself: weight tables and scratch buffers
        (not the kept sensitivity, nor the caller's volumes and images)."""
        own = sum(b.nbytes for b in [*self._d.values(), *self._scratch.values()])
        if self.frame is not None:
            own += self.frame.device_bytes() + sum(
                s.nbytes for slabs in self._frame_slabs.values() for s in slabs)
        return int(own)

    # ---- host API ---------------------------------------------------------------------
    def forward(self, vol: np.ndarray) -> np.ndarray:
        """Project a volume ``(nz, ny, nx)`` onto the sensor: an image ``(H, W)`` float32."""
        slabs = self.volume_to_device(vol)
        return self.forward_device(slabs).get()

    def back(self, image: np.ndarray) -> np.ndarray:
        """Back-project an image ``(H, W)``: a volume ``(nz, ny, nx)`` float32 (``Aᵀ image``)."""
        img = _checked(image, self.image_shape, "image")
        return self.volume_to_host(self.back_device(upload(self.queue, img)))

    def volume_to_device(self, vol: np.ndarray) -> list[cl_array.Array]:
        """Checked float32 copy of a host volume as device slabs (see ``plan.slabs``)."""
        vol = _checked(vol, self.shape, "volume")
        return [upload(self.queue, vol[a:b]) for a, b in self.plan.slabs]

    def volume_to_host(self, slabs: VolumeLike) -> np.ndarray:
        """Gather device slabs into one host volume."""
        return np.concatenate([s.get() for s in self._as_slabs(slabs)], axis=0)

    def empty_volume(self) -> list[cl_array.Array]:
        """Uninitialised device slabs for a volume."""
        _, ny, nx = self.shape
        return [pool.empty(self.queue, (b - a, ny, nx), np.float32)
                for a, b in self.plan.slabs]

    def empty_image(self) -> cl_array.Array:
        """An uninitialised device image."""
        return pool.empty(self.queue, self.image_shape, np.float32)

    def sensitivity(self) -> list[cl_array.Array]:
        """``Aᵀ 1`` as device slabs: the fraction of each voxel's light that reaches the
        sensor. Computed on the first call and kept (one volume of device memory), so
        that reconstructing many images with one projector back-projects it once. The
        slabs are shared: do not write to them."""
        if self._sensitivity is None:
            ones = self.empty_image()
            fill(ones, 1.0)
            self._sensitivity = self.back_device(ones)
        return self._sensitivity

    def use_sensitivity(self, sensitivity: VolumeLike | np.ndarray) -> None:
        """Keep a known ``Aᵀ 1`` (a host volume of this grid, or its device slabs, e.g. a
        larger projector's, cropped: :meth:`volume_box`) instead of back-projecting it on
        the first :meth:`sensitivity` call."""
        self._sensitivity = (self.volume_to_device(sensitivity)
                             if isinstance(sensitivity, np.ndarray)
                             else self._as_slabs(sensitivity))

    # ---- dark-microlens skipping ------------------------------------------------------
    def lit_lenses(self, image, threshold: float = 0.0) -> np.ndarray:
        """Bool per lens (flat, row-major): does any pixel it can reach exceed
        ``threshold``? Missing lenses are never lit (see :mod:`plenocl.projection.lenses`).
        ``image``: a host image, or a float32 device array of the image's shape on this
        projector's queue (then found there, ``kernels/lenses.cl``: the same flags)."""
        if not np.isfinite(threshold):
            raise ValueError(f"threshold must be a finite number, got {threshold}")
        threshold = float(threshold)  # compared with the float32 image as a float32
        if isinstance(image, cl_array.Array):
            if image.shape != tuple(self.image_shape) or image.dtype != np.float32:
                raise ValueError(f"a device image must be float32 of shape "
                                 f"{tuple(self.image_shape)}, got {image.dtype} {image.shape}")
            lit = lit_lenses_on_device(self._lens_kernels(), image, self._lens_centres(),
                                       self.lens_reach, threshold)
        else:
            lit = lit_lenses(_checked(image, self.image_shape, "image"),
                             self.model.lens_tables[0], self.lens_reach, threshold)
        return lit & self.model.present

    def _lens_kernels(self) -> KernelSet:
        """``kernels/lenses.cl`` on this queue, built at the first device image."""
        if self._lit_kernels is None:
            self._lit_kernels = KernelSet(self.queue, "lenses.cl", ["lit_patches", "pack_flags"])
        return self._lit_kernels

    def _lens_centres(self) -> cl_array.Array:
        """The rounded lens centres ``(n_lenses, 2)`` int32 on the device, uploaded once."""
        if self._lit_centres is None:
            rounded = np.asarray(self.model.lens_tables[0], np.int32).reshape(-1, 2)
            self._lit_centres = upload(self.queue, rounded)
        return self._lit_centres

    def lens_set(self, lit: np.ndarray) -> LensSet:
        """The :class:`plenocl.projection.lenses.LensSet` of the lenses flagged in ``lit`` (for the
        ``lenses`` argument of :meth:`forward_device` and :meth:`back_device`)."""
        lit = np.asarray(lit, bool).ravel()
        if lit.size == self.model.present.size:
            lit = lit & self.model.present
        return lens_set(self.queue, lit, self.camera.ml_count, self.colour_stride)

    def _lenses(self, lenses: LensSet | None) -> LensSet:
        if lenses is None:
            return self.all_lenses
        if lenses.lit.size != self.model.present.size:
            raise ValueError(f"the lens set has {lenses.lit.size} lenses, the camera "
                             f"{self.model.present.size}")
        return lenses

    # ---- device API -------------------------------------------------------------------
    def forward_device(self, vol: VolumeLike, out: cl_array.Array | None = None,
                       active: np.ndarray | None = None, lenses: LensSet | None = None,
                       extent: PlaneExtent | None = None) -> cl_array.Array:
        """Forward projection of device slabs (or one device volume) into ``out``.

        Nothing is copied to the host; operations are enqueued on ``self.queue``.
        ``active`` (bool per depth slice) skips slices known to be zero. ``lenses`` (a
        :meth:`lens_set`) projects onto those microlenses only: the image is exact at
        every pixel they alone can reach (all lit pixels, for :meth:`lit_lenses`) and 0
        behind the others. ``extent`` (an :meth:`extent`): the volume is 0 beyond it, and
        the separable path reads it only inside.
        """
        slabs = self._as_slabs(vol)
        active = self._active(active)
        lenses = self._lenses(lenses)
        out = self.empty_image() if out is None else out
        _check_device(out, self.image_shape, "out")
        if self.frame is not None:
            return self._resampled_forward(slabs, out, active, lenses)
        if self.method == "direct":
            fill(out, 0.0)
            for (z0, _), slab in zip(self.plan.slabs, slabs, strict=True):
                self._direct("fwd_direct", slab, out, z0)
            return out
        fill(out, 0.0)
        if not active.any() or not lenses.count:
            return out
        for i0, i1 in self.plan.columns:
            light = self.volume_to_light(slabs, i0, i1, active, lenses, extent)
            self.light_to_image(light, out, i0, i1, lenses)
        return out

    def back_device(self, image: cl_array.Array, out: VolumeLike | None = None,
                    active: np.ndarray | None = None, lenses: LensSet | None = None,
                    support: VolumeLike | None = None, reuse_forward: bool = False,
                    extent: PlaneExtent | None = None) -> list[cl_array.Array]:
        """Back projection of a device image into device slabs (returned).

        ``active`` (bool per depth slice) computes only those slices; the others are 0.
        ``lenses`` (a :meth:`lens_set`) reads only the pixels of those microlenses: exact
        for an image that is zero behind every other lens (a ratio image of the lit
        lenses). ``support`` (device slabs of the grid, e.g. the volume being updated):
        its zero voxels may be left out, the result there is then 0 (what a
        multiplicative update needs: a zero voxel stays zero); the separable path skips
        them in the rows where they are the majority, the general and direct paths
        compute them. ``reuse_forward``: ``support`` is the volume this projector's last
        :meth:`forward_device` projected, unchanged since (an iteration's order): a
        resampled grid's frame then takes that projection's resampled volume as its
        support instead of resampling ``support`` again (the same zero voxels).
        ``extent`` (an :meth:`extent`): only the voxels inside it are wanted; the
        separable path computes those alone and writes 0 beyond them.
        """
        _check_device(image, self.image_shape, "image")
        slabs = self.empty_volume() if out is None else self._as_slabs(out)
        sup = [None] * len(slabs) if support is None else self._as_slabs(support)
        active = self._active(active)
        lenses = self._lenses(lenses)
        for (z0, z1), slab in zip(self.plan.slabs, slabs, strict=True):
            for a, b in runs(~active[z0:z1]):
                fill(slab[a:b], 0.0)
        if self.frame is not None:
            return self._resampled_back(image, slabs, active, lenses, support,
                                        reuse_forward)
        if self.method == "direct":
            for (z0, _), slab in zip(self.plan.slabs, slabs, strict=True):
                self._direct("back_direct", image, slab, z0)
            return slabs
        for n, (i0, i1) in enumerate(self.plan.columns):
            light = self.image_to_light(image, i0, i1, lenses)
            for (z0, z1), slab, s in zip(self.plan.slabs, slabs, sup, strict=True):
                self.light_to_volume(light, slab, z0, z1, i0, i1, n > 0, active, lenses, s,
                                     extent)
        return slabs

    # ---- a grid across the lens rows, through the lens-row frame (.resample) -------------
    def _frame_volume(self, name: str) -> list[cl_array.Array]:
        """Frame-grid device slabs kept for ``name`` (``"forward"``, ``"support"``,
        ``"back"``)."""
        if name not in self._frame_slabs:
            self._frame_slabs[name] = self.frame.empty_volume()
        return self._frame_slabs[name]

    def _resampled_forward(self, slabs, out: cl_array.Array, active: np.ndarray,
                           lenses: LensSet) -> cl_array.Array:
        """``out = A_frame S vol`` (docs/design.md §5.1)."""
        frame_vol = self._frame_volume("forward")
        self.resampler.to_frame(slabs, self.plan.slabs, frame_vol, self.frame.plan.slabs,
                                 active)
        return self.frame.forward_device(frame_vol, out, self._frame_active(active), lenses,
                                         self._frame_extent)

    def _resampled_back(self, image: cl_array.Array, slabs, active: np.ndarray,
                        lenses: LensSet, support, reuse_forward: bool = False
                        ) -> list[cl_array.Array]:
        """``slabs = Sᵀ A_frameᵀ image`` on the active planes; a support is resampled onto
        the frame (its zero frame voxels touch no support voxel, so skipping them there is
        exact here too), or with ``reuse_forward`` the last forward projection's
        resampled volume is (:meth:`back_device`)."""
        own, frame = self.plan.slabs, self.frame.plan.slabs
        frame_support = None
        if support is not None:
            support = self._as_slabs(support)
            if reuse_forward and "forward" in self._frame_slabs:
                frame_support = self._frame_volume("forward")
            else:
                frame_support = self._frame_volume("support")
                self.resampler.to_frame(support, own, frame_support, frame, active)
        back = self.frame.back_device(image, self._frame_volume("back"),
                                      self._frame_active(active), lenses, frame_support,
                                      extent=self._frame_extent)
        self.resampler.from_frame(back, frame, slabs, own, active, support)
        return slabs

    def _frame_active(self, active: np.ndarray) -> np.ndarray:
        """The frame's planes that read this grid's ``active`` planes (the same planes,
        but for a posed camera's tilted frame)."""
        if self.pose is None:
            return active
        return self.resampler.frame_active(active)

    def volume_to_frame(self, vol: np.ndarray) -> np.ndarray:
        """``S vol``: a host volume on this grid resampled onto the lens-row frame's grid
        (:attr:`frame`, a grid across the array's lens rows only; docs/design.md §5.1)."""
        self._need_frame()
        out = self.frame.empty_volume()
        for slab in out:  # a tilted frame's planes beyond the grid are not written
            fill(slab, 0.0)
        self.resampler.to_frame(self.volume_to_device(vol), self.plan.slabs, out,
                                 self.frame.plan.slabs, np.ones(self.shape[0], bool))
        return self.frame.volume_to_host(out)

    def volume_from_frame(self, vol: np.ndarray) -> np.ndarray:
        """``Sᵀ vol``: a host volume on the lens-row frame's grid resampled onto this one,
        each voxel the mix of the frame voxels about its centre with its normalised
        bilinear weights (which sum to 1)."""
        self._need_frame()
        out = self.empty_volume()
        self.resampler.from_frame(self.frame.volume_to_device(vol), self.frame.plan.slabs,
                                   out, self.plan.slabs, np.ones(self.shape[0], bool))
        return self.volume_to_host(out)

    def _need_frame(self) -> None:
        if self.frame is None:
            raise ValueError(f"this projector's grid is not resampled (path {self.path!r}): "
                             "only a grid across a rotated array's lens rows has a frame")

    def _active(self, active: np.ndarray | None) -> np.ndarray:
        """The per-slice activity mask (all slices when ``None``)."""
        if active is None:
            return np.ones(self.shape[0], bool)
        active = np.asarray(active, bool)
        if active.shape != (self.shape[0],):
            raise ValueError(f"active must be one bool per depth slice ({self.shape[0]}), "
                             f"got shape {active.shape}")
        return active

    def _as_slabs(self, vol: VolumeLike) -> list[cl_array.Array]:
        slabs = [vol] if isinstance(vol, cl_array.Array) else list(vol)
        if len(slabs) != len(self.plan.slabs):
            raise ValueError(f"expected {len(self.plan.slabs)} device slab(s) of depths "
                             f"{self.plan.slabs}, got {len(slabs)}")
        _, ny, nx = self.shape
        for (a, b), s in zip(self.plan.slabs, slabs, strict=True):
            _check_device(s, (b - a, ny, nx), f"volume slab z[{a}:{b}]")
        return slabs

    def footprint_entries(self, voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw products of voxels ``(N, 3)`` as ``(iz, iy, ix)``: pixel indices and weights.

        Returns arrays ``(N, n_samples * 16)``; lost products have index -1 and weight 0.
        Duplicated pixels are not merged (see :meth:`voxel_weights`).
        """
        vox = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        nz, ny, nx = self.shape
        if ((vox < 0) | (vox >= np.array([nz, ny, nx]))).any():
            raise IndexError(f"voxel indices must lie in the grid of shape {self.shape}")
        if self.frame is not None:
            return self._resampled_footprints(vox)
        packed = np.zeros((len(vox), 4), np.int32)
        packed[:, :3] = vox[:, ::-1]
        nkx, nky, _ = self._lens_args()
        ns = self.n_samples
        idx = cl_array.empty(self.queue, (len(vox), ns * 16), np.int32)
        wts = cl_array.empty(self.queue, (len(vox), ns * 16), np.float32)
        self._k.launch("voxel_footprint", (ns, len(vox)), self._k.to_device(packed), idx, wts,
                       self._d["coef"], self._d["ij"], self._d["px"], self._d["rnd"],
                       self._d["frac"], nkx, nky, *self._pixel_args(), i32(ns), self._ic,
                       self._scale)
        return idx.get(), wts.get()

    def _resampled_footprints(self, vox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`footprint_entries` of ``A_frame S``: each voxel's frame voxels (its
        column of ``S``), their products scaled by its weight in them."""
        if self.pose is not None:
            frame_vox, w = self.resampler.columns(vox)
            n, k = w.shape
            frame_vox = frame_vox.reshape(-1, 3)
        else:
            ab, w = self.resampler.columns(vox[:, 2], vox[:, 1])
            n, k = w.shape
            frame_vox = np.column_stack([np.repeat(vox[:, 0], k), ab[..., 1].ravel(),
                                         ab[..., 0].ravel()])
        idx, wts = self.frame.footprint_entries(frame_vox)
        wts = wts * w.reshape(-1, 1).astype(np.float32)
        idx = np.where(wts > 0, idx, -1)
        return idx.reshape(n, -1), np.where(idx >= 0, wts, 0).reshape(n, -1)

    def refined(self, factor: int) -> Projector:
        """A projector for this grid with ``factor x factor`` lateral sub-voxels per voxel
        (:meth:`plenocl.Grid.refined`; same camera, queue and options), built once per
        factor and kept: the supersampled reconstruction's projector. A resampled grid's
        refines through its frame's refined grid (``refined(f).frame`` is
        ``frame.refined(f)``)."""
        if factor == 1:
            return self
        frame = None if self.frame is None else self.frame.refined(factor)
        return self._kept(("refined", factor), frame, self.grid.refined(factor))

    @property
    def oversample(self) -> float:
        """Aperture samples per pixel footprint (:attr:`WeightingModel.oversample`)."""
        return self.model.oversample

    def sampled(self, oversample: float) -> Projector:
        """A projector for this grid with the aperture sampled ``oversample`` times per
        pixel footprint (same camera, queue and other options; a resampled grid's through
        its frame's), built once per value and kept: the coarse-to-fine reconstruction's
        coarse iterations and its first sub-voxel ones (docs/design.md §6.5). ``self`` at
        this projector's own value."""
        if oversample == self.oversample:
            return self
        frame = None if self.frame is None else self.frame.sampled(oversample)
        return self._kept(("oversample", oversample), frame, oversample=oversample)

    def weighted(self, lens_weights: str) -> Projector:
        """A projector for this grid with ``lens_weights`` (:data:`LENS_WEIGHTS`; same
        camera, queue and other options; a resampled grid's through its frame's), built
        once per value and kept: what a reconstruction whose settings name the lens
        weights runs on. ``self`` at this projector's own."""
        if lens_weights == self.lens_weights:
            return self
        frame = None if self.frame is None else self.frame.weighted(lens_weights)
        return self._kept(("lens_weights", lens_weights), frame, lens_weights=lens_weights)

    def _kept(self, key: tuple, frame: Projector | None, grid: Grid | None = None,
              **changes) -> Projector:
        """The projector of ``grid`` (default: this one's) with this one's options but
        ``changes``, through ``frame``, built on the first call with ``key`` and kept:
        :meth:`refined`, :meth:`sampled` and :meth:`weighted` share it."""
        if key not in self._variants:
            self._variants[key] = Projector(self.camera, self.grid if grid is None else grid,
                                            self.queue, **{**self._options, **changes},
                                            frame=frame)
        return self._variants[key]

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
                   z=(g.z[0] + z.start * dz, g.z[0] + z.stop * dz), rotation_deg=g.rotation_deg)
        out = Projector(self.camera, sub, self.queue, **self._options)
        if self._sensitivity is not None:
            out.use_sensitivity(self.volume_box(self._sensitivity, box, out))
        return out

    def volume_box(self, vol: VolumeLike, box: tuple[slice, slice, slice],
                   into: Projector) -> list[cl_array.Array]:
        """``vol[box]`` of this projector's device volume as device slabs of ``into``
        (this projector :meth:`cropped` to ``box``), copied on the device: one
        rectangular copy per pair of slabs that overlap, nothing through the host."""
        size = tuple(s.stop - s.start for s in box)
        if size != tuple(into.shape):
            raise ValueError(f"box {box} holds {size} voxels, the projector it goes to "
                             f"{tuple(into.shape)}: give this projector's cropped(box)")
        return copy_slabbed(into.empty_volume(), into.plan.slabs, (0, 0, 0),
                            self._as_slabs(vol), self.plan.slabs,
                            tuple(s.start for s in box), size)

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


def cpu_vector_width(device) -> int:
    """The row kernels' vector width on a CPU ``device`` (a ``pyopencl.Device``): 16
    where its native float vectors hold 16 (AVX-512), else 8. The same sums either way
    (each lane adds as before, the padding lanes hold zeros); on an AVX-512 Xeon a
    forward + back on the paper's sub-voxels took 0.79x the time at 16 under PoCL and
    0.86x under Intel's runtime (``benchmarks/projector.py``; docs/design.md §6.5)."""
    return 16 if device.native_vector_width_float >= 16 else 8


# ---- checks -----------------------------------------------------------------------------
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
