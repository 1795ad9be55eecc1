"""NumPy's ``.npz`` and ``.npy`` files read with their failures named: a truncated,
corrupt or foreign file is a ``ValueError`` that names the file, what it should hold and
the fix, never a bare ``zipfile.BadZipFile`` or NumPy's note on pickled data."""

from __future__ import annotations

import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np


class MissingArray(ValueError):
    """A readable ``.npz`` without an array asked for: a file of another kind."""


#: What a file that cannot be opened raises: said as it is, not as damage.
ACCESS = (FileNotFoundError, PermissionError, IsADirectoryError)
#: What reading a damaged ``.npz`` or ``.npy`` raises, at opening or at an array.
DAMAGED = (zipfile.BadZipFile, EOFError, zlib.error, ValueError, OSError)


def damaged(path, what: str, exc: BaseException) -> ValueError:
    """The error for a file that cannot be read as ``what``."""
    why = ("not a NumPy file, or one of objects: NumPy read pickled data, which it does "
           "not load" if "pickle" in str(exc) else f"{type(exc).__name__}: {exc}")
    return ValueError(f"{path} cannot be read as {what} ({why}): the file is truncated, "
                      "damaged or not one plenocl wrote; write or copy it again")


@contextmanager
def open_npz(path, what: str) -> Iterator[np.lib.npyio.NpzFile]:
    """``np.load`` of a ``.npz`` (no pickles) as a context; a file that cannot be opened
    or whose arrays cannot be read (damaged) is a ``ValueError`` naming it and ``what``
    it should be, one that lacks an array asked for a :class:`MissingArray`
    (``FileNotFoundError`` stays)."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"no such file: {path}")
    try:
        data = np.load(path)
    except ACCESS:
        raise
    except DAMAGED as exc:
        raise damaged(path, what, exc) from exc
    if not isinstance(data, np.lib.npyio.NpzFile):  # a .npy file named .npz
        raise damaged(path, what, ValueError("a single .npy array, not an .npz archive"))
    with data:
        try:
            yield data
        except KeyError as exc:
            raise MissingArray(f"{path} is not {what}: {exc.args[0]} (it holds "
                               f"{sorted(data.files)})") from exc
        except (zipfile.BadZipFile, EOFError, zlib.error) as exc:
            raise damaged(path, what, exc) from exc
        except ValueError as exc:  # an object array (pickles are never loaded)
            if "allow_pickle" not in str(exc):
                raise
            raise damaged(path, what, exc) from exc


def load_npy(path, what: str) -> np.ndarray:
    """The array of a ``.npy`` file (no pickles); a damaged or foreign one is a
    ``ValueError`` naming it and ``what`` it should be."""
    try:
        return np.load(path)
    except ACCESS:
        raise
    except DAMAGED as exc:
        raise damaged(path, what, exc) from exc
