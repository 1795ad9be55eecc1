"""A user's grid across a rotated array's lens rows, projected through the lens-row frame
(docs/design.md §5.1).

The separable projector path needs a grid whose axes follow the microlens rows
(:meth:`plenocl.Grid.for_camera` makes one). A grid in other axes (the sensor's, or a
user's grid file) takes the general kernels, about 12x slower at the paper's size. The
projector of such a grid instead applies ``A_frame S``: ``S`` interpolates the volume
bilinearly, depth plane by depth plane, at the voxel centres of a *frame grid* with the
same voxel size whose axes follow the lens rows (:func:`frame_grid`), and ``A_frame``
is that grid's separable projector; the back projection is ``Sᵀ A_frameᵀ``, its exact
transpose. ``kernels/resample.cl`` holds ``S`` and ``Sᵀ``;
:func:`plenocl.reference.resample.resample_matrix` is the NumPy twin.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import numpy as np
import pyopencl.array as cl_array

from ..camera.lattice import rotation_matrix
from ..grid import Grid
from ..opencl.program import KernelSet
from .plan import runs

i32, f32 = np.int32, np.float32
Slabs = Sequence[cl_array.Array]
SlabRanges = Sequence[tuple[int, int]]


def frame_grid(grid: Grid, rotation_deg: float) -> Grid:
    """The grid turned to ``rotation_deg`` that holds every voxel of ``grid``'s
    interpolation: same voxel size and depth planes, lateral extents covering ``grid``
    grown by one voxel on every side (snapped to whole voxels about its centre)."""
    _, dy, dx = grid.spacing
    corners = np.array([[x, y] for x in (grid.x[0] - dx, grid.x[1] + dx)
                        for y in (grid.y[0] - dy, grid.y[1] + dy)])
    world = np.column_stack(grid.to_world(corners[:, 0], corners[:, 1]))
    turned = world @ rotation_matrix(rotation_deg)  # world -> frame: Rᵀ x, as row vectors
    lo, hi = turned.min(axis=0), turned.max(axis=0)
    centre = (lo + hi) / 2
    nx, ny = (math.ceil((hi[k] - lo[k]) / step - 1e-9) for k, step in enumerate((dx, dy)))
    return Grid((grid.shape[0], ny, nx), (centre[0] - nx * dx / 2, centre[0] + nx * dx / 2),
                (centre[1] - ny * dy / 2, centre[1] + ny * dy / 2), grid.z, rotation_deg)


def index_map(frame: Grid, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """``(M, t)``: the fractional lateral index ``M (a, b) + t`` in ``grid`` of the frame
    voxel ``(a, b)``'s centre (float64; the grids share their depth planes)."""
    ab = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    p = grid.to_index(frame.from_index(ab))[:, :2]
    return np.column_stack([p[1] - p[0], p[2] - p[0]]), p[0]


def _overlaps(a: SlabRanges, b: SlabRanges, active: np.ndarray
              ) -> Iterator[tuple[int, int, int, int]]:
    """``(slab of a, slab of b, z_lo, z_hi)`` for every run of active planes shared."""
    for ia, (a0, a1) in enumerate(a):
        for ib, (b0, b1) in enumerate(b):
            lo, hi = max(a0, b0), min(a1, b1)
            for r0, r1 in runs(active[lo:hi]) if hi > lo else ():
                yield ia, ib, lo + r0, lo + r1


