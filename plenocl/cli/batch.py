"""``plenocl run``: a configured batch of image pairs (:mod:`plenocl.batch`)."""

from __future__ import annotations

import argparse


def run_command(args: argparse.Namespace) -> int:
    """Process every pair of an experiment file; exit 1 when a pair failed."""
    from ..batch import run

    summary = run(args.experiment, args.out, queue=args.device)
    return 1 if summary.failed else 0


def add_run_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``run``."""
    p = subparsers.add_parser("run", help="process every image pair of an experiment file "
                                          "(resumable: finished pairs are skipped)")
    p.add_argument("experiment", help="experiment TOML (camera, grid, images, dt, settings)")
    p.add_argument("--out", default=None,
                   help="output folder (default: [output] folder of the experiment file)")
    p.set_defaults(func=run_command)
    return p
