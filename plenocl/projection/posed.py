"""A world grid seen by a posed camera, projected through the camera's own frame
(docs/design.md §5.5, issue 49).

A camera file's ``[pose]`` places the camera in a world frame shared with other cameras
(:class:`plenocl.camera.Pose`: ``X_camera = R X_world + t``). The separable projector
needs a grid in the camera's own frame, its axes along the lens rows; a world grid is
tilted against it in three dimensions. Its projector applies ``A_frame S``: ``S``
interpolates the world volume trilinearly at the voxel centres of a *frame grid* in the
camera's frame with the same voxel size (:func:`posed_frame_grid`), each world voxel's
taps normalised to sum to 1 (light conserved), and ``A_frame`` is that grid's separable
projector; the back projection is ``Sᵀ A_frameᵀ``, its exact transpose. The lateral
resampling of :mod:`plenocl.projection.resample` is the special case without a tilt;
``kernels/resample.cl`` (``to_frame_3d``, ``from_frame_3d``) holds ``S`` and ``Sᵀ``, and
:func:`plenocl.reference.resample.resample_matrix_3d` is the NumPy twin.
"""

from __future__ import annotations

import math

import numpy as np
import pyopencl.array as cl_array

from ..camera import Camera, Pose
from ..camera.lattice import rotation_matrix
from ..grid import Grid
from ..opencl.program import KernelSet
from ..optics.depthrange import field_of_view_mm
from .plan import runs
from .resample import SlabRanges, Slabs

i32, f32 = np.int32, np.float32


def posed_frame_grid(grid: Grid, camera: Camera, rotation_deg: float) -> Grid:
    """The grid in the posed ``camera``'s own frame, its lateral axes turned by
    ``rotation_deg`` (the lens rows), that holds every voxel of the world ``grid``'s
    interpolation the camera can see: the same voxel size, covering ``grid`` grown by
    one voxel on every side, cut laterally to the camera's field of view over those
    depths (:func:`plenocl.optics.depthrange.field_of_view_mm`, also grown by one voxel:
    a tilted grid's corners reach beyond it, where no light reaches the sensor), snapped
    to whole voxels about its centre."""
    dz, dy, dx = grid.spacing
    turn = rotation_matrix(rotation_deg)
    camera_pts = camera.pose.to_camera(grid.corners(1.0))
    turned = camera_pts.copy()
    turned[:, :2] = camera_pts[:, :2] @ turn  # Rᵀ x, as rows
    lo, hi = turned.min(axis=0), turned.max(axis=0)
    steps = np.array([dx, dy, dz])
    n = np.ceil((hi - lo) / steps - 1e-9).astype(int)
    lo = (lo + hi) / 2 - n * steps / 2  # whole voxels about the box's centre
    seen_lo, seen_hi = _field_box(camera.with_pose(None), lo[2], lo[2] + n[2] * steps[2],
                                  turn)
    # whole voxels off each side beyond the field (and a voxel's margin): the voxels
    # kept stay where the uncut grid has them
    cut_lo = np.clip(np.floor((seen_lo - steps[:2] - lo[:2]) / steps[:2]), 0, None)
    cut_hi = np.clip(np.floor((lo[:2] + n[:2] * steps[:2] - seen_hi - steps[:2])
                              / steps[:2]), 0, None)
    lo[:2] += cut_lo * steps[:2]
    n[:2] -= (cut_lo + cut_hi).astype(int)
    if np.any(n < 1):  # check_grid refuses such a grid first
        raise ValueError("the posed camera sees no part of the grid")
    ext = [(lo[k], lo[k] + n[k] * steps[k]) for k in range(3)]
    return Grid((int(n[2]), int(n[1]), int(n[0])), *ext, rotation_deg=rotation_deg)


