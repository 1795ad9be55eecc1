"""docs/results.md from one command: every benchmark of the manifest run, its output
recorded with the machine it ran on, and the page written from the records.

    python benchmarks/results_page.py [--only NAME ...] [--page-only] [--list]
                                      [--out docs/results.md]

Each entry of :data:`plenocl.bench.results_manifest.MANIFEST` runs as ``python
benchmarks/X.py ARGS`` from the repository root; its record (command, output, wall time,
UTC date, OpenCL device, CPU, commit, plenocl version) goes to ``results/NAME.json``
beside the page, and the page is rewritten from every record there after each entry, so
entries not rerun keep their last record. ``--only`` reruns some entries, ``--page-only``
rebuilds the page from the records alone, ``--list`` prints the manifest with each
entry's expected run time (about 40 minutes in all on 2 CPU cores with PoCL). The
device is the one the scripts pick: ``PYOPENCL_CTX``, else plenocl's default. A failing
entry is recorded and marked on the page, the others still run, and the command exits 1.
See :mod:`plenocl.bench.results`.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from plenocl.bench.results import records_dir, run_entries, write_page  # noqa: E402
from plenocl.bench.results_manifest import MANIFEST  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402


def print_manifest() -> None:
    """Each entry's name, section, expected minutes and command, then the total."""
    for entry in MANIFEST:
        print(f"{entry.name:12s} {entry.section:12s} {entry.minutes:5.1f} min  {entry.command}")
    print(f"{'total':25s} {sum(e.minutes for e in MANIFEST):5.1f} min (2 CPU cores, PoCL)")


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__)
    names = [e.name for e in MANIFEST]
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--only", nargs="+", metavar="NAME", choices=names,
                      help="run only these entries, then rebuild the page from every record")
    mode.add_argument("--page-only", action="store_true",
                      help="rebuild the page from the records; run nothing")
    mode.add_argument("--list", action="store_true",
                      help="print the manifest with each entry's expected run time")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "results.md",
                        help="the page (default docs/results.md); records in results/ "
                             "beside it")
    args = parser.parse_args(argv)
    if args.list:
        print_manifest()
        return 0
    if args.page_only:
        print(f"wrote {write_page(args.out, MANIFEST)} from {records_dir(args.out)}")
        return 0
    entries = [e for e in MANIFEST if args.only is None or e.name in args.only]
    failed = run_entries(entries, MANIFEST, ROOT, args.out)
    print(f"wrote {args.out} from {records_dir(args.out)}"
          + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
