"""Which two files make each pair of a run: pairs from frame numbers, never positions.

A camera's frames are numbered (``frame_000.tif``, ``frame_001.tif``, ...). Pairs are
formed from those numbers, so a missing frame leaves a gap, reported by name, instead
of shifting every later pair onto the wrong exposures:

- ``sequence``: pair ``k`` is frames ``first + 2k`` and ``first + 2k + 1``;
- ``sliding``: pair ``k`` is frames ``first + k`` and ``first + k + 1``;
- ``ab``: pair ``k`` is ``<name>_a`` and ``<name>_b``, ``k`` from ``<name>``'s number
  (``first`` subtracted) or, without numbers, the position among the sorted names;
- ``list``: the pairs listed in the experiment file, ``k`` their position.

A tracking run (``[tracking]``) takes every frame by number instead, from ``first`` on,
with no gap (:func:`numbered_series`).

``first`` is ``[images] first_frame``, by default the lowest frame number found. The
number of a frame is the last run of digits in its file name (without the extension).
Each pair's source files are fingerprinted (name, size, modification time, SHA-256), so
that a rerun can tell whether its inputs changed (:func:`changed_since`).
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path

#: The pairing rules (see the module notes).
PAIRINGS = ("sequence", "sliding", "ab", "list")


@dataclass(frozen=True)
class ImagePair:
    """Pair ``index`` of a run and its two image files; with several cameras, those of
    the first camera, and ``others`` the other cameras' ``(a, b)`` in their order."""

    index: int
    a: Path
    b: Path
    others: tuple[tuple[Path, Path], ...] = ()


@dataclass
class PairPlan:
    """The pairs of a run, its gaps (``{pair index: why it cannot be made}``) and the
    files that belong to no pair."""

    pairs: list[ImagePair]
    gaps: dict[int, str] = field(default_factory=dict)
    unpaired: list[str] = field(default_factory=list)


def frame_number(path: Path) -> int | None:
    """The last run of digits in the file name's stem, or None."""
    found = re.findall(r"\d+", Path(path).stem)
    return int(found[-1]) if found else None


def numbered_frames(files: list[Path], pairing: str | None) -> dict[int, Path]:
    """``{frame number: file}``; a file without a number, or two files with the same
    number, is an error naming them and the fix (``pairing=None``: a tracking run's
    recording, which has no list of pairs to fall back on)."""
    frames: dict[int, Path] = {}
    fix = ("rename the frames or narrow [images] pattern to the recording's frames"
           if pairing is None else
           "rename the frames or list the pairs ([images] pairs = [[\"a.tif\", \"b.tif\"], "
           "...])")
    how = ("tracking orders the frames" if pairing is None
           else f"pairing {pairing!r} pairs frames")
    for f in files:
        n = frame_number(f)
        if n is None:
            raise ValueError(f"{f.name} has no frame number: {how} by the number in their "
                             f"names; {fix}")
        if n in frames:
            raise ValueError(f"{frames[n].name} and {f.name} have the same frame number {n}; "
                             f"keep one, or {fix.split(' or ', 1)[1]}")
        frames[n] = f
    return frames


def _by_numbers(frames: dict[int, Path], first: int, step: int, folder: Path,
                name_of) -> PairPlan:
    """Pairs ``(first + step k, first + step k + 1)`` up to the highest frame."""
    plan = PairPlan([])
    last = max(frames)
    # sequence: a last frame without its partner is reported; sliding: the last frame
    # simply has no successor
    count = (last - first) // 2 + 1 if step == 2 else last - first
    for k in range(count):
        na, nb = first + step * k, first + step * k + 1
        fa, fb = frames.get(na), frames.get(nb)
        if fa is not None and fb is not None:
            plan.pairs.append(ImagePair(k, fa, fb))
            continue
        missing = [name_of(n) for n, f in ((na, fa), (nb, fb)) if f is None]
        plan.gaps[k] = f"frame {na} + {nb}: {' and '.join(missing)} missing in {folder}"
    return plan


def numbered_series(files: list[Path], first_frame: int | None, folder: Path
                    ) -> dict[int, Path]:
    """The frames of one time-resolved recording, ``{frame number: file}`` in order from
    ``first_frame`` (default: the lowest found) to the highest: a time series at a
    constant interval, so a missing frame between them is an error naming it."""
    frames = numbered_frames(files, None)
    first = min(frames) if first_frame is None else int(first_frame)
    frames = {n: frames[n] for n in sorted(frames) if n >= first}
    if not frames:
        raise ValueError(f"no frame numbered {first} ([images] first_frame) or later in "
                         f"{folder}")
    example = next(iter(frames.values()))
    missing = [_name_like(example, n) for n in range(first, max(frames)) if n not in frames]
    if missing:
        raise ValueError(
            f"{', '.join(missing[:5])}{' and more' if len(missing) > 5 else ''} missing in "
            f"{folder}: tracking follows every frame of a recording at a constant interval; "
            "restore the frame, or track the frames before or after it ([images] "
            "first_frame, pattern)")
    return frames