class FrameResampler:
    """``S`` and ``Sᵀ`` between a grid and its frame grid on one queue.

    ``S`` interpolates bilinearly with each user voxel's taps normalised to sum to 1
    over the frame (:attr:`norm` holds the sums before): a voxel's light is spread onto
    frame voxels, none lost or gained.

    Parameters
    ----------
    queue
        The projector's queue.
    grid, frame
        The user's grid and the frame grid (:func:`frame_grid`), with the same depth
        planes.
    """

    def __init__(self, queue, grid: Grid, frame: Grid) -> None:
        if grid.shape[0] != frame.shape[0] or grid.z != frame.z:
            raise ValueError("the frame grid must share the grid's depth planes")
        self.grid, self.frame = grid, frame
        self._k = KernelSet(queue, "resample.cl", ("to_frame", "from_frame"))
        m, t = index_map(frame, grid)
        inv = np.linalg.inv(m)
        self._forward = tuple(f32(v) for v in (*m.ravel(), *t))
        self._inverse = tuple(f32(v) for v in (*inv.ravel(), *(-inv @ t)))
        reach = np.abs(inv).sum(axis=1) * (1 + 1e-6)  # |a - q_a| < reach, rounding spared
        self._reach = (*(f32(r) for r in reach), *(i32(math.ceil(2 * r)) for r in reach))
        self.norm = self._column_sums()
        self._norm = self._k.to_device(np.where(self.norm > 0, 1 / self.norm, 0)
                                       .astype(np.float32))

    def _column_sums(self) -> np.ndarray:
        """``(ny, nx)`` float64: each user voxel's bilinear taps summed over the frame (the
        unnormalised ``Sᵀ 1`` of one plane, on the device)."""
        ones = self._k.to_device(np.ones((1, *self.frame.shape[1:]), np.float32))
        out = self._k.array((1, *self.grid.shape[1:]))
        unit = self._k.to_device(np.ones(self.grid.shape[1:], np.float32))
        self._from_frame([ones], [(0, 1)], [out], [(0, 1)], np.ones(1, bool), None, unit)
        return out.get()[0].astype(np.float64)

    def to_frame(self, vol: Slabs, vol_slabs: SlabRanges, out: Slabs, out_slabs: SlabRanges,
                 active: np.ndarray) -> None:
        """``out = S vol`` on the active planes (the others are left as they are)."""
        _, uny, unx = self.grid.shape
        _, fny, fnx = self.frame.shape
        for iu, i_f, z0, z1 in _overlaps(vol_slabs, out_slabs, active):
            self._k.launch("to_frame", (fnx, fny, z1 - z0), vol[iu], self._norm, i32(unx),
                           i32(uny), i32(vol_slabs[iu][0]), out[i_f], i32(fnx), i32(fny),
                           i32(out_slabs[i_f][0]), i32(z0), *self._forward)

    def from_frame(self, frame_vol: Slabs, frame_slabs: SlabRanges, out: Slabs,
                   out_slabs: SlabRanges, active: np.ndarray, support: Slabs | None = None
                   ) -> None:
        """``out = Sᵀ frame_vol`` on the active planes (the others are left as they are);
        0 without computing it where ``support`` (slabs like ``out``) is 0."""
        self._from_frame(frame_vol, frame_slabs, out, out_slabs, active, support, self._norm)

    def _from_frame(self, frame_vol: Slabs, frame_slabs: SlabRanges, out: Slabs,
                    out_slabs: SlabRanges, active: np.ndarray, support: Slabs | None,
                    norm: cl_array.Array) -> None:
        """:meth:`from_frame` with each user voxel's sum scaled by ``norm``."""
        _, uny, unx = self.grid.shape
        _, fny, fnx = self.frame.shape
        for i_f, iu, z0, z1 in _overlaps(frame_slabs, out_slabs, active):
            sup = (out[iu], i32(0)) if support is None else (support[iu], i32(1))
            self._k.launch("from_frame", (unx, uny, z1 - z0), frame_vol[i_f], i32(fnx),
                           i32(fny), i32(frame_slabs[i_f][0]), out[iu], norm, *sup, i32(unx),
                           i32(uny), i32(out_slabs[iu][0]), i32(z0), *self._forward,
                           *self._inverse, *self._reach)

    def columns(self, ix: np.ndarray, iy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The columns of ``S`` (normalised) of the user voxels ``(ix, iy)`` (any depth), on
        the host: frame voxels ``(N, K, 2)`` as ``(a, b)`` and their weights ``(N, K)``
        (``K`` candidates per voxel, the unused ones at ``(0, 0)`` with weight 0)."""
        m = np.array(self._forward[:4], np.float64).reshape(2, 2)
        t = np.array(self._forward[4:], np.float64)
        inv = np.array(self._inverse[:4], np.float64).reshape(2, 2)
        user = np.column_stack([ix, iy]).astype(np.float64)
        reach = np.array(self._reach[:2], np.float64)
        start = np.floor(user @ inv.T + np.array(self._inverse[4:], np.float64) - reach) + 1
        na, nb = (int(n) for n in self._reach[2:])
        da, db = np.meshgrid(np.arange(na), np.arange(nb), indexing="xy")
        ab = start.astype(np.int64)[:, None, :] + np.column_stack([da.ravel(), db.ravel()])[None]
        p = ab @ m.T + t
        w = _tap(p[..., 0], user[:, None, 0]) * _tap(p[..., 1], user[:, None, 1])
        _, fny, fnx = self.frame.shape
        w[(ab[..., 0] < 0) | (ab[..., 0] >= fnx) | (ab[..., 1] < 0) | (ab[..., 1] >= fny)] = 0
        w = w / self.norm[np.asarray(iy), np.asarray(ix)][:, None]
        return np.where(w[..., None] > 0, ab, 0), w


def _tap(p: np.ndarray, i: np.ndarray) -> np.ndarray:
    """Bilinear tap weight of integer index ``i`` for fractional positions ``p``."""
    return np.maximum(0.0, 1.0 - np.abs(p - i))
