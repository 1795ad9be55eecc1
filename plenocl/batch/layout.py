"""Where a run keeps each pair's files in its output folder (one place for the names);
a pair is done when its field file exists with the run's record (:mod:`.record`)."""

from __future__ import annotations

from pathlib import Path

from ..pipeline import resume

#: The folder of per-pair files inside a run's output folder.
PAIRS = "pairs"


#: The copies of a field a run may write beside its ``.npz`` (``[output] formats``).
COPY_SUFFIXES = (".vti", ".h5", ".dat", ".csv")


def field_copies(field_file: Path, formats: tuple[str, ...] = ()) -> list[Path]:
    """The copies of a field beside it: those present, and those of ``formats`` (the
    suffixes a run writes) whether present or not."""
    return [field_file.with_suffix(s) for s in COPY_SUFFIXES
            if s in formats or field_file.with_suffix(s).is_file()]


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
    """Delete what a killed run left half-written in ``out`` and its pairs folder
    (:func:`plenocl.pipeline.resume.remove_partial_files`)."""
    return resume.remove_partial_files(Path(out), Path(out) / PAIRS)


def finished_pairs(out: Path) -> list[tuple[int, Path]]:
    """``(index, field file)`` of every finished pair in ``out``, by index: the inverse of
    :func:`pair_file`."""
    found = []
    for path in (Path(out) / PAIRS).glob("pair_*.npz"):
        number = path.stem.removeprefix("pair_")
        if number.isdigit():
            found.append((int(number), path))
    return sorted(found)
