"""Stable orders of integer keys, as ``np.argsort(keys, kind="stable")`` gives them.

NumPy's stable sort is a radix sort for integers of 16 bits or fewer and a merge sort
(``O(n log n)``) above; keys known to fit 16 bits (row indices of a sensor, rows of
windows) are sorted as such: the same order, several times faster on millions of keys.
"""

from __future__ import annotations

import numpy as np

#: Keys below this sort as 16-bit integers (radix sort).
RADIX_LIMIT = 1 << 16


def stable_order(keys: np.ndarray) -> np.ndarray:
    """The indices that sort ``keys`` (non-negative integers), equal keys in their
    order: ``np.argsort(keys, kind="stable")``, by radix sort where every key is below
    :data:`RADIX_LIMIT`."""
    keys = np.asarray(keys)
    if keys.size and 0 <= keys.min() and keys.max() < RADIX_LIMIT:
        keys = keys.astype(np.uint16)
    return np.argsort(keys, kind="stable")
