"""The particle refinement's window means on an OpenCL device (``kernels/windowmeans.cl``;
docs/design.md §7.1, §7.5).

:class:`DeviceWindowMeans` runs the two per-window steps of
:func:`plenocl.piv.refinement.window_means` (each window's local gradient from the pairs
of its doubled box, then the mean of its own pairs moved to its centre along it, and the
mean's uncertainty) with one work-item per window, in double precision, so that the pairs
each window keeps and its results are the host's to rounding. The host lists each
window's pairs (``refinement``'s box search) and fits the rare gradients whose pairs
scatter too flatly for the normal equations (``np.linalg.lstsq``, as its own path does).
Devices without ``cl_khr_fp64`` keep the host path (:meth:`DeviceWindowMeans.supports`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from ..opencl.device import DeviceInfo
from ..opencl.program import KernelSet
from .pairoutliers import MAD_SIGMA

__all__ = ["DeviceWindowMeans", "PairsOnDevice", "WindowLists"]

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
    """Windows' pairs as a CSR table on the host: listed window ``k`` is grid window
    ``win[k]``, its pairs ``member[start[k]:start[k + 1]]``."""

    win: np.ndarray
    start: np.ndarray
    member: np.ndarray

    @classmethod
    def of(cls, window: np.ndarray, member: np.ndarray, size: int) -> WindowLists:
        """From flat (window, pair) entries sorted by ``window`` over ``size`` windows."""
        counts = np.bincount(window, minlength=size)
        win = np.flatnonzero(counts)
        start = np.concatenate([[0], np.cumsum(counts[win])])
        return cls(win.astype(i32), start.astype(i32), np.asarray(member, i32))


def _scale(spread: float | None) -> np.float64:
    """The kernels' ``spread``: the robust rule's standard deviations times
    :data:`plenocl.piv.pairoutliers.MAD_SIGMA` (0: the search range alone)."""
    return f64(0.0 if spread is None else spread * MAD_SIGMA)


def _triple(values) -> np.ndarray:
    """Three numbers as an OpenCL ``double3`` argument."""
    return cl.cltypes.make_double3(*(float(v) for v in values))


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
                             "(cl_khr_fp64): keep the window means on the host (means=None)")
        self._k = KernelSet(queue, "windowmeans.cl", ["window_gradients", "window_estimates"],
                            looping=["window_gradients", "window_estimates"])

    @staticmethod
    def supports(queue: cl.CommandQueue) -> bool:
        """Whether ``queue``'s device runs the kernels (double precision)."""
        return DeviceInfo.probe(queue.device).fp64

    @property
    def queue(self) -> cl.CommandQueue:
        """The device's queue."""
        return self._k.queue

    def pairs(self, mid: np.ndarray, disp: np.ndarray, weight: np.ndarray | None,
              amb: np.ndarray | None) -> PairsOnDevice:
        """Upload one call's pairs (see :class:`PairsOnDevice`)."""
        up = self._upload
        return PairsOnDevice(up(mid), up(disp), None if weight is None else up(weight),
                             None if amb is None else up(amb))

    def gradients(self, pairs: PairsOnDevice, lists: WindowLists, centres: np.ndarray,
                  search, spread: float | None, floor, min_keep: int, well_posed: float
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Each window's gradient ``(W, 3, 3)`` (0 where it has no pairs listed or keeps
        fewer than ``min_keep``) and status ``(W,)`` (:data:`FITTED`,
        :data:`ILL_POSED`: the host fits it; 0 otherwise); ``centres`` ``(W, 3)``."""
        size = len(centres)
        grad, status = self._k.array(9 * size, f64), self._k.to_device(np.zeros(size, i32))
        if len(lists.win):
            self._launch("window_gradients", pairs, False, lists, centres,
                         _triple(search), _scale(spread), _triple(floor), i32(min_keep),
                         f64(well_posed), self._k.array(len(lists.member), f64), grad,
                         status)
        out = np.zeros((size, 3, 3))
        listed = lists.win
        out.reshape(size, 9)[listed] = grad.get().reshape(size, 9)[listed]
        return out, status.get()

    def estimates(self, pairs: PairsOnDevice, lists: WindowLists, centres: np.ndarray,
                  grad: np.ndarray, search, spread: float | None, floor, min_count: int,
                  t: np.ndarray, position_sigma
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per window ``(W,)``: the pairs kept, and where at least ``min_count``, their
        mean and its uncertainty ``(W, 3)`` (NaN elsewhere); ``t[n]``: Student's quantile
        for ``n`` kept pairs (``len(t)`` above the most pairs a window lists)."""
        size = len(centres)
        count = self._k.to_device(np.zeros(size, i32))
        mean, error = (self._k.to_device(np.full(3 * size, np.nan)) for _ in range(2))
        if len(lists.win):
            self._launch("window_estimates", pairs, True, lists, centres,
                         self._upload(grad.reshape(-1)), _triple(search), _scale(spread),
                         _triple(floor), i32(min_count), self._upload(t),
                         _triple(position_sigma), self._k.array(len(lists.member), f64),
                         count, mean, error)
        return (count.get().astype(int), mean.get().reshape(size, 3),
                error.get().reshape(size, 3))

    def _launch(self, name: str, pairs: PairsOnDevice, with_amb: bool, lists: WindowLists,
                centres: np.ndarray, *rest) -> None:
        """Launch ``name`` over the listed windows: the pairs' and lists' arguments, then
        the rest of the kernel's (after the listed count for the estimates' grad)."""
        dummy = pairs.mid  # stands for an unused buffer (the flag says so)
        head = [pairs.mid, pairs.disp, dummy if pairs.weight is None else pairs.weight,
                i32(pairs.weight is not None)]
        if with_amb:
            head += [dummy if pairs.amb is None else pairs.amb, i32(pairs.amb is not None)]
        tables = [self._k.to_device(a) for a in (lists.win, lists.start, lists.member)]
        head += [*tables, self._upload(centres.reshape(-1))]
        listed = i32(len(lists.win))
        args = ([*head, rest[0], listed, *rest[1:]] if with_amb else [*head, listed, *rest])
        self._k.launch(name, (len(lists.win),), *args)

    def _upload(self, host: np.ndarray) -> cl_array.Array:
        """A float64 device copy."""
        return self._k.to_device(np.asarray(host, f64))
