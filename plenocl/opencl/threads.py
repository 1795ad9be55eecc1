"""How many threads host-side work (FFTs, BLAS) may use in this process."""

from __future__ import annotations

import os


def thread_count(workers: int | None = -1) -> int:
    """Threads for ``workers`` (``-1`` or ``None``: the ``PLENOCL_THREADS`` variable,
    which a batch run sets for its worker processes so that they share the cores, else
    every core this process may use)."""
    if workers is not None and workers >= 1:
        return int(workers)
    if os.environ.get("PLENOCL_THREADS"):
        return max(1, int(os.environ["PLENOCL_THREADS"]))
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1
