"""Choices measured once and kept between processes, as FFTW keeps its wisdom.

Some choices plenocl makes by timing (which side runs PIV's FFT correlations,
:class:`plenocl.piv.devicefft.FFTRoute`) change results at float32 rounding. Measured
afresh in every process, they follow the machine's load, and two runs of the same data
can differ. :class:`KeptChoices` keeps each choice in a small JSON file the first time it
is measured; every later process on that machine reads it instead of measuring, so runs
agree to the bit. Several processes measuring at once (a batch's Dask workers starting
together) agree too: the first choice written stands, and :meth:`KeptChoices.keep`
returns it to the others.

The folder is ``$PLENOCL_CACHE_DIR`` where set (empty: keep nothing, each process
measures), else the user's cache folder (``platformdirs.user_cache_dir("plenocl")``,
``~/.cache/plenocl`` on Linux). Delete a file there to measure again (after a driver or
hardware change). A folder that cannot be written, or a damaged file, is said once in a
warning and the process goes on measuring for itself.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import platformdirs

from .atomic import write_json

__all__ = ["CACHE_VARIABLE", "KeptChoices", "cache_dir"]

#: The environment variable naming the folder of kept choices ("": none kept).
CACHE_VARIABLE = "PLENOCL_CACHE_DIR"
_FORMAT = 1  # the files' layout; a file of another is measured again, not read


def cache_dir() -> Path | None:
    """The folder of kept choices: ``$PLENOCL_CACHE_DIR``, else the user's cache folder;
    ``None`` where the variable is set empty (nothing kept)."""
    value = os.environ.get(CACHE_VARIABLE)
    if value is None:
        return Path(platformdirs.user_cache_dir("plenocl"))
    return Path(value) if value.strip() else None


class KeptChoices:
    """One kind of measured choice kept in ``<cache_dir>/<name>.json``.

    Parameters
    ----------
    name
        The file's name without ``.json`` (e.g. ``"fft_routes"``).
    what
        What the choice is, for the warnings (e.g. "the FFT route").

    Notes
    -----
    A key is a tuple of strings and numbers (written as its JSON text); a value any JSON
    object. Thread-safe; across processes the file is updated under an exclusive lock
    (``fcntl`` where the system has it) and replaced atomically.
    """

    def __init__(self, name: str, what: str) -> None:
        self.name, self.what = name, what
        self._lock = threading.Lock()
        self._warned = False

    def path(self) -> Path | None:
        """The file (``None``: nothing kept, :func:`cache_dir`)."""
        folder = cache_dir()
        return None if folder is None else folder / f"{self.name}.json"

    def get(self, key: tuple) -> dict | None:
        """The value kept for ``key``, or ``None``."""
        path = self.path()
        if path is None:
            return None
        with self._lock:
            return self._read(path).get(_text(key))

    def keep(self, key: tuple, value: dict,
             valid: Callable[[object], bool] | None = None) -> dict:
        """Keep ``value`` for ``key`` unless a value stands there already, and return the
        one that stands (``value`` where none did, or where nothing can be kept). A
        standing value that ``valid`` refuses is replaced."""
        path = self.path()
        if path is None:
            return value
        with self._lock:
            try:
                with _exclusive(path):
                    kept = self._read(path)
                    standing = kept.get(_text(key))
                    if standing is not None and (valid is None or valid(standing)):
                        return standing
                    write_json(path, {"format": _FORMAT,
                                      "choices": {**kept, _text(key): value}}, sort_keys=True)
            except OSError as exc:
                self._warn(f"could not write {path} ({exc.strerror or exc})")
        return value

    def _read(self, path: Path) -> dict:
        """The file's choices (empty where there is none, or it is damaged: warned)."""
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as exc:
            self._warn(f"could not read {path} ({exc})")
            return {}
        if not (isinstance(doc, dict) and doc.get("format") == _FORMAT
                and isinstance(doc.get("choices"), dict)):
            self._warn(f"{path} is not a file of kept choices this plenocl reads")
            return {}
        return doc["choices"]

    def _warn(self, problem: str) -> None:
        """Say once per object that ``what`` is measured in each process."""
        if not self._warned:
            self._warned = True
            warnings.warn(
                f"{problem}: {self.what} is measured in each process instead, so two runs "
                f"may choose differently (results differ at float32 rounding); set "
                f"{CACHE_VARIABLE} to a writable folder, or delete the file",
                RuntimeWarning, stacklevel=3)


def _text(key: tuple) -> str:
    """A key's JSON text (the file's key)."""
    return json.dumps(list(key))


@contextlib.contextmanager
def _exclusive(path: Path) -> Iterator[None]:
    """An exclusive lock on ``path``'s lock file for the block (no lock where the system
    has no ``fcntl``: the atomic replace still leaves a whole file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # not a POSIX system
        yield
        return
    with open(path.with_suffix(".lock"), "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
