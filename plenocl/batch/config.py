"""The experiment file of ``plenocl run``: its sections, their checks, the image pairs.

The file names the camera (a calibrated camera file or a preset, calibrated from a white
image first if one is given), the grid, the images and how they pair, ``dt``, the
reconstruction and PIV settings and the outputs. Every key is checked before any work
starts: an unknown section or key, or a bad value, is an error naming it.

Example::

    [camera]
    file = "camera_calibrated.toml"     # or preset = "synthetic"; with white = "white.tif"
                                         # the camera is calibrated from that image first
    [grid]
    z_mm = [-2.0, 2.0]                   # Grid.for_camera; or file = "grid.toml"
    [images]
    folder = "raw"
    pattern = "frame_*.tif"
    pairing = "sequence"                 # by frame number: 0+1, 2+3, ...; "sliding": 0+1,
                                         # 1+2, ...; "ab": files with a_suffix / b_suffix;
                                         # "list": pairs = [["a.tif", "b.tif"], ...]
    first_frame = 0                      # optional: the number pairs count from (default:
                                         # the lowest found; batch/pairing.py)
    channel = "g"                        # optional, for colour frames: r, g, b, luminance
    dark = "dark.tif"                    # optional dark frame, subtracted (white image too)
    flat = "flat.tif"                    # optional flat field, divided out
    dt_s = 175e-6                        # between the two exposures of a pair (s; outside
                                         # 0.1 µs to 1 s refused unless force_dt = true)
    pair_interval_s = 0.01               # between successive pairs: the time axis
    [reconstruction]                     # every ReconstructionSettings option
    method = "mlem"
    iterations = 7                       # on the sub-voxels, after
    coarse_iterations = 4                # iterations on the voxels (docs/design.md §6.5)
    relax = 1.5                          # MLEM over-relaxed, 0 < relax < 2
    supersample = 3                      # lateral sub-voxels per voxel (1: the voxels,
                                         # depth about 3x worse; docs/design.md §6.4)
    [piv]                                # every PIVSettings option, and ensemble
    windows = [48, 32, 24]               # optional: fitted to the volume by default
    ensemble = false                     # also the ensemble-correlation mean field (keeps
                                         # each pair's volumes beside its field)
    [mte]                                # motion-tracking enhancement (MTESettings)
    cycles = 0
    [particles]                          # the particle refinement of the field
    enabled = true
    [image_fit]                          # those particles fitted to the raw images first
    enabled = true                       # and any ImageFitSettings option
    [output]
    folder = "results"
    vti = false                          # also a ParaView .vti per pair
    formats = []                         # more copies of each field beside its .npz:
                                         # "vti", "h5", "dat" (Tecplot ASCII), "csv"

Several cameras (docs/design.md §6.7) replace ``[camera]`` by one ``[[cameras]]`` table
each, naming its camera (a file whose ``[pose]`` places it in the world, or a preset),
an optional white image and the folder of its images; ``[images]`` pairs every folder by
the same rule, and a pair is made where every camera has it, matched by its frame
numbers (:func:`plenocl.batch.pairing.matched_pairs`)::

    [[cameras]]
    file = "cam1.toml"
    white = "white_1.tif"                # optional, as [camera] white
    folder = "raw/cam1"
    [[cameras]]
    file = "cam2.toml"
    folder = "raw/cam2"
    [grid]
    file = "grid.toml"                   # the world grid every camera sees

A ``[tracking]`` section (:mod:`.trackconfig`) makes the run track the frames as one
time-resolved recording instead of processing pairs.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ..io.tomlfile import read_toml
from ..pipeline.settings import PARTS, PairSettings
from ..units import check_dt
from .layout import COPY_SUFFIXES
from .pairing import (
    PAIRINGS,
    PairPlan,
    ab_pairs,
    common_first_frame,
    listed_pairs,
    matched_pairs,
    numbered_pairs,
)
from .trackconfig import TrackingOptions, check_images_for_tracking, tracking_options

#: Keys each section of an experiment file may hold, with their defaults (None: required
#: or optional without default), besides the pair's settings (:data:`PAIR_SECTIONS`).
SECTIONS = {
    "camera": {"file": None, "preset": None, "white": None},
    "grid": {"file": None, "z_mm": None, "voxel_mm": None, "depth_voxel_mm": None,
             "fraction": 1.0},
    "images": {"folder": ".", "pattern": "*.tif", "pairing": "sequence", "a_suffix": "_a",
               "b_suffix": "_b", "dt_s": None, "pair_interval_s": None, "pairs": None,
               "first_frame": None, "force_dt": False, "channel": None, "dark": None,
               "flat": None},
    "piv": {"ensemble": False},
    "output": {"folder": "results", "vti": False, "formats": []},
}


#: Keys of each ``[[cameras]]`` table (several cameras): its camera (a file placed by its
#: ``[pose]``, or a preset), an optional white image, and the folder of its images.
CAMERA_KEYS = {"file": None, "preset": None, "white": None, "folder": None}
#: The array of tables of several cameras.
CAMERAS = "cameras"


@dataclass(frozen=True)
class Experiment:
    """A validated experiment file: every section's values with defaults filled in, the
    folder relative paths are resolved against, and each pair's settings; with an
    enabled ``[tracking]`` section, its options (the run tracks the frames instead);
    with several cameras, each ``[[cameras]]`` table (defaults filled in; empty: one
    camera, ``[camera]``)."""

    sections: dict = field(compare=False)
    base: Path = Path(".")
    pair: PairSettings = field(default_factory=PairSettings)
    tracking: TrackingOptions | None = None
    cameras: tuple[dict, ...] = field(default=(), compare=False)

    def __getitem__(self, section: str) -> dict:
        return self.sections[section]


#: The sections that make each pair's :class:`~plenocl.pipeline.PairSettings`.
PAIR_SECTIONS = PARTS
#: The section of a time-resolved recording's tracking (:mod:`.trackconfig`).
TRACKING = "tracking"


def load_experiment(path: str | Path) -> Experiment:
    """Read and check an experiment file; every unknown or bad key is an error naming it."""
    path = Path(path)
    doc = read_toml(path)
    unknown = set(doc) - set(SECTIONS) - set(PAIR_SECTIONS) - {TRACKING, CAMERAS}
    if unknown:
        raise ValueError(f"{path}: unknown section(s) {sorted(unknown)}; the sections are "
                         f"{list(dict.fromkeys([*SECTIONS, *PAIR_SECTIONS, TRACKING]))} "
                         f"and [[{CAMERAS}]]")
    batch, pair = _split(doc)
    sections = {}
    for name, defaults in SECTIONS.items():
        given = batch.get(name, {})
        bad = set(given) - set(defaults)
        if bad:
            raise ValueError(f"{path}: unknown key(s) {sorted(bad)} in [{name}]; it takes "
                             f"{list(defaults)}")
        sections[name] = {**defaults, **given}
    table = doc.get(TRACKING)
    cameras = _cameras(doc, path, isinstance(table, Mapping) and table.get("enabled", True)
                       is not False)
    tracking = tracking_options(table, pair, sections["images"], path)
    _check(sections, path, tracking is not None, several=bool(cameras))
    # the weights named, so that each pair's record says which made its volumes
    settings = PairSettings.from_dict(pair, source=str(path)).with_named_weights()
    return Experiment(sections, path.parent, settings, tracking, cameras)


def _cameras(doc: dict, path: Path, tracking: bool) -> tuple[dict, ...]:
    """The ``[[cameras]]`` tables checked, defaults filled in (``()``: one camera)."""
    tables = doc.get(CAMERAS)
    if tables is None:
        return ()
    how = ("several cameras take one [[cameras]] table each (file or preset, folder, "
           "optional white)")
    if not (isinstance(tables, list) and len(tables) >= 2
            and all(isinstance(t, Mapping) for t in tables)):
        raise ValueError(f"{path}: {how}, at least two; one camera is [camera]")
    if "camera" in doc:
        raise ValueError(f"{path}: [camera] and [[cameras]] together: {how}; leave out "
                         "[camera]")
    if tracking:
        raise ValueError(f"{path}: [tracking] follows one camera's recording; track "
                         "several cameras' frames with plenocl.track([frames_1, ...], "
                         "[projector_1, ...], dt) (docs/usage.md)")
    out = []
    for k, table in enumerate(tables, start=1):
        bad = set(table) - set(CAMERA_KEYS)
        if bad:
            raise ValueError(f"{path}: unknown key(s) {sorted(bad)} in [[cameras]] "
                             f"{k}; it takes {list(CAMERA_KEYS)}")
        cam = {**CAMERA_KEYS, **table}
        if len([key for key in ("file", "preset") if cam[key]]) != 1 \
                or not isinstance(cam["folder"], str):
            raise ValueError(f"{path}: [[cameras]] {k} needs exactly one of file or preset, "
                             "and the folder of its images")
        out.append(cam)
    if "folder" in doc.get("images", {}):
        raise ValueError(f"{path}: [images] folder with [[cameras]]: each camera's images "
                         "are in the folder its [[cameras]] table names; leave it out")
    return tuple(out)


def _split(doc: dict) -> tuple[dict, dict]:
    """The file's batch sections and its pair settings' sections (``[piv]`` holds both:
    ``ensemble`` is the batch's)."""
    batch = {k: v for k, v in doc.items() if k in SECTIONS and k not in PAIR_SECTIONS}
    pair = {k: v for k, v in doc.items() if k in PAIR_SECTIONS}
    piv = pair.get("piv")
    if isinstance(piv, Mapping):
        batch["piv"] = {k: v for k, v in piv.items() if k in SECTIONS["piv"]}
        pair["piv"] = {k: v for k, v in piv.items() if k not in SECTIONS["piv"]}
    return batch, pair


def _check(s: dict, path: Path, tracking: bool = False, several: bool = False) -> None:
    """Every section's values (``tracking``: the pair keys refused instead of needed;
    ``several``: the cameras are ``[[cameras]]``'s, checked apart)."""
    cam = [k for k in ("file", "preset") if s["camera"][k]]
    if not several and len(cam) != 1:
        raise ValueError(f"{path}: [camera] needs exactly one of file or preset (the "
                         f"camera, calibrated from `white` if given), got {cam or 'none'}")
    if bool(s["grid"]["file"]) == bool(s["grid"]["z_mm"]):
        raise ValueError(f"{path}: [grid] needs exactly one of file or z_mm")
    _check_pairing(s["images"], path)
    _check_frames(s["images"], path)
    for section, key in (("output", "vti"), ("piv", "ensemble")):
        if not isinstance(s[section][key], bool):
            raise ValueError(f"{path}: [{section}] {key} must be true or false, got "
                             f"{s[section][key]!r}")
    formats = output_formats(s["output"], path)
    if tracking:
        check_images_for_tracking(s["images"], s["piv"]["ensemble"], path, formats)
    else:
        _check_times(s["images"], path)


#: What ``[output] formats`` may list: the field formats written beside each ``.npz``.
EXTRA_FORMATS = tuple(suffix.lstrip(".") for suffix in COPY_SUFFIXES)


def output_formats(output: dict, path: Path | str = "the experiment file") -> tuple[str, ...]:
    """The suffixes (``".vti"``, ...) each field is written in beside its ``.npz``:
    ``[output] formats``, with ``vti = true`` as ``"vti"``; a ``ValueError`` for a name
    that is not one of :data:`EXTRA_FORMATS`."""
    names = output["formats"]
    if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
        raise ValueError(f"{path}: [output] formats must be a list of format names, e.g. "
                         f"[\"dat\", \"csv\"], got {names!r}")
    names = [n.lower().lstrip(".") for n in names] + (["vti"] if output["vti"] else [])
    bad = [n for n in names if n not in EXTRA_FORMATS]
    if bad:
        raise ValueError(f"{path}: [output] formats: unknown format(s) {bad}; it takes "
                         f"{list(EXTRA_FORMATS)} (each field's .npz is always written)")
    return tuple(f".{n}" for n in dict.fromkeys(names))


def _check_times(img: dict, path: Path) -> None:
    """The pairs' ``dt_s`` (needed) and ``pair_interval_s``."""
    dt = img["dt_s"]
    if not isinstance(dt, (int, float)) or isinstance(dt, bool):
        raise ValueError(f"{path}: [images] dt_s must be the time between the exposures in "
                         f"seconds (e.g. 175e-6), got {dt!r}")
    check_dt(dt, f"{path}: [images] dt_s", img["force_dt"], flag="[images] force_dt = true")
    interval = img["pair_interval_s"]
    if interval is not None and not (isinstance(interval, (int, float)) and interval > 0):
        raise ValueError(f"{path}: [images] pair_interval_s must be the time between "
                         f"successive pairs in seconds, got {interval!r}")


def _check_frames(img: dict, path: Path) -> None:
    from ..io.files import CHANNELS

    if not isinstance(img["force_dt"], bool):
        raise ValueError(f"{path}: [images] force_dt must be true or false")
    if img["channel"] is not None and img["channel"] not in CHANNELS:
        raise ValueError(f"{path}: [images] channel must be one of {CHANNELS}, got "
                         f"{img['channel']!r}")
    for key in ("dark", "flat"):
        name = img[key]
        if name is not None and not (path.parent / name).is_file():
            raise ValueError(f"{path}: [images] {key} = {name!r}: no such file (relative "
                             "to the experiment file's folder)")


def _check_pairing(img: dict, path: Path) -> None:
    if img["pairing"] not in PAIRINGS:
        raise ValueError(f"{path}: [images] pairing must be one of {PAIRINGS}, got "
                         f"{img['pairing']!r}")
    listed = img["pairs"]
    if (img["pairing"] == "list") != (listed is not None):
        raise ValueError(f"{path}: [images] pairs (a list of [a, b] file names) goes with "
                         f"pairing = \"list\" and only with it; got pairing "
                         f"{img['pairing']!r} and {'no ' if listed is None else ''}pairs")
    if listed is not None and not (isinstance(listed, list) and listed and all(
            isinstance(p, list) and len(p) == 2 and all(isinstance(f, str) for f in p)
            for p in listed)):
        raise ValueError(f"{path}: [images] pairs must be a list of [a, b] file names, "
                         f"e.g. [[\"run1_a.tif\", \"run1_b.tif\"]], got {listed!r}")
    first = img["first_frame"]
    if first is not None and not (isinstance(first, int) and not isinstance(first, bool)
                                  and first >= 0):
        raise ValueError(f"{path}: [images] first_frame must be a frame number (an integer "
                         f">= 0), got {first!r}")


def image_pairs(exp: Experiment) -> PairPlan:
    """The image pairs of the experiment, by frame number (:mod:`.pairing`), and its gaps.

    Raises
    ------
    ValueError
        When no pair can be made (naming the folder, pattern and pairing; several
        cameras: no pair that every camera has, naming each pair's gap), or when frame
        names do not give frame numbers.
    """
    if not exp.cameras:
        return _folder_pairs(exp, exp["images"]["folder"])
    first = exp["images"]["first_frame"]
    if first is None:  # one count for every camera: pair k is the same instants in each
        first = common_first_frame([_folder_files(exp, cam["folder"]) for cam in exp.cameras],
                                   exp["images"])
    plan = matched_pairs([_folder_pairs(exp, cam["folder"], first) for cam in exp.cameras])
    if not plan.pairs:
        gaps = "; ".join(f"pair {k}: {why}" for k, why in plan.gaps.items())
        raise ValueError(f"no image pair that every camera has (pairs are matched by frame "
                         f"number): {gaps}")
    return plan


def image_folders(exp: Experiment) -> list[Path]:
    """The folders the run's frames come from: ``[images] folder``, or each camera's
    (``[[cameras]] folder``) in their order."""
    names = [cam["folder"] for cam in exp.cameras] or [exp["images"]["folder"]]
    return [exp.base / name for name in names]


def _folder_files(exp: Experiment, name: str) -> list[Path]:
    """The files of one folder that ``[images] pattern`` matches, sorted."""
    return sorted(f for f in (exp.base / name).glob(exp["images"]["pattern"]) if f.is_file())


def _folder_pairs(exp: Experiment, name: str, first_frame: int | None = None) -> PairPlan:
    """The pairs of one folder of images (:func:`image_pairs`), counted from
    ``first_frame`` (``None``: ``[images] first_frame``, else the folder's lowest)."""
    img = exp["images"]
    folder = exp.base / name
    files = _folder_files(exp, name)
    first = img["first_frame"] if first_frame is None else first_frame
    if img["pairing"] == "list":
        plan = listed_pairs(img["pairs"], folder)
    elif not files:
        plan = PairPlan([])
    elif img["pairing"] == "ab":
        plan = ab_pairs(files, img["a_suffix"], img["b_suffix"], first, folder)
    else:
        plan = numbered_pairs(files, img["pairing"], first, folder)
    if not plan.pairs:
        raise ValueError(f"no image pairs in {folder} matching {img['pattern']!r} "
                         f"(pairing {img['pairing']!r})"
                         + (f": {'; '.join(plan.gaps.values())}" if plan.gaps else ""))
    return plan
