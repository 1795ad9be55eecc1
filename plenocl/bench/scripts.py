"""What the scripts in ``benchmarks/`` share besides timing (:mod:`.timing`) and
workloads (:mod:`.core`, :mod:`.piv_section`): their command line."""

from __future__ import annotations

import argparse
from collections.abc import Mapping

__all__ = ["script_parser"]


def script_parser(doc: str | None, skips: Mapping[str, str | None] | None = None
                  ) -> argparse.ArgumentParser:
    """The argument parser of a benchmark script: its docstring's first line as the
    description, and a ``--skip-NAME`` flag for each entry of ``skips`` (name: help text
    or None)."""
    parser = argparse.ArgumentParser(description=doc.strip().splitlines()[0] if doc else None)
    for name, text in (skips or {}).items():
        parser.add_argument(f"--skip-{name}", action="store_true", help=text)
    return parser
