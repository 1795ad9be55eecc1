"""Pairs from frame numbers, gaps reported by name, source fingerprints (batch/pairing)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from plenocl.batch.pairing import (
    ImagePair,
    ab_pairs,
    changed_since,
    fingerprint,
    frame_number,
    listed_pairs,
    numbered_pairs,
    same_file,
)


def _frames(folder: Path, numbers, pattern="frame_{:03d}.tif") -> list[Path]:
    files = []
    for n in numbers:
        f = folder / pattern.format(n)
        f.write_bytes(f"frame {n}".encode())
        files.append(f)
    return sorted(files)


def _as_names(plan) -> dict[int, tuple[str, str]]:
    return {p.index: (p.a.name, p.b.name) for p in plan.pairs}


def test_frame_numbers_are_the_last_digits_of_the_stem():
    assert frame_number(Path("run2_frame_0042.tif")) == 42
    assert frame_number(Path("B00017.tiff")) == 17
    assert frame_number(Path("white.tif")) is None


def test_a_missing_frame_is_a_gap_not_a_shift(tmp_path):
    """The issue's case: frame_003 deleted from six pairs. Every later pair keeps its
    own two exposures; pair 1 is reported with the missing file's name."""
    files = _frames(tmp_path, [n for n in range(12) if n != 3])
    plan = numbered_pairs(files, "sequence", None, tmp_path)
    assert _as_names(plan) == {k: (f"frame_{2 * k:03d}.tif", f"frame_{2 * k + 1:03d}.tif")
                               for k in (0, 2, 3, 4, 5)}
    assert list(plan.gaps) == [1] and "frame_003.tif missing" in plan.gaps[1]


def test_sliding_pairs_skip_both_pairs_touching_a_gap(tmp_path):
    files = _frames(tmp_path, [0, 1, 2, 4, 5])
    plan = numbered_pairs(files, "sliding", None, tmp_path)
    assert _as_names(plan) == {0: ("frame_000.tif", "frame_001.tif"),
                               1: ("frame_001.tif", "frame_002.tif"),
                               4: ("frame_004.tif", "frame_005.tif")}
    assert sorted(plan.gaps) == [2, 3] and all("frame_003.tif" in g for g in plan.gaps.values())


def test_an_odd_last_frame_and_first_frame_are_honoured(tmp_path):
    files = _frames(tmp_path, range(1, 6))  # frames 1..5: numbered from 1
    plan = numbered_pairs(files, "sequence", None, tmp_path)
    assert _as_names(plan) == {0: ("frame_001.tif", "frame_002.tif"),
                               1: ("frame_003.tif", "frame_004.tif")}
    assert "frame_006.tif missing" in plan.gaps[2]
    # the first frame itself lost: first_frame keeps the pairs on their exposures
    plan = numbered_pairs(files[1:], "sequence", 1, tmp_path)
    assert _as_names(plan) == {1: ("frame_003.tif", "frame_004.tif")}
    assert "frame_001.tif missing" in plan.gaps[0] and 2 in plan.gaps


def test_names_without_numbers_or_with_one_number_twice_are_refused(tmp_path):
    files = _frames(tmp_path, [0, 1]) + [tmp_path / "white.tif"]
    with pytest.raises(ValueError, match=r"white.tif has no frame number.*\[images\] pairs"):
        numbered_pairs(files, "sequence", None, tmp_path)
    twice = _frames(tmp_path, [0, 1]) + _frames(tmp_path, [1], "frame_{:d}.tif")
    with pytest.raises(ValueError, match="same frame number 1"):
        numbered_pairs(sorted(twice), "sequence", None, tmp_path)


def test_ab_pairs_report_a_missing_partner_at_its_own_index(tmp_path):
    names = ["run_00_a", "run_00_b", "run_01_a", "run_02_a", "run_02_b", "run_03_b"]
    files = sorted(_frames(tmp_path, [0])[:0] + [tmp_path / f"{n}.tif" for n in names])
    for f in files:
        f.write_bytes(b"x")
    plan = ab_pairs(files, "_a", "_b", None, tmp_path)
    assert _as_names(plan) == {0: ("run_00_a.tif", "run_00_b.tif"),
                               2: ("run_02_a.tif", "run_02_b.tif")}
    assert "run_01_b.tif missing" in plan.gaps[1]
    assert "run_03_b.tif has no _a partner" in plan.gaps[3]


def test_listed_pairs_keep_their_positions(tmp_path):
    _frames(tmp_path, [0, 1, 3])
    plan = listed_pairs([["frame_000.tif", "frame_001.tif"], ["frame_002.tif", "frame_003.tif"],
                         ["frame_003.tif", "frame_001.tif"]], tmp_path)
    assert sorted(_as_names(plan)) == [0, 2] and "frame_002.tif missing" in plan.gaps[1]