def _field_box(camera: Camera, z0: float, z1: float, turn: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The lateral box (in the frame turned by ``turn``) holding the camera's field of
    view at every depth in ``[z0, z1]`` (sampled at 17 depths and its ends)."""
    corners = []
    for z in np.linspace(z0, z1, 17):
        (x0, x1), (y0, y1) = field_of_view_mm(camera, float(z))
        corners += [[x0, y0], [x0, y1], [x1, y0], [x1, y1]]
    turned = np.asarray(corners) @ turn
    return turned.min(axis=0), turned.max(axis=0)


def pose_index_map(frame: Grid, grid: Grid, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """``(M, t)``: the world ``grid``'s fractional index ``M (a, b, c) + t`` of the frame
    voxel ``(a, b, c)``'s centre (float64; the frame lies in the camera's frame)."""
    abc = np.vstack([np.zeros(3), np.eye(3)])
    p = grid.to_index(pose.to_world(frame.from_index(abc)))
    return (p[1:] - p[0]).T, p[0]


def frame_columns(frame_shape: tuple[int, int, int], grid_shape: tuple[int, int, int],
                  matrix: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``(fnz, 2)`` int: each frame plane's voxel columns ``[a0, a1)`` whose trilinear
    taps can reach the world grid, one column more each side (``a0 == a1``: none).

    A frame voxel ``(a, b, c)`` has a tap in the grid only where its world index
    ``p = M (a, b, c) + t`` lies within ``(-1, n)`` on every axis; for each ``(b, c)``
    that bounds ``a`` to an open interval, and a plane's columns are the hull over ``b``.
    The extra column each side absorbs the kernels' fixed-point rounding."""
    fnz, fny, fnx = frame_shape
    n = np.array(grid_shape[::-1], np.float64)  # (nx, ny, nz): p's axes
    b, c = np.meshgrid(np.arange(fny), np.arange(fnz), indexing="xy")  # (fnz, fny)
    lo, hi = np.full(b.shape, -np.inf), np.full(b.shape, np.inf)
    for k in range(3):
        m = matrix[k, 0]
        rest = matrix[k, 1] * b + matrix[k, 2] * c + offset[k]
        if abs(m) < 1e-12:  # this axis does not change along a
            outside = (rest <= -1) | (rest >= n[k])
            lo[outside], hi[outside] = np.inf, -np.inf
            continue
        ends = np.stack([(-1 - rest) / m, (n[k] - rest) / m])
        lo, hi = np.maximum(lo, ends.min(axis=0)), np.minimum(hi, ends.max(axis=0))
    # the open interval's whole numbers run from floor(lo) + 1 to ceil(hi) - 1: one more
    # each side
    first, last = np.floor(lo), np.ceil(hi)
    seen = last >= first
    out = np.zeros((fnz, 2), np.int64)
    for z in np.flatnonzero(seen.any(axis=1)):
        a0 = int(np.clip(first[z][seen[z]].min(), 0, fnx))
        a1 = int(np.clip(last[z][seen[z]].max() + 1, 0, fnx))
        out[z] = (a0, max(a0, a1))
    return out


#: The fixed-point scale of the kernels' frame-to-world map (``PL_FX_ONE``: 32 bits of
#: fraction in 64-bit integers).
FX_ONE = 2.0 ** 32


def _whole_snapped(values) -> np.ndarray:
    """``values`` (float64) with entries within 1e-9 of a whole number taken whole."""
    values = np.asarray(values, np.float64)
    whole = np.round(values)
    return np.where(np.abs(values - whole) < 1e-9, whole, values)


