"""Row lists made on the device (:mod:`plenocl.opencl.rowlists`, ``kernels/rowlists.cl``):
each row's items in item order, the NumPy twin's to the element, on awkward tables
(rows no item holds, items holding nothing or every row, ranges beyond the table),
with only the ranges and the starts crossing to the device."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from plenocl.bench.clprofile import OpenCLProfile
from plenocl.opencl.rowlists import DeviceRowLists, box_counts, clipped, row_counts
from plenocl.reference import rowlists as ref


def _ranges(rng: np.random.Generator, n: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` ranges over a table of ``rows``: some empty, some past either end."""
    lo = rng.integers(-3, rows + 3, n)
    return lo, lo + rng.integers(-1, rows // 2 + 3, n)


def _device_lists(lists) -> tuple[np.ndarray, np.ndarray]:
    """A :class:`RowLists` as the twin's ``(start, items)``."""
    assert (lists.start_device.get() == lists.start).all()
    return lists.start, lists.items.get()[:lists.total]


@pytest.mark.parametrize("n, rows", [(0, 5), (1, 1), (7, 13), (37, 64), (300, 129)])
def test_row_lists_match_the_twin(queue, n, rows):
    rng = np.random.default_rng(n + rows)
    lo, hi = _ranges(rng, n, rows)
    start, items = _device_lists(DeviceRowLists(queue).rows(lo, hi, rows))
    want_start, want_items = ref.row_lists(*clipped(lo, hi, rows), rows)
    np.testing.assert_array_equal(start, want_start)
    np.testing.assert_array_equal(items, want_items)


@pytest.mark.parametrize("n, na, nb", [(0, 2, 3), (1, 1, 1), (9, 3, 7), (60, 8, 5),
                                       (250, 11, 13)])
def test_box_lists_match_the_twin(queue, n, na, nb):
    rng = np.random.default_rng(100 + n)
    a, b = _ranges(rng, n, na), _ranges(rng, n, nb)
    start, items = _device_lists(DeviceRowLists(queue).boxes(a, b, na, nb))
    want_start, want_items = ref.box_lists(clipped(*a, na), clipped(*b, nb), na, nb)
    np.testing.assert_array_equal(start, want_start)
    np.testing.assert_array_equal(items, want_items)


@pytest.mark.parametrize("n, na, nb", [(1, 1, 1), (9, 3, 7), (250, 11, 13)])
def test_box_lists_of_device_ranges_are_counted_there(queue, n, na, nb):
    """Ranges already on the device (the window means make theirs there): the device
    counts each row's items (``boxes_count``) and the lists are the twin's; what crosses
    is each row's count back and its start up, not the ranges."""
    rng = np.random.default_rng(200 + n)
    a, b = clipped(*_ranges(rng, n, na), na), clipped(*_ranges(rng, n, nb), nb)
    lists = DeviceRowLists(queue)
    dev = [tuple(cla.to_device(queue, r) for r in pair) for pair in (a, b)]
    lists.boxes(*dev, na, nb)  # kernels built before the profile
    with OpenCLProfile() as prof:
        made = lists.boxes(*dev, na, nb)
        queue.finish()
    start, items = _device_lists(made)
    want_start, want_items = ref.box_lists(a, b, na, nb)
    np.testing.assert_array_equal(start, want_start)
    np.testing.assert_array_equal(items, want_items)
    moved = {kind: sum(c.nbytes for c in prof.calls if c.kind == kind)
             for kind in ("h2d", "d2h")}
    assert moved == {"h2d": 4 * (na * nb + 1), "d2h": 4 * na * nb}


@pytest.mark.parametrize("n", [0, 1, 63, 64, 65, 257, 1000, 12345])
def test_starts_scanned_on_the_device_are_numpys_cumsum(queue, n):
    """``scan_starts``: the starts of device counts are NumPy's exclusive prefix sum, the
    total last, with the largest count, on sizes around and across the work-group's
    (runs of unequal length, an empty table); only the total and the largest cross, for
    several tables at once."""
    rng = np.random.default_rng(n)
    counts = rng.integers(0, 40, n).astype(np.int32)
    if n > 3:
        counts[n // 3] = 977  # the largest, inside a run
    lists = DeviceRowLists(queue)
    dev = cla.to_device(queue, counts)
    with OpenCLProfile() as prof:
        (start, total, largest), (again, twice, _) = lists.starts(dev, 2 * dev)
    assert sum(c.nbytes for c in prof.calls if c.kind == "d2h") == 16
    np.testing.assert_array_equal(start.get(), np.concatenate([[0], np.cumsum(counts)]))
    assert total == counts.sum() and largest == counts.max(initial=0)
    np.testing.assert_array_equal(again.get(), 2 * start.get())  # two tables, one wait
    assert twice == 2 * total


def test_the_host_counts_are_each_rows_items():
    """The difference arrays' sums against counting every row's items one by one."""
    rng = np.random.default_rng(7)
    lo, hi = clipped(*_ranges(rng, 80, 30), 30)
    want = [np.sum((lo <= r) & (r < hi)) for r in range(30)]
    np.testing.assert_array_equal(row_counts(lo, hi, 30), want)
    (la, ha), (lb, hb) = clipped(*_ranges(rng, 80, 6), 6), clipped(*_ranges(rng, 80, 9), 9)
    want = [np.sum((la <= i) & (i < ha) & (lb <= j) & (j < hb))
            for i in range(6) for j in range(9)]
    np.testing.assert_array_equal(box_counts(la, ha, lb, hb, 6, 9), want)


def test_only_the_ranges_and_starts_cross(queue):
    """Twelve rows held by 500 items each: the list (6,000 items) is made on the device;
    the bytes sent are the ranges and the starts."""
    n, rows = 500, 12
    lo, hi = np.zeros(n, int), np.full(n, rows)
    lists = DeviceRowLists(queue)
    lists.rows(lo[:1], hi[:1], rows)  # kernels built before the profile
    with OpenCLProfile() as prof:
        made = lists.rows(lo, hi, rows)
        queue.finish()
    sent = sum(c.nbytes for c in prof.calls if c.kind == "h2d")
    assert made.total == n * rows
    assert sent == 4 * (2 * n + rows + 1)
