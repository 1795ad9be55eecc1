"""The whole benchmark report from one command: every stage against a baseline measured
in the same run, written to ``OUT/report.md`` with PNG plots beside it.

    python benchmarks/run_all.py [--size ci|small|paper] [--out plenocl_bench] [--repeats N]

The same as ``plenocl bench``; see :mod:`plenocl.bench` for what each section measures.
``ci`` takes about 1-2 minutes on 2 CPU cores, ``small`` 10-15 minutes, ``paper`` adds the
paper's full 16 MP, 300 x 200 x 150 experiment.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl.bench import SIZES, run_report  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402


def main() -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--size", choices=SIZES, default="ci")
    parser.add_argument("--out", default="plenocl_bench", help="output folder")
    parser.add_argument("--repeats", type=int, default=None,
                        help="runs per timing (median reported); default per size")
    parser.add_argument("--device", default=None,
                        help="OpenCL device name or type substring (default: PYOPENCL_CTX, "
                             "else a GPU, else a CPU)")
    args = parser.parse_args()
    path = run_report(args.size, args.out, args.repeats, queue=args.device)
    print(f"benchmark report: {path} (plots beside it)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
