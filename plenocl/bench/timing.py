"""Wall-clock timing for the benchmarks: the one place runs are timed.

:func:`run_times` times repeated calls (after an untimed warm-up unless told not to);
:func:`median_time` and :func:`timed` are its medians, without and with the result.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any


def run_times(fn: Callable[[], object], repeats: int, warmup: bool = True
              ) -> list[float]:
    """Wall times of ``repeats`` calls of ``fn()`` (at least one), after one untimed
    warm-up call unless ``warmup=False``."""
    return _timed_calls(fn, repeats, warmup)[0]


def median_time(fn: Callable[[], object], repeats: int, warmup: bool = True) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs (after one warm-up by default)."""
    return statistics.median(run_times(fn, repeats, warmup))


def timed(fn: Callable[[], object], repeats: int) -> tuple[Any, float]:
    """The result of the last of ``repeats`` calls of ``fn()`` and their median wall time.

    No warm-up call: callers warm up with a cheaper call of the same setting (one
    iteration), as these runs are long.
    """
    times, out = _timed_calls(fn, repeats, warmup=False)
    return out, statistics.median(times)


def _timed_calls(fn: Callable[[], object], repeats: int, warmup: bool
                 ) -> tuple[list[float], Any]:
    if warmup:
        fn()
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times, out
