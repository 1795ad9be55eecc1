"""``plenocl bench``: the benchmark report from the command line."""

from __future__ import annotations

import argparse

from ..bench import SIZES, run_report


def cmd_bench(args: argparse.Namespace) -> int:
    """``plenocl bench``: run the benchmark report and say where it is."""
    path = run_report(args.size, args.out, args.repeats, queue=getattr(args, "device", None))
    print(f"benchmark report: {path} (plots beside it)")
    return 0


def add_bench_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``bench`` on the CLI's subparsers (the device comes from ``--device``)."""
    p = subparsers.add_parser("bench", help="benchmark every stage against a baseline; "
                                            "write a Markdown report with plots")
    p.add_argument("--size", choices=SIZES, default="ci",
                   help="ci: 1-2 min on 2 cores; small: 10-15 min; paper: adds the 16 MP "
                        "experiment (default: ci)")
    p.add_argument("--out", default="plenocl_bench", help="output folder (default: "
                                                          "plenocl_bench)")
    p.add_argument("--repeats", type=_positive_int, default=None,
                   help="runs per timing, the median is reported (default: per size)")
    p.set_defaults(func=cmd_bench)
    return p


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value
