"""What every settings object shares: built from keywords or from a document's table.

The settings classes (``ReconstructionSettings``, ``PIVSettings``, ``MTESettings``,
``ImageFitSettings``, ``PairSettings``) are frozen dataclasses that check their values
when made. A function that takes one also takes its fields as keywords
(:func:`with_keywords`); a file's table becomes one through :func:`from_table`, which
names an unknown key and the keys allowed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

import numpy as np


def is_integer(value) -> bool:
    """An integer (Python's or NumPy's), and not a bool: what a count option takes."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def is_number(value) -> bool:
    """A real number (Python's or NumPy's), and not a bool or text: what a quantity
    option takes."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, bool)


def whole_counts(settings, names) -> None:
    """The counts ``names`` of a frozen settings object given as whole floats (``3.0``,
    as a file may write them) made integers; other values are left to its checks."""
    for name in names:
        value = getattr(settings, name)
        if isinstance(value, (float, np.floating)) and np.isfinite(value) \
                and float(value).is_integer():
            object.__setattr__(settings, name, int(value))


def field_names(cls) -> list[str]:
    """The fields of a settings dataclass, in order."""
    return [f.name for f in dataclasses.fields(cls)]


def _same(a, b) -> bool:
    try:
        return bool(a == b)
    except (ValueError, TypeError):  # arrays: equal only when they are the same object
        return a is b


def with_keywords(cls, settings, keywords: dict, where: str):
    """``settings`` (an instance of ``cls`` or ``None``: the defaults) with ``keywords``.

    Raises
    ------
    TypeError
        A keyword that is no field of ``cls``; ``settings`` of another type; or, with
        ``settings`` given, a keyword whose value differs from the settings' (pass one
        or the other).
    """
    names = field_names(cls)
    unknown = sorted(set(keywords) - set(names))
    if unknown:
        raise TypeError(f"{where}() got unknown keyword(s) {unknown}; the options are "
                        f"{names}")
    if settings is None:
        return cls(**keywords)
    if not isinstance(settings, cls):
        raise TypeError(f"{where}(settings=...) takes a {cls.__name__}, got "
                        f"{type(settings).__name__}{_part_hint(cls, settings)}")
    conflict = sorted(k for k, v in keywords.items() if not _same(getattr(settings, k), v))
    if conflict:
        raise TypeError(f"{where}() got both settings and keyword(s) {conflict} that differ "
                        f"from them; pass the options one way (dataclasses.replace(settings, "
                        f"...) changes a settings object)")
    return settings


#: How a file writes an option set to ``None`` (TOML has no null): ``weighting = "none"``.
NONE = "none"


def refuse_unknown(given, allowed, message: Callable[[list[str]], str]) -> None:
    """A ``ValueError`` with ``message(unknown)`` when ``given`` holds keys that
    ``allowed`` does not (sorted, so the message is stable)."""
    unknown = sorted(set(given) - set(allowed))
    if unknown:
        raise ValueError(message(unknown))


def _part_hint(cls, settings) -> str:
    """``"; pass it as part=..."`` when ``settings`` is of the type of one of ``cls``'s
    fields (a ReconstructionSettings given where a PairSettings is taken)."""
    name = type(settings).__name__
    parts = [f.name for f in dataclasses.fields(cls) if name in str(f.type)]
    return f"; pass it as {parts[0]}=... (a part of the {cls.__name__})" if parts else ""


def from_table(cls, table, where: str):
    """A ``cls`` from a document's table (e.g. a TOML section): an unknown key, a table
    that is none, or a bad value is a ``ValueError`` naming ``where``. The string
    :data:`NONE` stands for ``None`` (no option takes it as a string)."""
    if not isinstance(table, Mapping):
        raise ValueError(f"{where} must be a table of {cls.__name__} options, got {table!r}")
    names = field_names(cls)
    refuse_unknown(table, names, lambda bad: f"{where}: unknown key(s) {bad}; it takes {names}")
    try:
        return cls(**{k: None if v == NONE else v for k, v in table.items()})
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from exc


def to_table(settings, skip: tuple[str, ...] = (), none=None) -> dict:
    """A settings object's fields as a plain dict (tuples as lists), ``skip`` left out;
    ``None`` values written as ``none`` (:data:`NONE` for a file :func:`from_table`
    reads back)."""
    return {f.name: _plain(getattr(settings, f.name), none)
            for f in dataclasses.fields(settings) if f.name not in skip}


def _plain(value, none=None):
    if isinstance(value, (tuple, list)):
        return [_plain(v, none) for v in value]
    return none if value is None else value