def _name_like(example: Path, number: int) -> str:
    """The file name frame ``number`` would have, after ``example``'s pattern."""
    digits = re.findall(r"\d+", example.stem)[-1]
    start = example.stem.rfind(digits)
    stem = example.stem[:start] + f"{number:0{len(digits)}d}" + example.stem[start + len(digits):]
    return stem + example.suffix


def numbered_pairs(files: list[Path], pairing: str, first_frame: int | None,
                   folder: Path) -> PairPlan:
    """The plan of ``sequence`` or ``sliding`` pairing (see the module notes)."""
    frames = numbered_frames(files, pairing)
    first = min(frames) if first_frame is None else int(first_frame)
    if first > min(frames):
        frames = {n: f for n, f in frames.items() if n >= first}
    example = next(iter(frames.values()))
    return _by_numbers(frames, first, 2 if pairing == "sequence" else 1, folder,
                       lambda n: _name_like(example, n))


def ab_pairs(files: list[Path], a_suffix: str, b_suffix: str, first_frame: int | None,
             folder: Path) -> PairPlan:
    """The plan of ``ab`` pairing: each ``<name><a_suffix>`` with ``<name><b_suffix>``."""
    a_files = sorted(f for f in files if f.stem.endswith(a_suffix))
    b_names = {f.name for f in files if f.stem.endswith(b_suffix)}
    numbers = [frame_number(Path(f.stem[: -len(a_suffix)])) for f in a_files]
    numbered = None not in numbers and len(set(numbers)) == len(numbers)
    first = 0
    if numbered and numbers:
        first = min(numbers) if first_frame is None else first_frame
    plan = PairPlan([])
    for pos, (fa, n) in enumerate(zip(a_files, numbers)):
        k = n - first if numbered else pos
        fb = fa.with_name(fa.stem[: -len(a_suffix)] + b_suffix + fa.suffix)
        if fb.name in b_names:
            plan.pairs.append(ImagePair(k, fa, fb))
            b_names.discard(fb.name)
        else:
            plan.gaps[k] = f"{fb.name} missing in {folder} (for {fa.name})"
    for orphan in sorted(b_names):
        why = f"{orphan} has no {a_suffix} partner in {folder}"
        n = frame_number(Path(Path(orphan).stem[: -len(b_suffix)]))
        if numbered and n is not None and n >= first:
            plan.gaps[n - first] = why
        else:
            plan.unpaired.append(why)
    return plan


def common_first_frame(folders: list[list[Path]], images: dict) -> int | None:
    """The lowest frame number in any of several cameras' folders (each a list of its
    files), from which every camera's pairs are counted (:func:`matched_pairs` matches
    them by that count: counted from each folder's own lowest frame, folders starting at
    different numbers would pair frames of different instants). ``None`` where the
    frames are not numbered (``list`` pairing, ``ab`` pairs without numbers) or none
    are found: each folder is then paired as it is."""
    lowest = []
    for files in folders:
        if images["pairing"] == "list" or not files:
            return None
        if images["pairing"] == "ab":
            stems = [f.stem[: -len(images["a_suffix"])] for f in files
                     if f.stem.endswith(images["a_suffix"])]
            numbers = [frame_number(Path(stem)) for stem in stems]
            if not numbers or None in numbers:
                return None
        else:
            numbers = list(numbered_frames(files, images["pairing"]))
        lowest.append(min(numbers))
    return min(lowest)


def matched_pairs(plans: list[PairPlan]) -> PairPlan:
    """Several cameras' plans (each camera's folder paired by the same rule) as one:
    a pair is made where every camera has it, matched by its index (its frame numbers),
    never by position; a pair some camera lacks is a gap naming the camera and why."""
    first, *rest = plans
    by_camera = [{p.index: p for p in plan.pairs} for plan in rest]
    plan = PairPlan([], {k: f"camera 1: {why}" for k, why in first.gaps.items()})
    for pair in first.pairs:
        missing = [c for c, pairs in enumerate(by_camera, start=2) if pair.index not in pairs]
        if missing:
            plan.gaps[pair.index] = "; ".join(
                f"camera {c}: {rest[c - 2].gaps.get(pair.index, 'no such pair')}"
                for c in missing)
        else:
            plan.pairs.append(ImagePair(pair.index, pair.a, pair.b, tuple(
                (pairs[pair.index].a, pairs[pair.index].b) for pairs in by_camera)))
    made = {p.index for p in first.pairs}
    for c, pairs in enumerate(by_camera, start=2):
        for k in sorted(set(pairs) - made - set(plan.gaps)):
            plan.gaps[k] = f"camera 1: no such pair (camera {c} has it)"
    plan.unpaired = [f"camera {c}: {why}" for c, other in enumerate(plans, start=1)
                     for why in other.unpaired]
    plan.gaps = dict(sorted(plan.gaps.items()))
    return plan


