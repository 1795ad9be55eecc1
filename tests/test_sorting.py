"""``plenocl.sorting.stable_order`` is NumPy's stable argsort, whichever sort runs."""

from __future__ import annotations

import numpy as np
import pytest

from plenocl.sorting import RADIX_LIMIT, stable_order


@pytest.mark.parametrize("high", [1, 7, 400, RADIX_LIMIT, RADIX_LIMIT + 1, 2**40])
@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.uint32])
def test_stable_order_is_numpys(high, dtype):
    """Many equal keys (their order kept), keys just below and above 16 bits."""
    keys = np.random.default_rng(high % 97).integers(0, min(high, 2**31), 20_000).astype(dtype)
    assert np.array_equal(stable_order(keys), np.argsort(keys, kind="stable"))


def test_stable_order_of_edge_cases():
    assert stable_order(np.zeros(0, np.int64)).size == 0
    negative = np.array([3, -1, 3, 0, -1])
    assert np.array_equal(stable_order(negative), np.argsort(negative, kind="stable"))
    assert np.array_equal(stable_order([RADIX_LIMIT - 1, 0, RADIX_LIMIT - 1]), [1, 0, 2])
