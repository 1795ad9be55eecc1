"""The particle refinement's window means on an OpenCL device (``kernels/windowmeans.cl``;
docs/design.md §7.1, §7.5).

:class:`DeviceWindowMeans` runs the two per-window steps of
:func:`plenocl.piv.refinement.window_means` (each window's local gradient from the pairs
of its doubled box, then the mean of its own pairs moved to its centre along it, and the
mean's uncertainty) with one work-item per window, in double precision, so that the pairs
each window keeps and its results are the host's to rounding; and the search for the
pairs each window's box holds (:meth:`DeviceWindowMeans.box_lists`), so that their lists
stay on the device. Each pair's window index ranges per axis are found on the device
from the pairs there (:meth:`DeviceWindowMeans.box_ranges`; a caller may give its own);
the pairs are listed by row of windows on the device
(:class:`plenocl.opencl.rowlists.DeviceRowLists`); the host fits the rare gradients whose pairs
scatter too flatly for the normal equations (``np.linalg.lstsq``, as its own path does).
Devices without ``cl_khr_fp64`` keep the host path (:meth:`DeviceWindowMeans.supports`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from ..opencl.arrays import KeptUpload, fill, read
from ..opencl.device import DeviceInfo
from ..opencl.program import KernelSet
from ..opencl.rowlists import DeviceRowLists
from .pairoutliers import MAD_SIGMA

__all__ = ["DeviceWindowMeans", "PairsOnDevice", "WindowCentres", "WindowLists"]

i32, f64 = np.int32, np.float64
#: Status of a window's gradient (``window_gradients``): fitted; too flat for the normal
#: equations (the host fits it).
FITTED, ILL_POSED = 1, 2


@dataclass(frozen=True)
class PairsOnDevice:
    """One call's pairs on the device: midpoints and displacements ``(P, 3)``, the
    per-component weights (``None``: alike) and the focal zone's depth ambiguity per
    pair (``None``: no focal zone), each float64."""

    mid: cl_array.Array
    disp: cl_array.Array
    weight: cl_array.Array | None
    amb: cl_array.Array | None


@dataclass(frozen=True)
class WindowLists:
    """Windows' pairs, the pair indices on the device: listed window ``k`` is grid window
    ``win[k]`` (on the host), its pairs ``member[start[k]:stop[k]]`` (at least one), in
    pair order; ``tables``: ``win``, ``start`` and ``stop`` on the device, for the
    kernels, made there (:meth:`start` and :meth:`stop` read on the host when asked);
    ``mask``: a byte per grid window on the device, 1 where listed (the next call's
    ``wanted``); ``most``: the most pairs a listed window holds."""

    win: np.ndarray
    member: cl_array.Array
    tables: tuple[cl_array.Array, cl_array.Array, cl_array.Array]
    mask: cl_array.Array
    most: int

    @functools.cached_property
    def start(self) -> np.ndarray:
        """Each listed window's first member, read from the device."""
        return self.tables[1][:len(self.win)].get()

    @functools.cached_property
    def stop(self) -> np.ndarray:
        """Each listed window's end of members, read from the device."""
        return self.tables[2][:len(self.win)].get()

    def members(self, k: int) -> np.ndarray:
        """Listed window ``k``'s pairs, on the host."""
        return self.member[int(self.start[k]):int(self.stop[k])].get()

    def largest(self) -> int:
        """The most pairs a listed window holds (0: none listed)."""
        return self.most


@dataclass(frozen=True)
class WindowCentres:
    """A field's window centres on the device as its three axes: window ``w = (kz ny +
    ky) nx + kx`` (``np.ndindex`` order over ``(nz, ny, nx)``) is centred at ``(x[kx],
    y[ky], z[kz])``, which the kernels read from ``axes`` (``x``, ``y`` and ``z`` one
    after the other, float64): ``nx + ny + nz`` numbers go up, not ``3 W``."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    axes: cl_array.Array

    @property
    def count(self) -> int:
        """The windows ``W``."""
        return len(self.x) * len(self.y) * len(self.z)

    def same(self, x, y, z) -> bool:
        """Whether these are the axes ``x``, ``y``, ``z``."""
        return all(np.array_equal(a, np.asarray(b, f64))
                   for a, b in zip((self.x, self.y, self.z), (x, y, z)))

    def centre(self, w: int) -> np.ndarray:
        """Window ``w``'s centre ``(x, y, z)`` on the host (``pl_centre``'s)."""
        kz, ky, kx = np.unravel_index(w, (len(self.z), len(self.y), len(self.x)))
        return np.array([self.x[kx], self.y[ky], self.z[kz]])

    def arguments(self) -> tuple:
        """The kernels' arguments: the axes, ``nx`` and ``ny``."""
        return self.axes, i32(len(self.x)), i32(len(self.y))


