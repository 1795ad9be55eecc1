"""One settings object for a pair (PairSettings): its parts, its documents, its defaults."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

from plenocl import (
    MTESettings,
    PairSettings,
    PIVSettings,
    ReconstructionSettings,
    piv3d,
    process_pair,
    reconstruct,
)
from plenocl.cli.main import build_parser
from plenocl.cli.volume import reconstruction_settings
from plenocl.io.tomlfile import read_toml, write_toml
from plenocl.options import NONE
from plenocl.piv.imagefit import ImageFitSettings
from plenocl.reconstruction import (
    COARSE_ITERATIONS,
    DEFAULTS,
    FINE_DEFAULTS,
    SUPERSAMPLE,
    SUPPORT,
)

CHANGED = PairSettings(
    reconstruction=ReconstructionSettings("mart", 12, 0.6, threshold=3.0, ratio_floor=0.2,
                                          supersample=2, mart_blocks=3),
    piv=PIVSettings(windows=(32, (24, 16, 16)), overlaps=0.5, weighting=0.5,
                    correlation="fft", min_peak_ratio=1.3),
    mte=MTESettings(cycles=1, iterations=4, combine="mean", smooth=0.5),
    particles=False, image_fit=ImageFitSettings(rays=200, blur_px=1.1))


#: Options set to None where their default is not: a dict holds them, a TOML file cannot.
NONES = PairSettings(reconstruction=ReconstructionSettings(background=None),
                     piv=PIVSettings(weighting=None), image_fit=None)


def test_to_dict_and_from_dict_round_trip_options_set_to_none():
    assert PairSettings.from_dict(NONES.to_dict()) == NONES


def test_options_set_to_none_round_trip_through_a_toml_file(tmp_path):
    """TOML has no null: ``"none"`` stands for ``None`` (``weighting = "none"``: top-hat
    windows), so a file can ask for what a dict can."""
    doc = NONES.to_dict(none=NONE)
    assert doc["piv"]["weighting"] == "none" and doc["reconstruction"]["background"] == "none"
    write_toml(tmp_path / "s.toml", doc)
    got = PairSettings.from_dict(read_toml(tmp_path / "s.toml"))
    assert got == NONES and got.piv.weighting is None


@pytest.mark.parametrize("settings", [PairSettings(), CHANGED,
                                      PairSettings(image_fit=None, particles=True)])
def test_to_dict_and_from_dict_round_trip(settings, tmp_path):
    assert PairSettings.from_dict(settings.to_dict()) == settings
    # through a TOML file (which holds no None: those keys are left out, their defaults)
    doc = {part: {k: v for k, v in table.items() if v is not None}
           for part, table in settings.to_dict().items()}
    write_toml(tmp_path / "s.toml", doc)
    assert PairSettings.from_dict(read_toml(tmp_path / "s.toml")) == settings


def test_switches_and_lists_are_read_as_the_objects_hold_them():
    doc = {"particles": False, "image_fit": False, "piv": {"windows": [48, [32, 24, 24]]}}
    got = PairSettings.from_dict(doc)
    assert got.particles is False and got.image_fit is None
    assert got.piv.windows == (48, (32, 24, 24))
    assert PairSettings.from_dict({"image_fit": {"rays": 100}}).image_fit.rays == 100
    assert PairSettings.from_dict({"image_fit": {"enabled": False}}).image_fit is None
    assert PairSettings(image_fit=True) == PairSettings()


@pytest.mark.parametrize("doc, message", [
    ({"pivv": {}}, r"e.toml: unknown section\(s\) \['pivv'\]; the pair settings are "
                   r"\['reconstruction', 'piv', 'mte', 'particles', 'image_fit'\]"),
    ({"piv": {"window": 3}}, r"\[piv\]: unknown key\(s\) \['window'\]; it takes "
                             r"\['windows', 'overlaps'"),
    ({"mte": {"cycle": 1}}, r"\[mte\]: unknown key\(s\) \['cycle'\]; it takes \['cycles'"),
    ({"image_fit": {"ray": 1}}, r"\[image_fit\]: unknown key\(s\) \['ray'\]; it takes "
                                r"\['enabled', 'rays'"),
    ({"particles": {"on": True}}, r"\[particles\]: unknown key\(s\) \['on'\]"),
    ({"mte": {"cycles": -1}}, r"\[mte\]: MTE cycles must be a non-negative integer"),
    ({"reconstruction": {"supersample": 9}}, r"\[reconstruction\]: supersample must be"),
    ({"reconstruction": {"method": "art"}}, r"\[reconstruction\]: method must be"),
    ({"piv": {"deform_order": 2}}, r"\[piv\]: deform_order must be 1"),
    ({"reconstruction": {"iterations": True}},
     r"\[reconstruction\]: iterations must be a non-negative integer, got True"),
    ({"reconstruction": {"coarse_iterations": 2.5}},
     r"\[reconstruction\]: coarse_iterations must be a non-negative integer, got 2.5"),
    ({"reconstruction": {"relax": "1"}}, r"\[reconstruction\]: relax must be a number, got"),
    ({"reconstruction": {"threshold": "5"}},
     r"\[reconstruction\]: threshold must be a number or None, got '5'"),
    ({"piv": {"final_iterations": 1.5}}, r"\[piv\]: final_iterations must be an integer >= 1"),
    ({"piv": {"final_iterations": 0}}, r"\[piv\]: final_iterations must be an integer >= 1"),
    ({"piv": {"windows": [0]}}, r"\[piv\]: window of pass 1 must be integers >= 8"),
    ({"piv": {"windows": [16, 8], "overlaps": [0.5, 0.5, 0.5]}},
     r"\[piv\]: overlaps \(3 values\) must match windows \(2 passes\)"),
    ({"piv": {"windows": [16], "overlaps": 1.0}}, r"\[piv\]: overlap of pass 1 must be"),
    ({"piv": {"overlaps": [0.5, 0.75]}}, r"\[piv\]: overlaps \(0.5, 0.75\) gives one per "
                                         r"pass, but without windows"),
    ({"piv": {"workers": 0}}, r"\[piv\]: workers must be -1 \(all cores\)"),
    ({"piv": {"fft": "fftpack"}}, r"\[piv\]: fft must be one of \('fftw', 'scipy', 'device'\)"),
    ({"image_fit": {"rays": 8}}, r"\[image_fit\]: ImageFitSettings.rays must be"),
    ({"particles": "yes"}, r"\[particles\] enabled must be true or false"),
    ({"mte": 3}, r"\[mte\] must be a table"),
])
def test_unknown_keys_and_bad_values_are_named(doc, message):
    with pytest.raises(ValueError, match=message):
        PairSettings.from_dict(doc, source="e.toml")


def test_a_whole_float_count_is_that_count():
    """``iterations = 3.0`` (a file's float) is 3 iterations, recorded as 3: the same
    settings and record as ``iterations = 3`` (it failed inside ``range`` before)."""
    as_float = PairSettings.from_dict({"reconstruction": {"iterations": 3.0,
                                                          "early_iterations": 2.0}})
    as_int = PairSettings.from_dict({"reconstruction": {"iterations": 3,
                                                        "early_iterations": 2}})
    assert as_float == as_int and as_float.to_dict() == as_int.to_dict()
    assert type(as_float.reconstruction.iterations) is int
    assert ReconstructionSettings(supersample=2.0) == ReconstructionSettings(supersample=2)
    from plenocl.pipeline import MTESettings, TrackSettings
    from plenocl.piv import PIVSettings
    from plenocl.piv.imagefit import ImageFitSettings

    for cls, counts in ((MTESettings, {"cycles": 1, "iterations": 2}),
                        (TrackSettings, {"min_length": 3, "window": 5, "refits": 1}),
                        (ImageFitSettings, {"rays": 400, "iterations": 2}),
                        (PIVSettings, {"final_iterations": 2})):
        made = cls(**{k: float(v) for k, v in counts.items()})
        assert made == cls(**counts), cls.__name__
        assert all(type(getattr(made, k)) is int for k in counts), cls.__name__
        with pytest.raises(ValueError, match="integer"):
            cls(**{next(iter(counts)): 2.5})


def _cli_settings(*options: str) -> ReconstructionSettings:
    """``plenocl reconstruct``'s reconstruction with these options."""
    args = build_parser().parse_args(["reconstruct", "r.tif", "--camera", "c", "--grid",
                                      "g", "--out", "v.npz", *options])
    return reconstruction_settings(args)


def _reconstruct_settings(monkeypatch, **keywords) -> ReconstructionSettings:
    """The settings :func:`plenocl.reconstruct` runs with these keywords."""
    module = sys.modules["plenocl.reconstruction.reconstruct"]  # not the function
    seen = []
    monkeypatch.setattr(module, "run_reconstruction",
                        lambda image, proj, settings, *rest: seen.append(settings) or (0, 0))
    reconstruct(None, None, **keywords)
    return seen[0]


def test_one_default_reconstruction(monkeypatch):
    """One default for every entry point: plenocl.reconstruct with no options,
    process_pair (its settings, an empty document) and plenocl reconstruct run the same
    reconstruction, coarse-to-fine MLEM on 3 x 3 sub-voxels (docs/design.md §6.5)."""
    rec = ReconstructionSettings()
    assert _reconstruct_settings(monkeypatch) == rec
    assert PairSettings().reconstruction == rec
    assert PairSettings.from_dict({}).reconstruction == rec
    assert PairSettings.from_dict({"reconstruction": {}}).reconstruction == rec
    assert _cli_settings() == rec
    assert (rec.method, rec.supersample, rec.coarse_iterations, rec.support, rec.iterations,
            rec.relax) == ("mlem", SUPERSAMPLE, COARSE_ITERATIONS, SUPPORT,
                           *FINE_DEFAULTS) == ("mlem", 3, 4, 0.01, 7, 1.5)
    assert (rec.background, rec.start, rec.total_iterations) == ("median", "uniform", 11)
    # the voxels themselves: the method's own iterations, everywhere alike
    one = ReconstructionSettings(supersample=1)
    assert (one.iterations, one.relax, one.coarse_iterations) == (*DEFAULTS["mlem"], 0)
    assert (one.iterations, one.relax) == (30, 1.0) and one.total_iterations == 30
    assert _reconstruct_settings(monkeypatch, supersample=1) == one
    assert _cli_settings("--supersample", "1") == one
    assert PairSettings.from_dict({"reconstruction": {"supersample": 1}}).reconstruction == one


def test_defaults_agree():
    """One default per option: the pair's reconstruction on 3 x 3 sub-voxels, MTE off,
    the particle refinement and the image fit on; an empty document is the defaults, as
    is the CLI's reconstruction; each option given replaces its own default only."""
    pair = PairSettings()
    assert pair.reconstruction.supersample == SUPERSAMPLE == 3
    assert pair.mte == MTESettings() and MTESettings().cycles == 0
    assert pair.particles and pair.image_fit == ImageFitSettings()
    assert pair.piv == PIVSettings()
    assert PairSettings.from_dict({}) == pair
    assert PairSettings.from_dict({"reconstruction": {"iterations": 7}}) == pair
    rec = pair.reconstruction
    assert (rec.coarse_iterations, rec.support, rec.iterations, rec.relax) == (
        COARSE_ITERATIONS, SUPPORT, *FINE_DEFAULTS) == (4, 0.01, 7, 1.5)
    assert _cli_settings() == rec
    # the voxels themselves, or another method, keep the method's own iterations; SMART
    # and MART smooth the image by 1 px
    one = PairSettings.from_dict({"reconstruction": {"supersample": 1}}).reconstruction
    assert (one.iterations, one.relax) == DEFAULTS["mlem"] and one.coarse_iterations == 0
    for method in ("mart", "smart"):
        other = PairSettings.from_dict({"reconstruction": {"method": method}}).reconstruction
        assert other == ReconstructionSettings(method=method)
        assert (other.iterations, other.relax) == DEFAULTS[method]
        assert (other.supersample, other.coarse_iterations, other.smooth_px) == (3, 4, 1.0)
        assert _cli_settings("--method", method) == other
        assert _cli_settings("--method", method, "--smooth-px", "0").smooth_px == 0
    assert rec.smooth_px is None  # MLEM: no smoothing, its record as before
    given = PairSettings.from_dict({"reconstruction": {"relax": 1.0}}).reconstruction
    assert (given.relax, given.iterations) == (1.0, 7)
    assert ReconstructionSettings(relax=1.0) == given
    assert (ReconstructionSettings(iterations=30).relax, _cli_settings(
        "--iterations", "30").relax) == (1.5, 1.5)
    # no coarse iterations: MLEM's own on the sub-voxels
    flat = ReconstructionSettings(coarse_iterations=0)
    assert (flat.supersample, flat.iterations, flat.relax) == (3, *DEFAULTS["mlem"])
    assert _cli_settings("--coarse-iterations", "0") == flat
    assert _cli_settings("--supersample", "1") == one
    # the document's "none" (TOML) is the default too
    assert PairSettings.from_dict({"reconstruction": {"iterations": NONE, "relax": NONE,
                                                      "coarse_iterations": NONE}}) == pair


def test_keywords_build_settings_and_conflicts_are_refused():
    vol = np.random.default_rng(0).random((16, 16, 16)).astype(np.float32)
    with pytest.raises(TypeError, match=r"both settings and keyword\(s\) \['windows'\]"):
        piv3d(vol, vol, PIVSettings(windows=(16,)), windows=(8,))
    with pytest.raises(TypeError, match=r"unknown keyword\(s\) \['window'\]"):
        piv3d(vol, vol, window=16)
    with pytest.raises(ValueError, match="deform_order must be"):
        piv3d(vol, vol, deform_order=2)
    settings = ReconstructionSettings("smart", 5)
    with pytest.raises(TypeError, match=r"both settings and keyword\(s\) \['method'\]"):
        reconstruct(None, None, "mart", settings=settings)
    with pytest.raises(TypeError, match=r"both settings and keyword\(s\) \['crop'\]"):
        reconstruct(None, None, settings=settings, crop=False)
    with pytest.raises(TypeError, match="takes a ReconstructionSettings"):
        reconstruct(None, None, settings=PIVSettings())
    # the old call process_pair(..., settings=ReconstructionSettings(...)) says the new one
    with pytest.raises(TypeError, match=r"takes a PairSettings, got ReconstructionSettings; "
                                        r"pass it as reconstruction="):
        process_pair(None, None, None, settings=settings)
    assert dataclasses.replace(settings, crop=False).crop is False
