"""A minimal reader of pyevtk's raw-appended VTK XML files (``.vti``, ``.vtu``), for the
tests that check what ParaView would read: header attributes and every data array."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

TYPES = {"Float64": "<f8", "Float32": "<f4", "UInt8": "u1", "Int32": "<i4", "Int64": "<i8"}


def read_appended(path: Path) -> tuple[dict, dict]:
    """``(attributes, arrays)``: the header's ``WholeExtent``, ``Origin`` and ``Spacing``
    (where present) and ``{name: (values, components)}`` of every data array."""
    raw = Path(path).read_bytes()
    head, _, data = raw.partition(b'<AppendedData encoding="raw">')
    text = head.decode("ascii")
    start = data.index(b"_") + 1
    attrs = dict(re.findall(r'(WholeExtent|Origin|Spacing)="([^"]*)"', text))
    arrays = {}
    for m in re.finditer(r"<DataArray ([^>]*)>", text):
        a = dict(re.findall(r'(\w+)="([^"]*)"', m.group(1)))
        off = start + int(a["offset"])
        nbytes = int(np.frombuffer(data[off:off + 8], "<u8")[0])
        arrays[a["Name"]] = (np.frombuffer(data[off + 8:off + 8 + nbytes], TYPES[a["type"]]),
                             int(a.get("NumberOfComponents", 1)))
    return attrs, arrays
