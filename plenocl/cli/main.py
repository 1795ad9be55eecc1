"""The ``plenocl`` command line: devices | simulate | calibrate | refocus | reconstruct |
piv | run | plot | demo | bench (and white, grid)."""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
import warnings
from collections.abc import Sequence

from ..io.outputs import disk_full
from .batch import add_run_parser
from .bench import add_bench_parser
from .calibrate import add_calibrate_parser, add_refocus_parser
from .outputs import check_outputs
from .plot import add_plot_parser
from .simulate import add_simulate_parsers
from .volume import add_demo_parser, add_piv_parser, add_reconstruct_parser


def cmd_devices(args: argparse.Namespace) -> int:
    """List OpenCL platforms and devices; with ``--agree``, compare them (exit 1 when a
    stage differs by more than its tolerance)."""
    from ..opencl.device import building_devices, describe_devices, get_queue

    print(describe_devices())
    if not args.agree:
        return 0
    from ..bench.agreement import agreement, agreement_table

    building, failing = building_devices()
    for dev, problem in failing:
        print(f"skipped {dev.name.strip()}: its driver cannot build kernels ({problem})")
    if len(building) < 2:
        print(f"\n{len(building)} OpenCL device(s) build plenocl's kernels: nothing to compare "
              "(with PoCL alone, POCL_DEVICES='pthread basic' gives two)")
        return 0
    rows = agreement([get_queue(d) for d in building], log=lambda m: print(m, flush=True))
    print("\n" + agreement_table(rows, building[0].name.strip()))
    bad = [r for r in rows if not r.ok]
    print(f"\n{len(rows) - len(bad)} of {len(rows)} comparisons within tolerance")
    return 1 if bad else 0


DEVICE_HELP = ("OpenCL device name or type substring (default: PYOPENCL_CTX, else the first "
               "of a GPU, PoCL, Intel's CPU runtime that builds plenocl's kernels; "
               "`plenocl devices` shows which)")


class _Parser(argparse.ArgumentParser):
    """An argument parser that reads every number with a minus sign as a value, also in
    exponent form (``--dt -175e-6``, which argparse alone takes for an option and answers
    "expected one argument"): the value's own check then names its sign."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        # argparse's own test (Python < 3.13) knows -1 and -.5 only
        self._negative_number_matcher = NEGATIVE_NUMBER


#: A number with a minus sign: an integer, a decimal, with or without an exponent.
NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


class _DefaultsHelp(argparse.HelpFormatter):
    """Help that states each option's default, unless it is none or already stated."""

    def _get_help_string(self, action) -> str:
        text = action.help or ""
        if ("default" not in text and action.default not in (None, False, argparse.SUPPRESS)
                and action.option_strings):
            text += " (default: %(default)s)"
        return text


class _Subcommands:
    """The subparsers, each made with the defaults shown in its help and ``--device``
    accepted after the subcommand as well as before it."""

    def __init__(self, action, common: argparse.ArgumentParser) -> None:
        self._action, self._common = action, common

    def add_parser(self, name: str, **kw) -> argparse.ArgumentParser:
        kw.setdefault("formatter_class", _DefaultsHelp)
        kw["parents"] = [*kw.get("parents", []), self._common]
        kw.setdefault("description", kw.get("help"))
        return self._action.add_parser(name, **kw)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every registered subcommand."""
    from ..version import __version__

    parser = _Parser(prog="plenocl", description=" ".join(__doc__.split()),
                     formatter_class=_DefaultsHelp)
    parser.add_argument("--version", action="version", version=f"plenocl {__version__}")
    parser.add_argument("--device", default=None, help=DEVICE_HELP)
    common = _Parser(add_help=False)
    common.add_argument("--device", default=argparse.SUPPRESS, help=DEVICE_HELP)
    for p in (parser, common):  # before or after the subcommand
        loud = p.add_mutually_exclusive_group()
        loud.add_argument("-q", "--quiet", action="store_true",
                          default=False if p is parser else argparse.SUPPRESS,
                          help="print errors and warnings only: no progress, no results "
                               "summary, no note of which device runs")
        loud.add_argument("-v", "--verbose", action="store_true",
                          default=False if p is parser else argparse.SUPPRESS,
                          help="also say which OpenCL device runs, and repeat each warning "
                               "where it recurs")
    sub = _Subcommands(parser.add_subparsers(dest="command", required=True), common)
    dev = sub.add_parser("devices", help="list OpenCL platforms and devices")
    dev.add_argument("--agree", action="store_true",
                     help="run the same small workloads on every device and compare them "
                          "with the first (stated tolerances; exit 1 beyond them)")
    dev.set_defaults(func=cmd_devices)
    add_simulate_parsers(sub)
    add_calibrate_parser(sub)
    add_refocus_parser(sub)
    add_reconstruct_parser(sub)
    add_piv_parser(sub)
    add_run_parser(sub)
    add_plot_parser(sub)
    add_demo_parser(sub)
    add_bench_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``plenocl`` and ``python -m plenocl``: errors print one line and
    exit 2, Ctrl-C exits 130, warnings print once each as ``plenocl CMD: warning: ...``."""
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings(), _quiet(args.quiet):
        warnings.showwarning = _warning_printer(args.command, once=not args.verbose)
        if args.quiet:  # which device runs is no error: -v says it
            from ..opencl.device import DeviceFallbackWarning

            warnings.simplefilter("ignore", DeviceFallbackWarning)
        if args.verbose:
            _say_device(args)
        try:
            check_outputs(args)  # before any work
            return int(args.func(args) or 0)
        except (ValueError, TypeError, OSError, MemoryError, RuntimeError) as exc:
            # TypeError: the API's refusal of a complex or boolean array, say
            print(f"plenocl {args.command}: error: {exc}{_hint(exc)}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"plenocl {args.command}: interrupted; finished outputs are kept, "
                  "unfinished ones were not written", file=sys.stderr)
            return 130


def _hint(exc: Exception) -> str:
    """The fix for an operating system's error the message alone does not say (a full
    disk); empty otherwise."""
    if disk_full(exc):
        return ("; free space on that disk or write elsewhere (--out): finished outputs "
                "are kept, a rerun makes the rest")
    return ""


def _warning_printer(command: str, once: bool = True):
    """A ``warnings.showwarning`` that prints each message once (every time with
    ``once=False``), without a source line."""
    seen: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = str(message)
        if text not in seen or not once:
            seen.add(text)
            print(f"plenocl {command}: warning: {text}", file=sys.stderr)

    return show


@contextlib.contextmanager
def _quiet(quiet: bool):
    """With ``-q``: what commands print to standard output, and progress bars, go
    nowhere; warnings and errors (standard error) still show."""
    if not quiet:
        yield
        return
    old = os.environ.get("TQDM_DISABLE")
    os.environ["TQDM_DISABLE"] = "1"  # tqdm reads it for every bar
    try:
        with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
            yield
    finally:
        if old is None:
            os.environ.pop("TQDM_DISABLE", None)
        else:
            os.environ["TQDM_DISABLE"] = old


def _say_device(args: argparse.Namespace) -> None:
    """``-v``: the device the command's default choice gives (or the one named)."""
    from ..opencl.device import create_context, fallback_note

    if args.command in ("devices", "run", "plot"):
        return  # devices lists them all; a run's workers choose their own; plot uses none
    dev = create_context(args.device).devices[0]
    print(f"plenocl {args.command}: OpenCL device {dev.name.strip()} on "
          f"{dev.platform.name.strip()}", file=sys.stderr)
    if args.device is None and fallback_note():
        print(f"plenocl {args.command}: {fallback_note()}", file=sys.stderr)
