"""A camera's levels counted on the device (issue 46, docs/design.md §7.5): the chain's
pair of 16-bit counts with each frame's histogram counted where the frame is uploaded
(``kernels/rawcounts.cl`` ``count_levels``; the host reads the levels back) against the
same pair with the host's ``np.bincount`` of each frame (the code before, put back here
by replacing ``DeviceCounts.histogram``), alternately in one process.

    python benchmarks/level_counts.py [--lenses 116 78] [--rounds 4]

Scene and rows: :func:`plenocl.bench.alternate.alternate_ways` (``benchmarks/
paper_pair.py``'s scene as 16-bit counts, default chain, the vectors alone): the host's
waits, its work outside OpenCL calls, the pair's wall time and the megabytes sent to the
device, and whether both ways gave the same vectors to the bit. The device is
``PYOPENCL_CTX``'s or the default one.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl.bench.alternate import alternation_script  # noqa: E402
from plenocl.optics.rawimage import count_histogram  # noqa: E402
from plenocl.reconstruction.deviceimage import DeviceCounts  # noqa: E402

ON_DEVICE = DeviceCounts.histogram


def host_histogram(self: DeviceCounts, raw, on_device=None):
    """The histogram as it was counted before: the host's bincount of the host frame."""
    return count_histogram(raw)


def counted_by(histogram) -> None:
    """Every :class:`DeviceCounts` made to count a frame's levels with ``histogram``."""
    DeviceCounts.histogram = histogram


def main() -> None:
    alternation_script(__doc__, lambda queue: {
        "levels counted on the host (before)": lambda: counted_by(host_histogram),
        "levels counted on the device": lambda: counted_by(ON_DEVICE)},
        warm=True, bit_depth=16)


if __name__ == "__main__":
    main()
