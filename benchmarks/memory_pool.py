"""Device memory kept for reuse (issue 46, docs/design.md §7.5): the chain's pair with
each queue's memory pool (``plenocl.opencl.pool``) against the same pair with the pool
switched off (every device array made and released by the driver: the code before),
alternately in one process.

    python benchmarks/memory_pool.py [--lenses 116 78] [--rounds 4]

Scene and rows: :func:`plenocl.bench.alternate.alternate_ways` (``benchmarks/
paper_pair.py``'s scene, default chain, the vectors alone), each round's pooled pair
after one unprofiled pair (switched on again, a pool starts empty; a batch's later
pairs find it full). The device is ``PYOPENCL_CTX``'s or the default one.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl.bench.alternate import alternation_script  # noqa: E402
from plenocl.opencl.pool import use_pool  # noqa: E402


def main() -> None:
    alternation_script(__doc__, lambda queue: {
        "no memory pool (before)": lambda: use_pool(queue, False),
        "memory pool": lambda: use_pool(queue, True)}, warm=True)


if __name__ == "__main__":
    main()
