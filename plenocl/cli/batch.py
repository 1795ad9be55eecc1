"""``plenocl run``: a configured batch of image pairs (:mod:`plenocl.batch`)."""

from __future__ import annotations

import argparse


def run_command(args: argparse.Namespace) -> int:
    """Process every pair of an experiment file (or track its frames, with
    ``[tracking]``); exit 1 when a pair failed, 130 when interrupted (the finished pairs
    are kept and gathered)."""
    from ..batch import run

    summary = run(args.experiment, args.out, queue=args.device, workers=args.workers,
                  scheduler=args.scheduler, progress=not args.no_progress, redo=args.redo)
    return summary.exit_status()


def add_run_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``run``."""
    p = subparsers.add_parser("run", help="process every image pair of an experiment file, "
                                          "or track its frames ([tracking]); resumable: "
                                          "finished work is skipped")
    p.add_argument("experiment", help="experiment TOML (camera, grid, images, dt, settings)")
    p.add_argument("--out", default=None,
                   help="output folder (default: [output] folder of the experiment file)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None,
                       help="process pairs on a local Dask cluster of N worker processes")
    where.add_argument("--scheduler", default=None,
                       help="address of a running Dask scheduler (e.g. tcp://host:8786) to "
                            "process pairs on")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--redo", action="store_true",
                   help="redo the finished pairs a rerun would refuse (another camera or "
                        "grid, changed images, results without a record) instead of "
                        "refusing; changed settings are redone without it")
    p.set_defaults(func=run_command)
    return p