def listed_pairs(pairs: list, folder: Path) -> PairPlan:
    """The plan of ``list`` pairing: ``[[a, b], ...]`` relative to ``folder``."""
    plan = PairPlan([])
    for k, (a, b) in enumerate(pairs):
        fa, fb = folder / a, folder / b
        missing = [p.name for p in (fa, fb) if not p.is_file()]
        if missing:
            plan.gaps[k] = f"{' and '.join(missing)} missing in {folder}"
        else:
            plan.pairs.append(ImagePair(k, fa, fb))
    return plan


# ---- fingerprints: which files made a pair, and whether they changed since ----------------
def fingerprint(path: Path) -> dict:
    """Name, size (bytes), modification time (ns) and SHA-256 of a file."""
    path = Path(path)
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            digest.update(block)
    stat = path.stat()
    return {"name": path.name, "bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns,
            "sha256": digest.hexdigest()}


def same_file(recorded: dict, path: Path) -> bool:
    """Whether ``path`` is the file ``recorded`` describes: name and size, then the
    modification time, else the SHA-256 (a copied file keeps its content)."""
    path = Path(path)
    if not path.is_file() or path.name != recorded.get("name"):
        return False
    stat = path.stat()
    if stat.st_size != recorded.get("bytes"):
        return False
    if stat.st_mtime_ns == recorded.get("mtime_ns"):
        return True
    return fingerprint(path)["sha256"] == recorded.get("sha256")


def sources_present(recorded: dict, folders: list[Path]) -> bool:
    """Whether every file a pair was made from (:func:`pair_sources`' record: camera 1's,
    then the other cameras' under ``"cameras"``) is still, unchanged, in its camera's
    folder of ``folders``."""
    per_camera = [recorded, *recorded.get("cameras", [])]
    if len(per_camera) != len(folders):
        return False
    return all(tag in files and _found(files[tag], Path(folder))
               for files, folder in zip(per_camera, folders) for tag in "ab")


def _found(recorded: dict, folder: Path) -> bool:
    """Whether the file ``recorded`` names is in ``folder`` or a folder below it (a
    pattern such as ``sub/*.tif`` reaches into one), unchanged."""
    name = str(recorded.get("name"))
    here = folder / name
    if here.is_file():
        return same_file(recorded, here)
    return any(same_file(recorded, path) for path in folder.rglob(name))


def pair_sources(pair: ImagePair) -> dict:
    """The fingerprints of a pair's files: ``{"a": .., "b": ..}``, and with several
    cameras ``"cameras"``: the other cameras' ``{"a": .., "b": ..}`` in their order."""
    sources = {"a": fingerprint(pair.a), "b": fingerprint(pair.b)}
    if pair.others:
        sources["cameras"] = [{"a": fingerprint(a), "b": fingerprint(b)}
                              for a, b in pair.others]
    return sources


def changed_since(recorded: dict, pair: ImagePair) -> str | None:
    """Why ``pair``'s files are not those ``recorded`` (:func:`pair_sources`), or None."""
    others = recorded.get("cameras", [])
    if len(others) != len(pair.others):
        return (f"it was made from {len(others) + 1} camera(s)' images, the run has "
                f"{len(pair.others) + 1}")
    files = [(recorded, "camera 1: " if others else "", pair.a, pair.b)] + [
        (rec, f"camera {c}: ", a, b)
        for c, (rec, (a, b)) in enumerate(zip(others, pair.others, strict=True), start=2)]
    for rec, whose, a, b in files:
        if (why := _changed_files(rec, a, b)) is not None:
            return whose + why
    return None


def _changed_files(recorded: dict, path_a: Path, path_b: Path) -> str | None:
    """Why the two files are not those ``recorded`` (``{"a": .., "b": ..}``), or None."""
    for tag, path in (("a", path_a), ("b", path_b)):
        rec = recorded.get(tag)
        if rec is None:
            return "its field records no source files (written by an older plenocl)"
        if not same_file(rec, path):
            size = path.stat().st_size if path.is_file() else None
            if rec.get("name") == path.name and rec.get("bytes") == size:
                return (f"it was made from {path.name} ({size} bytes), whose content has "
                        f"changed since (its SHA-256 differs) as exposure {tag}")
            return (f"it was made from {rec.get('name')} ({rec.get('bytes')} bytes), now "
                    f"{path.name} ({'missing' if size is None else f'{size} bytes'}) is "
                    f"exposure {tag}")
    return None