def test_fingerprints_tell_a_changed_file_from_a_copied_one(tmp_path):
    a, b = _frames(tmp_path, [0, 1])
    recorded = {"a": fingerprint(a), "b": fingerprint(b)}
    pair = ImagePair(0, a, b)
    assert changed_since(recorded, pair) is None
    os.utime(a, ns=(1, 1))  # touched (a copy): same content, other time
    assert same_file(recorded["a"], a) and changed_since(recorded, pair) is None
    a.write_bytes(b"frame 9")  # same size, other content
    assert not same_file(recorded["a"], a)
    assert "frame_000.tif" in changed_since(recorded, pair)
    assert "other" not in (changed_since(recorded, ImagePair(0, b, a)) or "other")
    assert "older plenocl" in changed_since({}, pair)
    # several cameras: the changed one named ("camera 2's it was made from" before)
    (tmp_path / "two").mkdir()
    c2 = _frames(tmp_path / "two", (0, 1), "g_{:03d}.tif")
    two = {"a": fingerprint(a), "b": fingerprint(b),
           "cameras": [{"a": fingerprint(c2[0]), "b": fingerprint(c2[1])}]}
    c2[1].write_bytes(b"changed since")
    assert changed_since(two, ImagePair(0, a, b, ((c2[0], c2[1]),))).startswith(
        "camera 2: it was made from g_001.tif")


def test_a_pairs_frames_are_found_where_its_pattern_reached(tmp_path):
    """``sources_present``: a finished pair's frames, by name, size and content, in each
    camera's folder or a folder below it (a pattern such as ``sub/*.tif``); a frame
    deleted or changed since, or a camera more or less, is not."""
    from plenocl.batch.pairing import fingerprint, sources_present

    for cam in ("one", "two"):
        (tmp_path / cam / "sub").mkdir(parents=True)
        for k in (1, 2):
            (tmp_path / cam / "sub" / f"f_{k:03d}.tif").write_bytes(bytes([k]) * 16)
    recorded = {tag: fingerprint(tmp_path / "one" / "sub" / f"f_{k:03d}.tif")
                for tag, k in (("a", 1), ("b", 2))}
    recorded["cameras"] = [{tag: fingerprint(tmp_path / "two" / "sub" / f"f_{k:03d}.tif")
                            for tag, k in (("a", 1), ("b", 2))}]
    folders = [tmp_path / "one", tmp_path / "two"]
    assert sources_present(recorded, folders)
    assert not sources_present(recorded, folders[:1])
    (tmp_path / "two" / "sub" / "f_002.tif").write_bytes(bytes([9]) * 16)  # changed
    assert not sources_present(recorded, folders)
    (tmp_path / "two" / "sub" / "f_002.tif").unlink()
    assert not sources_present(recorded, folders)


@pytest.mark.parametrize("pairing", ["sequence", "sliding", "ab"])
def test_several_cameras_pair_the_same_frame_numbers_whatever_each_folder_starts_at(
        tmp_path, pairing):
    """Camera 1 holds frames 0-5, camera 2 frames 2-7: pair k is the same frame numbers
    in both (counted from the lowest frame of any camera), the pairs camera 2 lacks are
    gaps naming it; counted per folder, camera 2's first pair (frames 2 + 3) was matched
    with camera 1's first (frames 0 + 1), of other instants."""
    from plenocl.batch import load_experiment
    from plenocl.batch.config import image_pairs

    pattern = "frame_{:03d}_a.tif" if pairing == "ab" else "frame_{:03d}.tif"
    for c, numbers in ((1, range(6)), (2, range(2, 8))):
        (tmp_path / f"raw{c}").mkdir()
        _frames(tmp_path / f"raw{c}", numbers, pattern)
        if pairing == "ab":
            _frames(tmp_path / f"raw{c}", numbers, "frame_{:03d}_b.tif")
        (tmp_path / f"cam{c}.toml").write_text("")
    (tmp_path / "experiment.toml").write_text(
        "[[cameras]]\nfile = 'cam1.toml'\nfolder = 'raw1'\n"
        "[[cameras]]\nfile = 'cam2.toml'\nfolder = 'raw2'\n"
        "[grid]\nz_mm = [-1.0, 1.0]\n"
        f"[images]\npattern = 'frame_*.tif'\npairing = '{pairing}'\ndt_s = 1e-3\n")
    plan = image_pairs(load_experiment(tmp_path / "experiment.toml"))
    assert plan.pairs
    for pair in plan.pairs:
        (a2, b2), = pair.others
        assert (frame_number(pair.a), frame_number(pair.b)) == \
            (frame_number(a2), frame_number(b2)), (pair.index, pair.a.name, a2.name)
    first = plan.pairs[0]
    assert frame_number(first.a) == 2 and first.index == (2 if pairing != "sequence" else 1)
    assert all("camera 2" in why for why in plan.gaps.values()) and 0 in plan.gaps