def _scale(spread: float | None) -> np.float64:
    """The kernels' ``spread``: the robust rule's standard deviations times
    :data:`plenocl.piv.pairoutliers.MAD_SIGMA` (-1: none, the search range alone; 0 is
    a reach of the floor, as on the host)."""
    return f64(-1.0 if spread is None else spread * MAD_SIGMA)


def _triple(values) -> np.ndarray:
    """Three numbers (or one for all three, as NumPy broadcasts it) as an OpenCL
    ``double3`` argument."""
    return cl.cltypes.make_double3(*np.broadcast_to(np.asarray(values, float), 3).tolist())


class DeviceWindowMeans:
    """The window means' gradients and estimates on ``queue``'s device.

    Parameters
    ----------
    queue
        The device's queue (the kernels are built once per context). Its device must
        support double precision (:meth:`supports`).
    """

    def __init__(self, queue: cl.CommandQueue) -> None:
        if not self.supports(queue):
            raise ValueError(f"{queue.device.name.strip()} has no double precision "
                             "(cl_khr_fp64): keep the window means on the host "
                             "(device_means=None)")
        names = ["window_gradients", "window_estimates", "box_tally", "box_compact",
                 "box_fill", "box_range"]
        self._k = KernelSet(queue, "windowmeans.cl", names, looping=names)
        self._rows = DeviceRowLists(queue)
        self._centres: WindowCentres | None = None
        self._pairs = KeptUpload(queue, f64)  # a refinement's calls repeat some pairs
        self._every = KeptUpload(queue, np.uint8)  # every window wanted: the same each call

    @staticmethod
    def supports(queue: cl.CommandQueue) -> bool:
        """Whether ``queue``'s device runs the kernels (double precision)."""
        return DeviceInfo.probe(queue.device).fp64

    @property
    def queue(self) -> cl.CommandQueue:
        """The device's queue."""
        return self._k.queue

    def box_ranges(self, pairs: PairsOnDevice, box, centres: WindowCentres,
                   radius: float) -> list[tuple[cl_array.Array, cl_array.Array]]:
        """Each pair's window index ranges ``[(x0, x1), (y0, y1), (z0, z1)]`` (int32
        device arrays ``(P,)``) for :meth:`box_lists`, made on the device from the pairs
        there: the windows whose centre lies within ``radius`` per axis of the pair's
        midpoint, both divided by ``box`` ``(x, y, z)`` (``kernels/windowmeans.cl``
        ``box_range``: the host's ``_axis_range``, the same doubles and test)."""
        count = pairs.mid.shape[0]
        first = np.cumsum([0, len(centres.x), len(centres.y)])
        ranges = []
        for axis, size in enumerate((len(centres.x), len(centres.y), len(centres.z))):
            lo, hi = self._k.array(max(count, 1), i32), self._k.array(max(count, 1), i32)
            if count:
                self._k.launch("box_range", (count,), pairs.mid, i32(count), i32(axis),
                               f64(np.broadcast_to(box, 3)[axis]), centres.axes,
                               i32(first[axis]), i32(size), f64(radius), lo, hi)
            ranges.append((lo[:count], hi[:count]))
        return ranges

    def box_lists(self, ranges, shape: tuple[int, int, int], wanted,
                  least: int = 1, counted: bool = True
                  ) -> tuple[WindowLists, np.ndarray | None]:
        """The pairs each ``wanted`` window's box holds (a boolean per window of the
        ``(nz, ny, nx)`` grid, flat, on the host; or an earlier call's
        :attr:`WindowLists.mask` on the device), from each pair's window index ranges
        ``ranges`` (``[(x0, x1), (y0, y1), (z0, z1)]``, each ``(P,)``: host arrays, or
        :meth:`box_ranges`' device arrays, which never cross): the windows with at least
        ``least`` (at least 1), listed with their tables made on the device (only the
        listed windows' indices come back), and with ``counted`` the count of every
        window ``(W,)`` (0 where not wanted; ``None`` without: not read back)."""
        nz, ny, nx = shape
        size = nz * ny * nx
        (x0, x1), y, z = ranges
        rows = self._rows.boxes(z, y, nz, ny)  # the pairs by (z, y) row of windows
        tables = [rows.start_device, rows.items] + [self._k.on_device(a, i32)
                                                    for a in (x0, x1)]
        mask, flag = self._k.array(size, np.uint8), self._k.array(size, i32)
        count, held = self._k.array(size, i32), self._k.array(size, i32)
        self._k.launch("box_tally", (size,), *tables, self._wanted(wanted, size), i32(size),
                       i32(nx), i32(max(least, 1)), mask, flag, count, held)
        (slot, listed, _), (first, members, most) = self._rows.starts(flag, held)
        lists = [self._k.array(max(listed, 1), i32) for _ in range(3)]  # win, start, stop
        self._k.launch("box_compact", (size,), mask, slot, first, held, i32(size), *lists)
        member = self._k.array(max(members, 1), i32)
        if listed:
            self._k.launch("box_fill", (listed,), *tables, lists[0], i32(listed), i32(nx),
                           lists[1], member)
        win = lists[0][:listed].get().astype(i32)
        return (WindowLists(win, member, tuple(lists), mask, most),
                count.get().astype(int) if counted else None)

    def _wanted(self, wanted, size: int) -> cl_array.Array:
        """The windows wanted as a byte per window on the device: a device mask as it
        is, every window's kept (the same each call), or the host's booleans uploaded."""
        if isinstance(wanted, cl_array.Array):
            if wanted.size != size or wanted.dtype != np.uint8:
                raise ValueError(f"a device mask of wanted windows must hold a byte per "
                                 f"window ({size}), got {wanted.dtype} {wanted.shape}")
            return wanted
        wanted = np.asarray(wanted, bool).reshape(-1)
        if wanted.size != size:
            raise ValueError(f"wanted must hold a boolean per window ({size}), got "
                             f"{wanted.size}")
        if wanted.all():
            return self._every(np.ones(size, np.uint8))[0]
        return self._k.to_device(wanted.astype(np.uint8))

    def pairs(self, mid: np.ndarray, disp: np.ndarray, weight: np.ndarray | None,
              amb: np.ndarray | None) -> PairsOnDevice:
        """One call's pairs on the device (see :class:`PairsOnDevice`). The last ones
        stay there: a refinement's next call often takes the same pairs (the sparse
        windows' wider boxes after the lateral means, the seeing pairs again for a blind
        column), which then go up once (the kernels only read them)."""
        return PairsOnDevice(*self._pairs(mid, disp, weight, amb))

    def gradients(self, pairs: PairsOnDevice, lists: WindowLists,
                  centres: WindowCentres | tuple, search, spread: float | None, floor,
                  min_keep: int, well_posed: float) -> tuple[np.ndarray, np.ndarray]:
        """Each window's gradient ``(W, 3, 3)`` (0 where it has no pairs listed or keeps
        fewer than ``min_keep``) and status ``(W,)`` (:data:`FITTED`,
        :data:`ILL_POSED`: the host fits it; 0 otherwise); ``centres``: the field's axes
        ``(x, y, z)`` or :meth:`device_centres`."""
        status, grad = self.device_gradients(pairs, lists, centres, search, spread, floor,
                                             min_keep, well_posed)
        return grad.get().reshape(len(status), 3, 3), status

    def device_gradients(self, pairs: PairsOnDevice, lists: WindowLists,
                         centres: WindowCentres | tuple,
                         search, spread: float | None, floor, min_keep: int,
                         well_posed: float) -> tuple[np.ndarray, cl_array.Array]:
        """:meth:`gradients`' status ``(W,)`` on the host, the gradients on the device
        alone (``W * 9`` float64, 0 where no pairs are listed) for :meth:`estimates`:
        only the status comes back (at the paper's size the gradients were 7 MB a pair).
        Where the host fits ill-posed ones, it reads them (``.get()``) and
        :meth:`set_gradients` writes them back. ``centres``: the field's axes ``(x, y,
        z)``, or :meth:`device_centres`."""
        centres = self.device_centres(centres)
        size, listed = centres.count, len(lists.win)
        grad, status = fill(self._k.array(9 * size, f64), 0.0), np.zeros(size, i32)
        if listed:
            own = self._k.array(listed, np.uint8)  # per listed window: these come back
            self._launch("window_gradients", pairs, False, lists, centres,
                         _triple(search), _scale(spread), _triple(floor), i32(min_keep),
                         f64(well_posed), self._k.array(lists.member.size, f64), grad,
                         own)
            status[lists.win] = own.get()
        return status, grad

    @staticmethod
    def set_gradients(device: cl_array.Array, grad: np.ndarray) -> None:
        """Write every window's gradient ``grad`` ``(W, 3, 3)`` into
        :meth:`device_gradients`' device copy ``device`` (one copy; after the host
        fitted ill-posed ones, which are rare)."""
        device.set(np.ascontiguousarray(grad, f64).reshape(-1))

    def device_centres(self, centres: WindowCentres | tuple) -> WindowCentres:
        """The window centres of a field with axes ``(x, y, z)`` on the device, for both
        :meth:`device_gradients` and :meth:`estimates` of one call (``centres`` itself
        when already there). The last ones stay there: a pair's refinement asks for the
        same field's centres at each of its calls, and they go up once (the kernels only
        read them)."""
        if isinstance(centres, WindowCentres):
            return centres
        x, y, z = (np.array(a, f64).reshape(-1) for a in centres)
        kept = self._centres
        if kept is None or not kept.same(x, y, z):
            kept = self._centres = WindowCentres(x, y, z,
                                                 self._upload(np.concatenate([x, y, z])))
        return kept

    def estimates(self, pairs: PairsOnDevice, lists: WindowLists,
                  centres: WindowCentres | tuple, grad: np.ndarray | cl_array.Array,
                  search, spread: float | None, floor, min_count: int,
                  t: np.ndarray, position_sigma
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per window ``(W,)``: the pairs kept, and where at least ``min_count``, their
        mean and its uncertainty ``(W, 3)`` (NaN elsewhere); ``t[n]``: Student's quantile
        for ``n`` kept pairs (``len(t)`` above the most pairs a window lists). ``grad``
        ``(W, 3, 3)`` on the host or :meth:`device_gradients`' device copy; ``centres``:
        the field's axes ``(x, y, z)`` or :meth:`device_centres`."""
        centres = self.device_centres(centres)
        size, listed = centres.count, len(lists.win)
        count, (mean, error) = np.zeros(size, int), np.full((2, size, 3), np.nan)
        if listed:  # written per listed window: only these come back
            out = [self._k.array(listed, i32), *(self._k.array(3 * listed, f64)
                                                 for _ in range(2))]
            self._launch("window_estimates", pairs, True, lists, centres,
                         self._k.on_device(grad, f64), _triple(search), _scale(spread),
                         _triple(floor), i32(min_count), self._upload(t),
                         _triple(position_sigma), self._k.array(lists.member.size, f64),
                         *out)
            n, m, e = read(*out)
            count[lists.win], mean[lists.win], error[lists.win] = (
                n, m.reshape(listed, 3), e.reshape(listed, 3))
        return count, mean, error

    def _launch(self, name: str, pairs: PairsOnDevice, with_amb: bool, lists: WindowLists,
                centres: WindowCentres, *rest) -> None:
        """Launch ``name`` over the listed windows: the pairs' and lists' arguments, then
        the listed count, then the rest of the kernel's."""
        dummy = pairs.mid  # stands for an unused buffer (the flag says so)
        head = [pairs.mid, pairs.disp, dummy if pairs.weight is None else pairs.weight,
                i32(pairs.weight is not None)]
        if with_amb:
            head += [dummy if pairs.amb is None else pairs.amb, i32(pairs.amb is not None)]
        head += [*lists.tables, lists.member, *centres.arguments()]
        self._k.launch(name, (len(lists.win),), *head, i32(len(lists.win)), *rest)

    def _upload(self, host: np.ndarray) -> cl_array.Array:
        """A float64 device copy."""
        return self._k.to_device(np.asarray(host, f64))
