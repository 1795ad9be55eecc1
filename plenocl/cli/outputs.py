"""What each command writes, checked before the command does any work: ``--out``'s
extension names a format the command writes, and its folder can be written in
(:func:`plenocl.io.outputs.check_output`); a command writing a folder of results gets
that folder checked (:func:`plenocl.io.outputs.check_output_folder`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io.fieldformat import FIELD_FORMATS
from ..io.files import VOLUME_FORMATS
from ..io.outputs import check_output, check_output_folder

__all__ = ["EXTRA_OUTPUTS", "FILE_OUTPUTS", "FOLDER_OUTPUTS", "check_outputs"]

_TIFF = {".tif": "TIFF", ".tiff": "TIFF"}
_TOML = {".toml": "TOML"}

#: Commands whose ``--out`` is a file: what it holds and the formats it may be written in.
FILE_OUTPUTS = {"piv": ("field", FIELD_FORMATS), "reconstruct": ("volume", VOLUME_FORMATS),
                "calibrate": ("camera", _TOML), "grid": ("grid", _TOML),
                "refocus": ("focal stack", _TIFF), "simulate": ("raw image", _TIFF),
                "white": ("white image", _TIFF)}
#: Commands whose ``--out`` is a folder of results.
FOLDER_OUTPUTS = ("run", "demo", "bench")
#: Further files a command writes, by option: what they hold and their formats.
_FIGURE = {".png": "PNG", ".pdf": "PDF", ".svg": "SVG"}
EXTRA_OUTPUTS = {"calibrate": {"diagnostic": ("diagnostic figure", _FIGURE),
                               "centres_out": ("centres table", {".csv": "CSV"})}}


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse (``ValueError``) an ``--out`` (or another output option of
    :data:`EXTRA_OUTPUTS`) of the wrong format or in a folder that cannot be written in,
    before the command starts."""
    for option, (what, formats) in EXTRA_OUTPUTS.get(args.command, {}).items():
        if getattr(args, option, None) is not None:
            check_output(getattr(args, option), formats, what)
    out = getattr(args, "out", None)
    if args.command == "plot":  # its folder (beside the input by default), before drawing
        check_output_folder(Path(out).parent if out is not None else
                            Path(args.input).parent)
    if out is None:
        return  # plenocl run without --out: the run checks its experiment's folder
    outputs = {"out", *EXTRA_OUTPUTS.get(args.command, {})}
    for option in outputs:
        if getattr(args, option, None) is not None:
            _not_an_input(args, option, outputs)
    if args.command in FILE_OUTPUTS:
        what, formats = FILE_OUTPUTS[args.command]
        check_output(out, formats, what)
    elif args.command in FOLDER_OUTPUTS:
        check_output_folder(out)


def _not_an_input(args: argparse.Namespace, option: str, outputs: set) -> None:
    """Refuse an output that is one of the command's input files: writing it would
    replace the input (a calibrated camera turned into a grid file, say)."""
    flag = "--" + option.replace("_", "-")
    check_not_inputs(args, [Path(getattr(args, option))], outputs,
                     f"{flag} {getattr(args, option)}")


def check_not_inputs(args: argparse.Namespace, paths, outputs=frozenset(),
                     said: str | None = None) -> None:
    """Refuse any of ``paths`` (files a command will write, ``--out`` or named after it)
    that is one of its input files (the options of ``args`` but ``outputs``): writing it
    would replace that input. ``said``: how the message names the output (the path)."""
    inputs = {}
    for name, value in vars(args).items():
        for given in value if isinstance(value, (list, tuple)) else [value]:
            if name not in outputs and isinstance(given, str) and Path(given).is_file():
                inputs.setdefault(Path(given).resolve(), name)
    for path in paths:
        name = inputs.get(Path(path).resolve())
        if name is not None:
            raise ValueError(f"{said or f'{path}, which this command writes,'} is also the "
                             f"command's input "
                             f"({name.replace('_', ' ')}): writing it would replace that "
                             "input; give the output another name")
