"""The direct correlation's window sums on an OpenCL device (``kernels/windowsums.cl``).

:class:`DeviceSums` computes what :class:`plenocl.piv.direct.HostSums` computes with three
matrix products per sum on the host: every weighted window sum of
:func:`plenocl.piv.direct.correlate_direct` and of
:func:`plenocl.piv.direct.correlation_uncertainty`, evaluated at the window corners only.
A row kernel (x) forms the fields (products of the two volumes at the 63 lags,
differences of neighbours) as it sums them, so no field is ever stored whole; a generic
axis kernel then sums the y and z axes. Both engines return float32 sums of the same
shapes, equal to float32 rounding (each kernel sum is one work-item's loop in tap order,
so the results do not depend on the device's core count either).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cl_array

from ..opencl.arrays import inside_zeros
from ..opencl.device import DeviceInfo, DeviceLike, check_fits, get_queue
from ..opencl.program import KernelSet
from .correlation import WindowGrid
from .deformation import DeviceDeformer
from .direct import (
    AXIS_LAGS,
    CUBE,
    LAGS,
    REACH,
    WindowFit,
    axis_taps,
    correlation_lags,
    lag_weight_sums,
    margin,
    sum_factor,
    weighed_voxels,
)

#: Sums the row kernels write per row segment (``NPAIR``, ``NSPREAD`` in the kernel):
#: ``a``, ``a^2``, ``b``, ``b^2`` at the 3 x lags, then the products at the 9 (y, x) lags of
#: each depth lag; the uncertainty's 9 fields per axis.
PAIR_FIELDS, SPREAD_FIELDS = 12 + 9 * CUBE[0], 27
#: The lags of the uncertainty's sums along every axis (lag zero and its neighbours).
UNIT_LAGS = (-1, 0, 1)

_KERNELS = ["pair_rows", "spread_rows", "axis_sums"]
#: Rows a work-item of ``column_partials`` adds (:meth:`DeviceSums.column_sums`).
COLUMN_BLOCK = 256


def tap_table(size: int, weighting: float | None, width: int = 0,
              lags=UNIT_LAGS) -> np.ndarray:
    """``(2 len(lags), width)`` float32: the weight of ``lags`` along one axis
    (:func:`plenocl.piv.direct.axis_taps`, the rows of ``WindowSums``) and their squares,
    zeros beyond the ``size + 2 margin`` taps (``width``, at least that, by default)."""
    rows = [axis_taps(size, weighting, -0.5 * s) for s in lags]
    table = np.array(rows + [r ** 2 for r in rows], np.float32)
    return np.pad(table, [(0, 0), (0, max(0, width - table.shape[1]))])


def pair_fields() -> tuple[np.ndarray, np.ndarray]:
    """``(source, tap row, offset)`` of every output of the y and z passes of the
    correlation sums: ``a``, ``a^2`` (first window), ``b``, ``b^2`` (second window,
    offset by its lag) at the lags of each axis, then the products at their own lag.
    The z pass leaves them in :data:`plenocl.piv.direct.LAGS` order, 63 per quantity."""
    nz, (rz, ry) = CUBE[0], REACH[:2]
    y, z = [], []
    for q in range(4):
        second = q >= 2
        y += [(3 * q + sx, sy, sy - ry if second else 0) for sy in range(3) for sx in range(3)]
        z += [(9 * q + j, sz, sz - rz if second else 0) for sz in range(nz) for j in range(9)]
    y += [(12 + p, (p // 3) % 3, 0) for p in range(len(LAGS))]
    z += [(36 + p, p // 9, 0) for p in range(len(LAGS))]
    return np.array(y, np.int32), np.array(z, np.int32)


def spread_fields() -> tuple[np.ndarray, np.ndarray]:
    """The same for the uncertainty's 9 fields per axis ``e``: the weight of lag +1 along
    ``e`` and of lag 0 along the other axes, squared for the last 6 fields."""
    def rows(axis: int) -> np.ndarray:
        return np.array([(9 * e + k, (2 if e == axis else 1) + (3 if k >= 3 else 0), 0)
                         for e in range(3) for k in range(9)], np.int32)
    return rows(1), rows(0)


class DeviceSums:
    """Window sums of :mod:`plenocl.piv.direct` by ``kernels/windowsums.cl``.

    Parameters
    ----------
    queue
        Device to run on (:func:`plenocl.get_queue` rules); the kernels are built once.
    fp64
        Whether the factors' and the windows' fits add in double (``None``: where the
        device has doubles; ``False`` takes the float path of a device without them).
    """

    def __init__(self, queue: DeviceLike, fp64: bool | None = None) -> None:
        self.kernels = KernelSet(get_queue(queue), "windowsums.cl", _KERNELS,
                                 options=[f"-DPL_ZREACH={REACH[0]}"],
                                 looping=["pair_rows", "spread_rows"])
        if fp64 is None:
            fp64 = DeviceInfo.probe(self.kernels.queue.device).fp64
        self._fit = KernelSet(self.kernels.queue, "windowfit.cl", ["window_fit"],
                              options=["-DPL_DOUBLE"] if fp64 else [])
        self._c = KernelSet(self.kernels.queue, "correlated.cl",
                            ["box_mean_axis", "contributions", "lagged_rows", "column_partials"],
                            options=["-DPL_DOUBLE"] if fp64 else [],
                            looping=["box_mean_axis", "contributions", "lagged_rows",
                                     "column_partials"])
        #: The dtype of ``column_partials``' sums (``PL_ACC``): float64 where the device
        #: has doubles, else float32.
        self.accumulator = np.float64 if fp64 else np.float32
        self._pair = [self.kernels.to_device(f) for f in pair_fields()]
        self._spread = [self.kernels.to_device(f) for f in spread_fields()]

    def correlation_sums(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                         weighting: float | None) -> tuple[np.ndarray, ...]:
        """``(s_a, s_b, raw_a, raw_b, products)``, each ``(63, *grid.count)`` float32, as
        :meth:`plenocl.piv.direct.HostSums.correlation_sums`."""
        out = self._sums("pair_rows", PAIR_FIELDS, self._pair, vol_a, vol_b, grid, weighting,
                         AXIS_LAGS[0])
        s_a, raw_a, s_b, raw_b, products = out.get().reshape(5, len(LAGS), *grid.count)
        return s_a, s_b, raw_a, raw_b, products

    def spread_sums(self, vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid,
                    weighting: float | None) -> np.ndarray:
        """``(3, 9, *grid.count)`` float32, as
        :meth:`plenocl.piv.direct.HostSums.spread_sums`."""
        out = self._sums("spread_rows", SPREAD_FIELDS, self._spread, vol_a, vol_b, grid,
                         weighting, UNIT_LAGS)
        return out.get().reshape(3, 9, *grid.count)

    def window_fit(self, vol_a, vol_b, grid: WindowGrid, weighting: float | None,
                   uncertainty: bool = False) -> WindowFit:
        """:func:`plenocl.piv.direct.window_fit` on the device: the window sums stay
        there and ``kernels/windowfit.cl`` fits them (twin: the host's
        :func:`~plenocl.piv.direct.direct_correlation`,
        :func:`~plenocl.piv.direct.fitted_windows` and
        :func:`~plenocl.piv.direct.uncertainty_from_sums` of the same sums), so that
        eight numbers per window come back instead of its 315 sums."""
        sums = self._sums("pair_rows", PAIR_FIELDS, self._pair, vol_a, vol_b, grid,
                          weighting, AXIS_LAGS[0])
        consts = [1.0] * 4  # not read without the uncertainty
        spread = sums
        if uncertainty:
            spread = self._sums("spread_rows", SPREAD_FIELDS, self._spread, vol_a, vol_b,
                                grid, weighting, UNIT_LAGS)
            consts = [*self.correlated_factors(vol_a, vol_b, grid, weighting),
                      weighed_voxels(grid, weighting)]
        windows = int(np.prod(grid.count))
        out = self._fit.array((7, windows), self.accumulator)
        flags = self._fit.array(windows, np.int32)
        self._fit.launch("window_fit", (windows,), sums,
                         self._fit.to_device(lag_weight_sums(grid, weighting).astype(
                             self.accumulator)), np.int32(windows), spread,
                         self._fit.to_device(np.asarray(consts, self.accumulator)),
                         np.int32(uncertainty), out, flags)
        return unpacked_fit(out.get(), flags.get(), grid.count, uncertainty)

    def _sums(self, rows: str, nfields: int, fields, vol_a, vol_b, grid: WindowGrid,
              weighting: float | None, zlags) -> cl_array.Array:
        """The x pass ``rows`` of both volumes, then the y and z passes with ``fields``
        (the z pass's tap rows those of ``zlags``), on the device."""
        nz, ny, nx = np.shape(vol_a)
        cz, cy, cx = grid.count
        mx = margin(grid.size[2], weighting)
        chunks = -(-(grid.size[2] + 2 * mx) // 8)      # 8-float chunks of the x taps
        width = nx + 2 * (mx + 1) + 8 * chunks - (grid.size[2] + 2 * mx)
        check_fits(self.kernels.queue, 4 * (2 * (nz + 2 * REACH[0]) * (ny + 2) * width
                                            + nfields * nz * ny * cx
                                            + fields[0].shape[0] * nz * cy * cx),
                   "the direct correlation's window sums")
        a, b = (self._padded(v, mx + 1, width) for v in (vol_a, vol_b))
        tx = self.kernels.to_device(tap_table(grid.size[2], weighting, 8 * chunks))
        x = self.kernels.array((nfields, nz, ny, cx))
        extra = _ints(mx + 1) if rows == "spread_rows" else []
        self.kernels.launch(rows, (cx, ny, nz), a, b,
                            *_ints(nz, ny, ny + 2, width, grid.offset[2] + 1, grid.step[2],
                                   cx, chunks), tx, *extra, x)
        y = self._axis(x, nz, ny, cx, grid, weighting, 1, fields[0], UNIT_LAGS)
        return self._axis(y, 1, nz, cy * cx, grid, weighting, 0, fields[1], zlags)

    def correlated_factors(self, vol_a, vol_b, grid: WindowGrid,
                           weighting: float | None) -> list[float]:
        """:func:`plenocl.piv.direct.correlated_factors` on the device
        (``kernels/correlated.cl``): the volumes padded there, their box means, each
        axis's contribution field and its products at the lags along every axis, summed
        per row there, then over blocks of rows there (:meth:`column_sums`) and over
        the blocks on the host in float64; only the blocks' sums come back."""
        shape = tuple(int(n) for n in vol_a.shape)
        pads = tuple(margin(w, weighting) + r for w, r in zip(grid.size, REACH))
        padded = tuple(n + 2 * p for n, p in zip(shape, pads))
        check_fits(self.kernels.queue, 4 * (6 * int(np.prod(padded)) + int(np.prod(shape))),
                   "the uncertainty's correlated-sum factors")
        a, b = (inside_zeros(self.kernels.queue, v, padded, pads) for v in (vol_a, vol_b))
        ma, mb = (self._box_mean(v, grid.size) for v in (a, b))
        field = self._c.array(shape)
        factors = []
        for axis in range(3):
            self._c.launch("contributions", (shape[0] * shape[1],), a, b, ma, mb,
                           *_ints(padded[1], padded[2], *pads, axis, shape[1], shape[2]),
                           field)
            factors.append(self._factor(field, shape))
        return factors

    def _factor(self, field, shape: tuple[int, int, int]) -> float:
        """:func:`plenocl.piv.direct.sum_factor` of one contribution field on the device."""
        rows = shape[0] * shape[1]
        lagged = []
        for axis in range(3):
            lags = correlation_lags(shape, axis)
            out = self._c.array(rows * (lags + 1))
            self._c.launch("lagged_rows", (rows,), field, *_ints(*shape, axis, lags), out)
            lagged.append(self.column_sums(out, rows, lags + 1))
        return sum_factor(float(lagged[2][0]), (products[1:] for products in lagged))

    def column_sums(self, rows_array: cl_array.Array, rows: int, cols: int) -> np.ndarray:
        """``(cols,)`` float64: the column sums of a device ``(rows, cols)`` float32
        array, added on the device in blocks of :data:`COLUMN_BLOCK` rows
        (``column_partials``; twin :func:`plenocl.reference.direct.column_partials`) and
        the blocks on the host: only the blocks' sums come back."""
        blocks = max(-(-rows // COLUMN_BLOCK), 1)
        partial = self._c.array((blocks, cols), self.accumulator)
        self._c.launch("column_partials", (cols, blocks), rows_array,
                       *_ints(rows, cols, COLUMN_BLOCK), partial)
        return partial.get().astype(np.float64).sum(axis=0)

    def _box_mean(self, vol, size) -> cl_array.Array:
        """``scipy.ndimage.uniform_filter(vol, size, mode="constant")``: the box means
        along z, y and x in turn."""
        pz, py, px = vol.shape
        plane = py * px
        lines = {0: (pz, plane, (py, px), (px, 1)), 1: (py, px, (pz, plane), (px, 1)),
                 2: (px, 1, (pz, plane), (py, px))}
        src = vol
        for axis in range(3):
            n, step, (nu, su), (nv, sv) = lines[axis]
            dst = self._c.array(vol.shape)
            self._c.launch("box_mean_axis", (nu * nv,), src, dst,
                           *_ints(n, step, nu, su, nv, sv, size[axis]))
            src = dst
        return src

    def _padded(self, vol, left: int, width: int):
        """``vol`` (host, or a device array) on the device inside zeros: the farthest
        depth lag's planes on each side in z, one row on each side in y, ``left`` voxels
        before each row, rows ``width`` long (the row kernels' layout)."""
        nz, ny, _ = vol.shape
        return inside_zeros(self.kernels.queue, vol, (nz + 2 * REACH[0], ny + 2, width),
                            (REACH[0], 1, left))

    def _axis(self, source, outer: int, n: int, inner: int, grid: WindowGrid,
              weighting: float | None, axis: int, fields, lags):
        """One y or z pass: ``(len(fields), outer, count, inner)`` on the device, the tap
        rows those of ``lags``."""
        count, size = grid.count[axis], grid.size[axis]
        taps = self.kernels.to_device(tap_table(size, weighting, lags=lags))
        out = self.kernels.array((fields.shape[0], outer, count, inner))
        self.kernels.launch("axis_sums", (inner, count, outer * fields.shape[0]), source,
                            *_ints(outer, n, inner, grid.offset[axis], grid.step[axis], count,
                                   margin(size, weighting), taps.shape[1]), taps, fields, out)
        return out


def _ints(*values: int) -> list[np.int32]:
    return [np.int32(v) for v in values]


def unpacked_fit(out: np.ndarray, flags: np.ndarray, shape: tuple[int, ...],
                 uncertainty: bool) -> WindowFit:
    """``window_fit``'s outputs (``(7, windows)`` values and the flags) as a
    :class:`~plenocl.piv.direct.WindowFit` of windows ``shape``."""
    values = out.astype(np.float64).reshape(7, *shape)
    flags = flags.reshape(shape)
    return WindowFit(values[:3], values[3], (flags & 1) > 0, (flags & 2) > 0,
                     (flags & 4) > 0, values[4:] if uncertainty else None)


def sums_for(deformer) -> DeviceSums | None:
    """The window sums' engine beside ``deformer``: :class:`DeviceSums` on the queue of a
    :class:`~plenocl.piv.deformation.DeviceDeformer`, ``None`` (the host,
    :class:`plenocl.piv.direct.HostSums`) for a host deformer (``queue=False``, or the
    quintic B-spline)."""
    if isinstance(deformer, DeviceDeformer):
        return DeviceSums(deformer.kernels.queue)
    return None