def fixed_point_map(matrix: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The kernels' map (``kernels/resample.cl``): ``matrix``'s columns (the steps of the
    world index along the frame's ``a``, ``b`` and ``c``) then ``offset``, as int64 with
    32 fractional bits. Entries within 1e-9 of a whole number are taken whole, so that a
    whole-voxel shift or a quarter turn resamples exactly (taps exactly 1 and 0)."""
    values = _whole_snapped(np.concatenate([np.asarray(matrix, np.float64).T.ravel(),
                                            np.asarray(offset, np.float64)]))
    return np.round(values * FX_ONE).astype(np.int64)


def candidate_box(matrix: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, tuple]:
    """Where ``Sᵀ`` looks for the frame voxels whose taps hold a world voxel ``X``: the
    box from ``floor(start X) + 1`` (``start``: the rows of ``M⁻¹`` then
    ``-M⁻¹ t - reach``, in the kernels' fixed point) with ``counts`` candidates along
    ``a``, ``b``, ``c``.

    A tap holds ``X`` only where ``|p - X| < 1`` on every axis, so its frame position
    ``q = M⁻¹ (X - t)`` is within ``reach = Σ|M⁻¹ row|`` (open), which holds at most
    ``ceil(2 reach)`` whole numbers; a candidate at that distance exactly has every
    ``|p - X|`` at 1, and weight 0. Where a row of ``M⁻¹`` and its start are whole
    numbers (an axis the pose leaves along the world's, on whole voxels: a turn about y
    keeps y), ``q - reach`` is whole for every ``X``, both ends fall on whole numbers and
    the open interval holds ``2 reach - 1`` (one candidate for a unit row). Elsewhere
    the fixed point's start errs by about 1e-7 voxel, so a candidate it could leave out
    weighs less than float32 resolves."""
    inv = _whole_snapped(np.linalg.inv(matrix))
    reach = np.abs(inv).sum(axis=1)
    start = _whole_snapped(np.concatenate([inv.ravel(), -inv @ _whole_snapped(offset)
                                           - reach]))
    counts = []
    for k, r in enumerate(reach):
        row = np.append(inv[k], start[9 + k])
        on_whole = np.all(row == np.round(row)) and 2 * r == round(2 * r)
        counts.append(i32(round(2 * r) - 1 if on_whole else math.ceil(2 * r - 1e-6)))
    return np.round(start * FX_ONE).astype(np.int64), tuple(counts)


class PoseResampler:
    """``S`` and ``Sᵀ`` between a world grid and a posed camera's frame grid, on one
    queue; the interface of :class:`plenocl.projection.resample.FrameResampler`.

    ``S`` interpolates trilinearly with each world voxel's taps normalised to sum to 1
    over the frame (:attr:`norm` holds the sums before). Both volumes are one device
    slab each (a posed camera's grid must fit one allocation).

    Parameters
    ----------
    queue
        The projector's queue.
    grid, frame
        The world grid and the frame grid (:func:`posed_frame_grid`).
    pose
        The camera's pose.
    """

    def __init__(self, queue, grid: Grid, frame: Grid, pose: Pose) -> None:
        self.grid, self.frame, self.pose = grid, frame, pose
        self._k = KernelSet(queue, "resample.cl",
                            ("to_frame_3d", "from_frame_3d", "from_frame_3d_row"),
                            looping=("from_frame_3d_row",))
        #: ``Sᵀ`` by world rows (a work-item along each: CPUs) or by voxels (GPUs); the
        #: same numbers either way
        self.row_form = self._k.is_cpu
        m, t = pose_index_map(frame, grid, pose)
        self.matrix, self.offset = m, t
        self.fixed_map = fixed_point_map(m, t)
        self._map = self._k.to_device(self.fixed_map)
        self.fixed_start, self.counts = candidate_box(m, t)
        self._start = self._k.to_device(self.fixed_start)
        # a pose that keeps the world's y: each y row's items run together (the kernels'
        # b_outer / y_outer: their reads stay in cache)
        self.rows_outer = bool(np.allclose(m[[0, 2], 1], 0.0) and np.allclose(m[1, [0, 2]], 0.0))
        self.frame_columns = frame_columns(frame.shape, grid.shape, m, t)
        self._columns = self._k.to_device(self.frame_columns.astype(np.int32))
        self._planes = self._planes_read()
        self.norm = self._column_sums()
        inverse = np.divide(1.0, self.norm, out=np.zeros_like(self.norm),
                            where=self.norm > 0)  # a voxel no frame voxel reads: 0
        self._norm = self._k.to_device(inverse.astype(np.float32))

    def _planes_read(self) -> np.ndarray:
        """``(fnz, 2)``: the first and last world planes each frame plane's taps read."""
        fnz, fny, fnx = self.frame.shape
        corners = np.array([[a, b, 0.0] for a in (0, fnx - 1) for b in (0, fny - 1)])
        z = corners @ self.matrix[2] + self.offset[2]
        z = z[None, :] + np.arange(fnz)[:, None] * self.matrix[2, 2]
        lo = np.floor(z.min(axis=1) - 1e-4).astype(int)
        return np.column_stack([lo, np.floor(z.max(axis=1) + 1e-4).astype(int) + 1])

    def frame_active(self, active: np.ndarray) -> np.ndarray:
        """Bool per frame plane: does it read an ``active`` world plane?"""
        nz = self.grid.shape[0]
        on = np.concatenate([[0], np.cumsum(np.asarray(active, bool))])
        lo, hi = np.clip(self._planes[:, 0], 0, nz), np.clip(self._planes[:, 1] + 1, 0, nz)
        return on[hi] > on[lo]

    def _column_sums(self) -> np.ndarray:
        """``(nz, ny, nx)`` float64: each world voxel's trilinear taps summed over the
        frame (the unnormalised ``Sᵀ 1``, on the device)."""
        ones = self._k.to_device(np.ones(self.frame.shape, np.float32))
        out = self._k.array(self.grid.shape)
        unit = self._k.to_device(np.ones(self.grid.shape, np.float32))
        self._from_frame(ones, out, np.ones(self.grid.shape[0], bool), None, unit)
        return out.get().astype(np.float64)

    def to_frame(self, vol: Slabs, vol_slabs: SlabRanges, out: Slabs, out_slabs: SlabRanges,
                 active: np.ndarray) -> None:
        """``out = S vol`` on the frame planes that read an active plane (the others are
        left as they are)."""
        (user,), (frame,) = one_slab(vol, vol_slabs), one_slab(out, out_slabs)
        unz, uny, unx = self.grid.shape
        _, fny, fnx = self.frame.shape
        outer = self.rows_outer
        for c0, c1 in runs(self.frame_active(active)):
            size = (fnx, c1 - c0, fny) if outer else (fnx, fny, c1 - c0)
            self._k.launch("to_frame_3d", size, user, self._norm, i32(unx), i32(uny),
                           i32(unz), frame, i32(fnx), i32(fny), i32(c0), self._map,
                           i32(outer), self._columns)

    def from_frame(self, frame_vol: Slabs, frame_slabs: SlabRanges, out: Slabs,
                   out_slabs: SlabRanges, active: np.ndarray, support: Slabs | None = None
                   ) -> None:
        """``out = Sᵀ frame_vol`` on the active planes (the others are left as they are);
        0 without computing it where ``support`` (slabs like ``out``) is 0."""
        (frame,), (user,) = one_slab(frame_vol, frame_slabs), one_slab(out, out_slabs)
        sup = None if support is None else one_slab(support, out_slabs)[0]
        self._from_frame(frame, user, active, sup, self._norm)

    def _from_frame(self, frame: cl_array.Array, user: cl_array.Array, active: np.ndarray,
                    support: cl_array.Array | None, norm: cl_array.Array) -> None:
        """:meth:`from_frame` on single arrays, each world voxel's sum scaled by ``norm``."""
        _, uny, unx = self.grid.shape
        fnz, fny, fnx = self.frame.shape
        sup = (user, i32(0)) if support is None else (support, i32(1))
        outer = self.rows_outer
        for z0, z1 in runs(np.asarray(active, bool)):
            if self.row_form:
                name, size = "from_frame_3d_row", (uny, z1 - z0)
            else:
                name = "from_frame_3d"
                size = (unx, z1 - z0, uny) if outer else (unx, uny, z1 - z0)
            self._k.launch(name, size, frame, i32(fnx), i32(fny), i32(fnz), user, norm, *sup,
                           i32(unx), i32(uny), i32(z0), self._map, self._start, *self.counts,
                           i32(outer))

    def columns(self, voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The columns of ``S`` (normalised) of world voxels ``(N, 3)`` ``(iz, iy, ix)``,
        on the host: frame voxels ``(N, K, 3)`` as ``(c, b, a)`` and their weights
        ``(N, K)`` (``K`` candidates per voxel, unused ones at ``(0, 0, 0)``, weight 0)."""
        vox = np.asarray(voxels, np.int64).reshape(-1, 3)
        user = vox[:, ::-1].astype(np.float64)
        fs = self.fixed_start  # the kernel's box, in its fixed point
        start = ((vox[:, ::-1] @ fs[:9].reshape(3, 3).T + fs[9:]) >> 32) + 1
        steps = np.stack(np.meshgrid(*(np.arange(int(n)) for n in self.counts),
                                     indexing="ij"), axis=-1).reshape(-1, 3)
        abc = start[:, None, :] + steps[None]
        fx = self.fixed_map  # the kernels' own p, exact in float64 (< 2^53)
        p = (abc @ fx[:9].reshape(3, 3) + fx[9:]) / FX_ONE
        w = np.prod(np.maximum(0.0, 1.0 - np.abs(p - user[:, None, :])), axis=-1)
        shape = np.array(self.frame.shape[::-1])
        w[np.any((abc < 0) | (abc >= shape), axis=-1)] = 0
        w = w / self.norm[vox[:, 0], vox[:, 1], vox[:, 2]][:, None]
        return np.where(w[..., None] > 0, abc[..., ::-1], 0), w


def one_slab(slabs, ranges: SlabRanges | None = None):
    """``slabs`` (device slabs, or a plan's depth ranges) when they are one slab (and
    ``ranges`` too), else an error naming the fix."""
    if len(slabs) != 1 or (ranges is not None and len(ranges) != 1):
        raise ValueError(f"a posed camera's grid is projected as one device buffer, got "
                         f"{len(slabs)} depth slabs: the volume is larger than the device's "
                         "largest allocation; use a coarser or smaller grid, or a device "
                         "with more memory")
    return slabs
