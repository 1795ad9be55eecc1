"""Reading and writing TOML files (camera and grid descriptions)."""

from __future__ import annotations

import sys
from pathlib import Path

import tomli_w

from .atomic import atomic_path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib


def read_toml(path: str | Path) -> dict:
    """Parse a TOML file, naming the file in any error."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise FileNotFoundError(f"no such file: {path}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path} is not valid TOML: {exc}") from None


def write_toml(path: str | Path, doc: dict) -> None:
    """Write ``doc`` as TOML, atomically (no half-written file on failure)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(tomli_w.dumps(doc).encode())
