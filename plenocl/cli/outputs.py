"""What each command writes, checked before the command does any work: ``--out``'s
extension names a format the command writes, and its folder can be written in
(:func:`plenocl.io.outputs.check_output`); a command writing a folder of results gets
that folder checked (:func:`plenocl.io.outputs.check_output_folder`).
"""

from __future__ import annotations

import argparse

from ..io.fields import FIELD_FORMATS
from ..io.files import VOLUME_FORMATS
from ..io.outputs import check_output, check_output_folder

__all__ = ["FILE_OUTPUTS", "FOLDER_OUTPUTS", "check_outputs"]

_TIFF = {".tif": "TIFF", ".tiff": "TIFF"}
_TOML = {".toml": "TOML"}

#: Commands whose ``--out`` is a file: what it holds and the formats it may be written in.
FILE_OUTPUTS = {"piv": ("field", FIELD_FORMATS), "reconstruct": ("volume", VOLUME_FORMATS),
                "calibrate": ("camera", _TOML), "grid": ("grid", _TOML),
                "refocus": ("focal stack", _TIFF), "simulate": ("raw image", _TIFF),
                "white": ("white image", _TIFF)}
#: Commands whose ``--out`` is a folder of results.
FOLDER_OUTPUTS = ("run", "demo", "bench")


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse (``ValueError``) an ``--out`` of the wrong format or in a folder that
    cannot be written in, before the command starts."""
    out = getattr(args, "out", None)
    if out is None:
        return  # plenocl run without --out: the run checks its experiment's folder
    if args.command in FILE_OUTPUTS:
        what, formats = FILE_OUTPUTS[args.command]
        check_output(out, formats, what)
    elif args.command in FOLDER_OUTPUTS:
        check_output_folder(out)
