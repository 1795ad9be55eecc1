"""Reading and writing TOML files (camera and grid descriptions)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import tomli_w

from .atomic import atomic_path


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
    except UnicodeDecodeError:  # a binary file (a volume, an image) given as a TOML file
        raise ValueError(f"{path} is not a TOML text file (a camera, grid or experiment "
                         "file is TOML text)") from None


def write_toml(path: str | Path, doc: dict) -> None:
    """Write ``doc`` as TOML, atomically (no half-written file on failure).

    Tables of numbers, strings and (nested) numeric lists, as camera and grid files hold,
    are written compactly: a list on one line, a list of lists one row per line (a
    calibrated camera's centres: one line per microlens row). Numbers keep their exact
    value (shortest round-trip representation).
    """
    with atomic_path(path) as tmp:
        tmp.write_text(dumps(doc), encoding="utf-8")


def dumps(doc: dict) -> str:
    """``doc`` as TOML text, compact for tables of scalars and numeric lists."""
    if not all(isinstance(t, dict) and all(_simple(v) for v in t.values())
               for t in doc.values()):
        return tomli_w.dumps(doc)
    parts = []
    for name, table in doc.items():
        lines = [f"[{name}]"] + [f"{key} = {_value(v)}" for key, v in table.items()]
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"


def _scalar(v) -> bool:
    return isinstance(v, (bool, int, float, str))


def _simple(v) -> bool:
    if _scalar(v):
        return True
    return isinstance(v, list) and all(
        _scalar(x) or (isinstance(x, list) and all(_scalar(y) for y in x)) for x in v)


def _value(v) -> str:
    if isinstance(v, list):
        if v and all(isinstance(x, list) for x in v):
            return "[\n" + "".join(f"    {_value(x)},\n" for x in v) + "]"
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, str):
        return tomli_w.dumps({"v": v})[4:].strip()  # TOML's string quoting
    if isinstance(v, bool):
        return "true" if v else "false"
    return repr(v) if isinstance(v, float) else str(v)
