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

from plenocl import get_queue  # noqa: E402
from plenocl.bench.alternate import alternate_ways  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.opencl.pool import use_pool  # noqa: E402


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[116, 78])
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args()
    queue = get_queue(profiling=True)
    print(f"device: {queue.device.name.strip()} ({queue.device.platform.name.strip()})")
    alternate_ways({"no memory pool (before)": lambda: use_pool(queue, False),
                    "memory pool": lambda: use_pool(queue, True)},
                   args.lenses, args.rounds, queue=queue, warm=True)


if __name__ == "__main__":
    main()
