"""Where a run keeps each pair's files in its output folder (one place for the names)."""

from __future__ import annotations

import shutil
from pathlib import Path

#: The folder of per-pair files inside a run's output folder.
PAIRS = "pairs"


def pair_file(out: Path, index: int) -> Path:
    """Where pair ``index``'s field goes (its presence marks the pair done)."""
    return Path(out) / PAIRS / f"pair_{index:05d}.npz"


def volume_file(field_file: Path) -> Path:
    """The reconstructed volumes kept beside a pair's field for ensemble correlation."""
    field_file = Path(field_file)
    return field_file.with_name("volumes_" + field_file.name.removeprefix("pair_"))


def pair_index(field_file: Path) -> int:
    """The pair index in a field file's name (the inverse of :func:`pair_file`)."""
    return int(Path(field_file).stem.removeprefix("pair_"))


def remove_partial_files(out: Path) -> list[Path]:
    """Delete what a killed run left half-written: the atomic writers' temporary files
    (``.<name>.*.part*``) and a time-series store being written (``*.partial``)."""
    out = Path(out)
    left = [*out.glob(".*.part*"), *(out / PAIRS).glob(".*.part*"), *out.glob("*.partial")]
    for path in left:
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    return left


def finished_pairs(out: Path) -> list[tuple[int, Path]]:
    """``(index, field file)`` of every finished pair in ``out``, by index: the inverse of
    :func:`pair_file`."""
    found = []
    for path in (Path(out) / PAIRS).glob("pair_*.npz"):
        number = path.stem.removeprefix("pair_")
        if number.isdigit():
            found.append((int(number), path))
    return sorted(found)
