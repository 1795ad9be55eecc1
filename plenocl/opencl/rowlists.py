"""Row lists made on the device: for each row of a table, the items whose range of rows
holds it, in item order, as one CSR list (``kernels/rowlists.cl``; docs/design.md §7.5).

The image fit's model lists the particles whose patch covers each sensor row, and the
window means the particle pairs by row of windows (from ranges the device made itself,
:meth:`DeviceRowLists.boxes`: then the device counts them too, and
:meth:`DeviceRowLists.starts` sums counts into starts there). Built on the host, the lists
crossed to the device at every step: 9.6 and 9.4 MB of a paper-size pair's 30 MB of tables
(issue 46). Here the host counts each row's items from the ranges alone (a difference
array: items + rows operations, no list), sums the counts into each row's start, and
the device writes the lists: only the ranges and the starts cross. The lists are the
host's to the element (:mod:`plenocl.reference.rowlists`, their NumPy twin).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from .arrays import read
from .device import is_cpu
from .program import KernelSet

__all__ = ["DeviceRowLists", "RowLists", "box_counts", "clipped", "row_counts", "scan_group"]

i32 = np.int32


class RowLists(NamedTuple):
    """The items of each row: row ``r``'s are ``items[start[r]:start[r + 1]]``, in
    ascending order; ``start`` on the host and on the device, ``items`` (int32, at
    least one element, so a kernel always has a buffer) on the device."""

    start: np.ndarray
    start_device: cl_array.Array
    items: cl_array.Array

    @property
    def total(self) -> int:
        """The items listed over all rows."""
        return int(self.start[-1])


def clipped(lo, hi, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Ranges ``[lo, hi)`` cut to ``[0, rows)`` (an empty range: ``hi == lo``), int32."""
    lo = np.clip(np.asarray(lo, np.int64), 0, rows)
    return lo.astype(i32), np.clip(np.asarray(hi, np.int64), lo, rows).astype(i32)


def row_counts(lo: np.ndarray, hi: np.ndarray, rows: int) -> np.ndarray:
    """The items holding each of ``rows`` rows, item ``p`` holding ``[lo[p], hi[p])``
    (within ``[0, rows]``, :func:`clipped`): the sum of a difference array."""
    ends = np.bincount(lo, minlength=rows + 1) - np.bincount(hi, minlength=rows + 1)
    return np.cumsum(ends[:rows])


def box_counts(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray,
               na: int, nb: int) -> np.ndarray:
    """The items holding each row ``a * nb + b`` of an ``(na, nb)`` table, item ``p``
    holding the box ``[lo_a[p], hi_a[p]) x [lo_b[p], hi_b[p])`` (each range within the
    table, :func:`clipped`; an empty one holds nothing): the sums of a two-dimensional
    difference array, flat ``(na * nb,)``."""
    full = (hi_a > lo_a) & (hi_b > lo_b)
    stride, size = nb + 1, (na + 1) * (nb + 1)
    corner = [np.bincount(a[full].astype(np.int64) * stride + b[full], minlength=size)
              for a, b in ((lo_a, lo_b), (lo_a, hi_b), (hi_a, lo_b), (hi_a, hi_b))]
    ends = (corner[0] - corner[1] - corner[2] + corner[3]).reshape(na + 1, nb + 1)
    return np.cumsum(np.cumsum(ends, axis=0), axis=1)[:na, :nb].ravel()


def scan_group(device: cl.Device) -> int:
    """Work-items of ``scan_starts``' one work-group (``PL_SCAN``): 64 on a CPU (its
    barriers are emulated: fewer items, longer runs), else 256 within the device's
    largest group."""
    return 64 if is_cpu(device) else min(256, int(device.max_work_group_size))


class DeviceRowLists:
    """Row lists on ``queue``'s device (``kernels/rowlists.cl``)."""

    def __init__(self, queue: cl.CommandQueue) -> None:
        self._group = scan_group(queue.device)
        self._k = KernelSet(queue, "rowlists.cl",
                            ("rows_fill", "boxes_fill", "boxes_count", "scan_starts"),
                            [f"-DPL_SCAN={self._group}"])

    def starts(self, *counts: cl_array.Array) -> list[tuple[cl_array.Array, int, int]]:
        """For each table of ``counts`` ``(n,)`` (int32 on the device): the starts
        ``(n + 1,)`` of rows holding those items (on the device: an exclusive prefix sum,
        ``start[n]`` the total) and, read back as two numbers with one wait for all
        tables, the total and the largest count (``scan_starts``; NumPy:
        ``np.concatenate([[0], np.cumsum(counts)])``)."""
        made, ends = [], []
        for table in counts:
            n = table.size
            start, largest = self._k.array(n + 1, i32), self._k.array(1, i32)
            self._k.launch("scan_starts", (self._group,), table, i32(n), start, largest,
                           local_size=(self._group,))
            made.append(start)
            ends += [start[n:], largest]
        read_back = read(*ends)
        return [(start, int(total[0]), int(most[0]))
                for start, total, most in zip(made, read_back[::2], read_back[1::2])]

    @property
    def queue(self) -> cl.CommandQueue:
        """The device's queue."""
        return self._k.queue

    def rows(self, lo, hi, rows: int) -> RowLists:
        """The items holding each of ``rows`` rows, item ``p`` holding rows
        ``[lo[p], hi[p])`` (cut to the table: :func:`clipped`)."""
        lo, hi = clipped(lo, hi, rows)
        lists = self._empty(row_counts(lo, hi, rows))
        if lists.total:
            self._k.launch("rows_fill", (rows,), self._k.to_device(lo),
                           self._k.to_device(hi), i32(len(lo)), i32(rows),
                           lists.start_device, lists.items)
        return lists

    def boxes(self, a: tuple, b: tuple, na: int, nb: int) -> RowLists:
        """The items holding each row ``a * nb + b`` of an ``(na, nb)`` table, item ``p``
        holding the box ``[a[0][p], a[1][p]) x [b[0][p], b[1][p])``: host arrays (cut to
        the table here; counted on the host) or int32 device arrays already within it
        (counted on the device, ``boxes_count``: only each row's count comes back and its
        start goes up, not the ranges)."""
        if isinstance(a[0], cl_array.Array):
            ranges, items = (*a, *b), a[0].size
            counts = self._k.array(na * nb, i32)
            self._k.launch("boxes_count", (na * nb,), *ranges, i32(items), i32(na), i32(nb),
                           counts)
            lists = self._empty(counts.get())
        else:
            (lo_a, hi_a), (lo_b, hi_b) = clipped(*a, na), clipped(*b, nb)
            lists = self._empty(box_counts(lo_a, hi_a, lo_b, hi_b, na, nb))
            ranges, items = (lo_a, hi_a, lo_b, hi_b), len(lo_a)
        if lists.total:
            self._k.launch("boxes_fill", (na * nb,),
                           *(self._k.on_device(r, i32) for r in ranges), i32(items),
                           i32(na), i32(nb), lists.start_device, lists.items)
        return lists

    def _empty(self, counts: np.ndarray) -> RowLists:
        """The starts of rows holding ``counts`` items (uploaded) and a list to fill."""
        start = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])
        if start[-1] > np.iinfo(i32).max:
            raise ValueError(f"the row lists would hold {start[-1]:,} items, more than "
                             "int32 indexes: process fewer particles at a time")
        start = start.astype(i32)
        return RowLists(start, self._k.to_device(start),
                        self._k.array(max(int(start[-1]), 1), i32))
