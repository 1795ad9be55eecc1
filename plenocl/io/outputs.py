"""Output paths checked before any work: a format the writer knows (by the file name's
extension) and a folder that can be written in.

Every command and run that writes a field, a volume or another result calls
:func:`check_output` (or :func:`check_output_folder` for a folder of results) first, so
that a wrong extension or an unwritable folder is refused in a second, not after the
reconstruction or the correlation.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

__all__ = ["check_output", "check_output_folder", "disk_full"]


def check_output(path: str | Path, formats: Mapping[str, str], what: str) -> Path:
    """``path`` as a ``Path`` once its extension is one of ``formats`` and its folder can
    be written in; a ``ValueError`` naming the supported extensions otherwise.

    Parameters
    ----------
    path
        The file to be written (it may exist: it will be replaced).
    formats
        The extensions the writer takes (lower case, with the dot), each with a short
        description.
    what
        What the file holds (``"field"``, ``"volume"``), for the message.
    """
    path = Path(path)
    if path.suffix.lower() not in formats:
        listed = ", ".join(f"{ext} ({name})" for ext, name in formats.items())
        raise ValueError(f"cannot tell the {what} format from {path.name!r}: use one of "
                         f"{listed}")
    if path.is_dir():
        raise ValueError(f"{path} is a folder; give a {what} file name inside it, e.g. "
                         f"{path / ('out' + next(iter(formats)))}")
    check_output_folder(path.parent)
    return path


def check_output_folder(folder: str | Path) -> Path:
    """``folder`` once files can be created in it (or in the nearest folder above it
    that exists, where it would be made); a ``ValueError`` naming the folder otherwise.

    The check writes and removes a small temporary file, so that it answers for what a
    writer will meet (permissions, a read-only disk), not for what the mode bits say.
    """
    folder = Path(folder)
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"cannot write in {folder}: {existing} is a file, not a folder; "
                         "choose another output path")
    try:
        fd, probe = tempfile.mkstemp(prefix=".plenocl-write-check.", dir=existing)
    except OSError as exc:
        raise ValueError(f"cannot write in {existing} ({exc.strerror or exc}); choose an "
                         "output folder you can write in") from None
    os.close(fd)
    os.unlink(probe)
    return folder


def disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` is the operating system's "no space left on device" (a batch stops
    at it; the command line says the fix)."""
    return isinstance(exc, OSError) and exc.errno == errno.ENOSPC
