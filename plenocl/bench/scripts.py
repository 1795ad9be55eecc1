"""What the scripts in ``benchmarks/`` share besides timing (:mod:`.timing`) and
workloads (:mod:`.core`, :mod:`.piv_section`): their command line."""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping

from ..io.kept import CACHE_VARIABLE

__all__ = ["script_parser"]


def script_parser(doc: str | None, skips: Mapping[str, str | None] | None = None
                  ) -> argparse.ArgumentParser:
    """The argument parser of a benchmark script: its docstring's first line as the
    description, and a ``--skip-NAME`` flag for each entry of ``skips`` (name: help text
    or None). A benchmark measures its own choices (PIV's FFT route): unless
    ``PLENOCL_CACHE_DIR`` is set, it neither reads nor keeps a choice on the machine
    (:mod:`plenocl.io.kept`), so its figures do not depend on an earlier run's."""
    os.environ.setdefault(CACHE_VARIABLE, "")
    parser = argparse.ArgumentParser(description=doc.strip().splitlines()[0] if doc else None)
    for name, text in (skips or {}).items():
        parser.add_argument(f"--skip-{name}", action="store_true", help=text)
    return parser
