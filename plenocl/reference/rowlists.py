"""NumPy twin of ``kernels/rowlists.cl`` (:mod:`plenocl.opencl.rowlists`): each row's
items in item order, as CSR, written for clarity (a row at a time)."""

from __future__ import annotations

import numpy as np


def row_lists(lo: np.ndarray, hi: np.ndarray, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """``(start, items)``: the items ``p`` with ``lo[p] <= r < hi[p]`` of every row ``r``
    of ``rows``, ascending, row after row (int32)."""
    lists = [[p for p in range(len(lo)) if lo[p] <= r < hi[p]] for r in range(rows)]
    return _csr(lists)


def box_lists(a: tuple, b: tuple, na: int, nb: int) -> tuple[np.ndarray, np.ndarray]:
    """``(start, items)`` over the rows ``ia * nb + ib`` of an ``(na, nb)`` table: the
    items whose box ``[a[0][p], a[1][p]) x [b[0][p], b[1][p])`` holds the row."""
    (lo_a, hi_a), (lo_b, hi_b) = a, b
    lists = [[p for p in range(len(lo_a))
              if lo_a[p] <= ia < hi_a[p] and lo_b[p] <= ib < hi_b[p]]
             for ia in range(na) for ib in range(nb)]
    return _csr(lists)


def _csr(lists: list[list[int]]) -> tuple[np.ndarray, np.ndarray]:
    start = np.cumsum([0] + [len(row) for row in lists]).astype(np.int32)
    return start, np.array([p for row in lists for p in row], np.int32)
