"""Row lists made on the device (issue 46, docs/design.md §7.5): the chain's pair with
the image fit's sensor-row lists and the window means' pair buckets written by
``kernels/rowlists.cl`` (``plenocl.opencl.rowlists``: only the ranges and each row's start
cross) against the same pair with the lists built on the host and uploaded whole (the
code before, put back here by replacing ``DeviceRowLists.rows`` and ``.boxes``),
alternately in one process.

    python benchmarks/row_lists.py [--lenses 116 78] [--rounds 4]

Scene and rows: :func:`plenocl.bench.alternate.alternate_ways` (``benchmarks/
paper_pair.py``'s scene, default chain, the vectors alone): the host's waits, its work
outside OpenCL calls, the pair's wall time and the megabytes sent to the device, and
whether both ways gave the same vectors to the bit. The device is ``PYOPENCL_CTX``'s or
the default one.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from plenocl.bench.alternate import alternation_script  # noqa: E402
from plenocl.opencl.arrays import upload  # noqa: E402
from plenocl.opencl.rowlists import DeviceRowLists, RowLists, clipped  # noqa: E402
from plenocl.sorting import stable_order  # noqa: E402

i32 = np.int32
ON_DEVICE = {"rows": DeviceRowLists.rows, "boxes": DeviceRowLists.boxes}


def _uploaded(queue, key: np.ndarray, item: np.ndarray, rows: int) -> RowLists:
    """The CSR lists of items ``item`` on rows ``key`` (one entry per item and row),
    sorted on the host and uploaded whole."""
    start = np.concatenate([[0], np.cumsum(np.bincount(key, minlength=rows))]).astype(i32)
    items = item[stable_order(key)].astype(i32)
    return RowLists(start, upload(queue, start),
                    upload(queue, items if len(items) else np.zeros(1, i32)))


def host_rows(self: DeviceRowLists, lo, hi, rows: int) -> RowLists:
    """The image fit's lists as they were built before (in ``plenocl.piv.fitsums``)."""
    lo, hi = clipped(lo, hi, rows)
    on = hi - lo
    pid = np.repeat(np.arange(len(on)), on)
    first = np.cumsum(on) - on
    key = lo[pid] + np.arange(len(pid)) - np.repeat(first, on)
    return _uploaded(self.queue, key, pid, rows)


def host_boxes(self: DeviceRowLists, a: tuple, b: tuple, na: int, nb: int) -> RowLists:
    """The window means' buckets as they were built before (in
    ``plenocl.piv.devicemeans``)."""
    (z0, z1), (y0, y1) = clipped(*a, na), clipped(*b, nb)
    zr, yr = z1 - z0, y1 - y0
    per = zr * yr
    pair = np.repeat(np.arange(len(per)), per)
    k = np.arange(len(pair)) - np.repeat(np.cumsum(per) - per, per)
    rows = np.maximum(yr, 1)[pair]
    key = (z0[pair] + k // rows) * nb + y0[pair] + k % rows
    return _uploaded(self.queue, key, pair, na * nb)


def lists_by(rows, boxes) -> None:
    """Every :class:`DeviceRowLists` made to build its lists with ``rows`` and ``boxes``."""
    DeviceRowLists.rows, DeviceRowLists.boxes = rows, boxes


def main() -> None:
    alternation_script(__doc__, lambda queue: {
        "lists from the host (before)": lambda: lists_by(host_rows, host_boxes),
        "lists on the device": lambda: lists_by(**ON_DEVICE)}, warm=True)


if __name__ == "__main__":
    main()
