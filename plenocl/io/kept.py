"""Choices measured once and kept between processes, as FFTW keeps its wisdom.

Some choices plenocl makes by timing (which side runs PIV's FFT correlations,
:class:`plenocl.piv.devicefft.FFTRoute`) change results at float32 rounding. Measured
afresh in every process, they follow the machine's load, and two runs of the same data
can differ. :class:`KeptChoices` keeps each choice in a small JSON file the first time it
is measured; every later process on that machine reads it instead of measuring, so runs
agree to the bit. Processes that need the same choice at once (a batch's Dask workers
starting together) take turns: one measures under the file's lock, the others wait and
read its choice.

The folder is ``$PLENOCL_CACHE_DIR`` where set (empty: keep nothing, each process
measures), else the user's cache folder (``platformdirs.user_cache_dir("plenocl")``:
``~/.cache/plenocl`` on Linux). Delete a file there to measure again (after a driver or
hardware change). A folder that cannot be written is warned of and the process measures
for itself; a damaged file is warned of and replaced by the process's measurements.
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
#: The files' layout, in their names: another layout's file is neither read nor written.
FORMAT = 1


def cache_dir() -> Path | None:
    """The folder of kept choices (absolute): ``$PLENOCL_CACHE_DIR`` (``~`` expanded),
    else the user's cache folder; ``None`` where the variable is set empty (nothing
    kept)."""
    value = os.environ.get(CACHE_VARIABLE)
    if value is None:
        return Path(platformdirs.user_cache_dir("plenocl")).absolute()
    return Path(value).expanduser().absolute() if value.strip() else None


class KeptChoices:
    """One kind of measured choice kept in ``<cache_dir>/<name>.v<FORMAT>.json``.

    Parameters
    ----------
    name
        The file's name before its format (e.g. ``"fft_routes"``).
    what
        What the choice is, for the warnings (e.g. "the FFT route").

    Notes
    -----
    A key is a tuple of strings and numbers (written as its JSON text, NumPy numbers as
    Python's); a value any JSON object. Thread-safe; across processes the file is read,
    measured for and written under an exclusive lock (``fcntl`` where the system has it)
    and replaced atomically.
    """

    def __init__(self, name: str, what: str) -> None:
        self.name, self.what = name, what
        self._lock = threading.Lock()

    def path(self) -> Path | None:
        """The file (``None``: nothing kept, :func:`cache_dir`)."""
        folder = cache_dir()
        return None if folder is None else folder / f"{self.name}.v{FORMAT}.json"

    def get(self, key: tuple, valid: Callable[[object], bool] | None = None) -> dict | None:
        """The value kept for ``key`` (``None``: none, or one ``valid`` refuses)."""
        path = self.path()
        if path is None:
            return None
        with self._lock:
            value = self._read(path).get(_text(key))
        return value if _usable(value, valid) else None

    def choose(self, key: tuple, measure: Callable[[], dict],
               valid: Callable[[object], bool] | None = None) -> dict:
        """The value kept for ``key``; where none is (or one ``valid`` refuses),
        ``measure()``'s, kept for every later call and process. Another process choosing
        the same file waits for this one, and then reads its value instead of measuring
        (so the processes agree, and no two measurements are timed against each other).
        Where nothing can be kept, ``measure()``'s value alone."""
        path = self.path()
        if path is None:
            return measure()
        value = None
        with self._lock:
            try:
                with _exclusive(path):
                    kept = self._read(path)
                    standing = kept.get(_text(key))
                    if _usable(standing, valid):
                        return standing
                    value = measure()
                    write_json(path, {"choices": {**kept, _text(key): value}}, sort_keys=True)
            except OSError as exc:
                self._warn(f"could not keep it in {path} ({exc.strerror or exc})")
        return measure() if value is None else value

    def _read(self, path: Path) -> dict:
        """The file's choices (empty where there is none, or it is damaged: warned)."""
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (FileNotFoundError, NotADirectoryError):  # none there (yet)
            return {}
        except (OSError, ValueError, RecursionError) as exc:
            self._warn(f"could not read {path} ({type(exc).__name__}: {exc}); it is "
                       "replaced by this process's measurements")
            return {}
        if not (isinstance(doc, dict) and isinstance(doc.get("choices"), dict)):
            self._warn(f"{path} holds no kept choices; it is replaced by this process's "
                       "measurements")
            return {}
        return doc["choices"]

    def _warn(self, problem: str) -> None:
        """Say ``problem`` (the warnings module shows it once per place by default)."""
        warnings.warn(f"{problem}: {self.what} is measured by the process that needs it, "
                      f"so two runs may choose differently (results differ at float32 "
                      f"rounding) until it is kept; set {CACHE_VARIABLE} to a writable "
                      "folder, or delete the file", RuntimeWarning, stacklevel=4)


def _usable(value, valid: Callable[[object], bool] | None) -> bool:
    """Whether a kept ``value`` stands: there, and not refused by ``valid``."""
    return value is not None and (valid is None or valid(value))


def _text(key: tuple) -> str:
    """A key's JSON text (the file's key; NumPy numbers written as Python's)."""
    return json.dumps([v.item() if hasattr(v, "item") else v for v in key])


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
    lock = path.with_suffix(".lock")
    try:
        handle = open(lock, "a")
    except PermissionError:  # another user's lock file: a read handle locks too
        handle = open(lock)
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
