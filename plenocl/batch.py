"""A configured, resumable batch of image pairs: ``plenocl run experiment.toml``.

The experiment file names the camera (a calibrated camera file, a preset, or a white
image to calibrate from), the grid, the images and how they pair, ``dt``, and the
reconstruction and PIV settings. Every key is checked before any work starts. Each pair
goes through :func:`plenocl.process_pair` with one projector, and its vector field is
written atomically to ``OUT/pairs/pair_NNNNN.npz``: a rerun skips the pairs already
written, and a pair that fails (an unreadable or wrong-sized image, NaN) is logged with
its reason while the run goes on. The configuration actually used (defaults filled in,
the plenocl version) is written beside the results, and ``summary.json`` says what was
done. (Issue 16: the time-series store, ensemble statistics and Dask are to come.)

Example::

    [camera]
    file = "camera_calibrated.toml"     # or preset = "synthetic"; with white = "white.tif"
                                         # the camera is calibrated from that image first
    [grid]
    z_mm = [-2.0, 2.0]                   # Grid.for_camera; or file = "grid.toml"
    [images]
    folder = "raw"
    pattern = "frame_*.tif"              # sorted by name
    pairing = "sequence"                 # 1+2, 3+4, ...; "sliding": 1+2, 2+3, ...;
                                         # "ab": files with a_suffix / b_suffix
    dt_s = 175e-6
    [reconstruction]
    method = "mlem"
    iterations = 30
    [piv]
    windows = [48, 32, 24]               # optional: fitted to the volume by default
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .atomic import atomic_path
from .tomlfile import read_toml, write_toml

#: Keys each section of an experiment file may hold, with their defaults (None: required
#: or optional without default).
SECTIONS = {
    "camera": {"file": None, "preset": None, "white": None},
    "grid": {"file": None, "z_mm": None, "voxel_mm": None, "depth_voxel_mm": None,
             "fraction": 1.0},
    "images": {"folder": ".", "pattern": "*.tif", "pairing": "sequence", "a_suffix": "_a",
               "b_suffix": "_b", "dt_s": None},
    "reconstruction": {"method": "mlem", "iterations": None, "relax": None,
                       "background": "median", "threshold": None},
    "piv": {"windows": None},
    "output": {"folder": "results"},
}
PAIRINGS = ("sequence", "sliding", "ab")


@dataclass(frozen=True)
class Experiment:
    """A validated experiment file: every section's values with defaults filled in, and
    the folder relative paths are resolved against."""

    sections: dict = field(compare=False)
    base: Path = Path(".")

    def __getitem__(self, section: str) -> dict:
        return self.sections[section]


def load_experiment(path: str | Path) -> Experiment:
    """Read and check an experiment file; every unknown or bad key is an error naming it."""
    path = Path(path)
    doc = read_toml(path)
    unknown = set(doc) - set(SECTIONS)
    if unknown:
        raise ValueError(f"{path}: unknown section(s) {sorted(unknown)}; the sections are "
                         f"{list(SECTIONS)}")
    sections = {}
    for name, defaults in SECTIONS.items():
        given = doc.get(name, {})
        bad = set(given) - set(defaults)
        if bad:
            raise ValueError(f"{path}: unknown key(s) {sorted(bad)} in [{name}]; it takes "
                             f"{list(defaults)}")
        sections[name] = {**defaults, **given}
    _check(sections, path)
    return Experiment(sections, path.parent)


def _check(s: dict, path: Path) -> None:
    cam = [k for k in ("file", "preset") if s["camera"][k]]
    if len(cam) != 1:
        raise ValueError(f"{path}: [camera] needs exactly one of file or preset (the "
                         f"camera, calibrated from `white` if given), got {cam or 'none'}")
    if bool(s["grid"]["file"]) == bool(s["grid"]["z_mm"]):
        raise ValueError(f"{path}: [grid] needs exactly one of file or z_mm")
    if s["images"]["pairing"] not in PAIRINGS:
        raise ValueError(f"{path}: [images] pairing must be one of {PAIRINGS}, got "
                         f"{s['images']['pairing']!r}")
    dt = s["images"]["dt_s"]
    if not (isinstance(dt, (int, float)) and dt > 0):
        raise ValueError(f"{path}: [images] dt_s must be the time between the exposures in "
                         f"seconds (e.g. 175e-6), got {dt!r}")
    from .reconstruction import ReconstructionSettings

    ReconstructionSettings(**s["reconstruction"])  # raises on a bad value, naming it


def image_pairs(exp: Experiment) -> list[tuple[Path, Path]]:
    """The image pairs of the experiment, in order."""
    img = exp["images"]
    folder = exp.base / img["folder"]
    files = sorted(folder.glob(img["pattern"]))
    if img["pairing"] == "ab":
        a = [f for f in files if f.stem.endswith(img["a_suffix"])]
        pairs = [(f, f.with_name(f.stem[: -len(img["a_suffix"])] + img["b_suffix"] + f.suffix))
                 for f in a]
    elif img["pairing"] == "sliding":
        pairs = list(zip(files[:-1], files[1:]))
    else:
        pairs = list(zip(files[0::2], files[1::2]))
    if not pairs:
        raise ValueError(f"no image pairs in {folder} matching {img['pattern']!r} "
                         f"(pairing {img['pairing']!r})")
    return pairs


@dataclass
class RunSummary:
    """What :func:`run` did."""

    pairs: int = 0
    processed: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    failed: dict[int, str] = field(default_factory=dict)
    seconds_per_pair: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)


def run(config: str | Path, out: str | Path | None = None, queue=None,
        log=print) -> RunSummary:
    """Process every image pair of an experiment file (see the module notes).

    Returns
    -------
    RunSummary
        Pairs processed, skipped (already written) and failed (with the reason).
    """
    exp = load_experiment(config)
    out = Path(out) if out is not None else exp.base / exp["output"]["folder"]
    pairs = image_pairs(exp)
    camera = _camera(exp, queue, log)
    grid = _grid(exp, camera)
    _write_used_config(exp, out, camera, grid)
    summary = RunSummary(pairs=len(pairs))
    proj = None
    for k, (path_a, path_b) in enumerate(pairs):
        target = out / "pairs" / f"pair_{k:05d}.npz"
        if target.is_file():
            summary.skipped.append(k)
            continue
        try:
            if proj is None:
                from .projection import Projector

                proj = Projector(camera, grid, queue)
            _one_pair(exp, proj, grid, path_a, path_b, target, summary)
            summary.processed.append(k)
            log(f"pair {k}: {path_a.name} + {path_b.name} done")
        except (ValueError, OSError) as exc:
            summary.failed[k] = f"{path_a.name} + {path_b.name}: {exc}"
            log(f"pair {k}: failed, skipped: {exc}")
    _finish(summary, out, log)
    return summary


def _one_pair(exp, proj, grid, path_a, path_b, target: Path, summary: RunSummary) -> None:
    from .io.fields import save_field
    from .io.files import read_image
    from .pipeline import process_pair
    from .reconstruction import ReconstructionSettings

    t0 = time.perf_counter()
    raw_a, raw_b = read_image(path_a), read_image(path_b)
    windows = exp["piv"]["windows"]
    pair = process_pair(raw_a, raw_b, proj,
                        settings=ReconstructionSettings(**exp["reconstruction"]),
                        piv_options={} if windows is None else {"windows": tuple(windows)})
    save_field(target, pair.piv, dt=exp["images"]["dt_s"], grid=grid)
    seconds = {"read": time.perf_counter() - t0 - sum(pair.seconds.values()), **pair.seconds}
    for key, value in seconds.items():
        summary.stage_seconds[key] = summary.stage_seconds.get(key, 0.0) + value


def _camera(exp: Experiment, queue, log):
    from .camera import load_camera

    cam = exp["camera"]
    camera = load_camera(exp.base / cam["file"] if cam["file"] else cam["preset"])
    if not cam["white"]:
        return camera
    from .calibration import calibrate
    from .io.files import read_image

    log(f"calibrating from {cam['white']}")
    return calibrate(read_image(exp.base / cam["white"]), camera)


def _grid(exp: Experiment, camera):
    from .grid import Grid

    g = exp["grid"]
    if g["file"]:
        return Grid.from_toml(exp.base / g["file"])
    return Grid.for_camera(camera, tuple(g["z_mm"]), voxel_mm=g["voxel_mm"],
                           depth_voxel_mm=g["depth_voxel_mm"], fraction=g["fraction"])


def _write_used_config(exp: Experiment, out: Path, camera, grid) -> None:
    from . import __version__

    out.mkdir(parents=True, exist_ok=True)
    used = {name: {k: v for k, v in values.items() if v is not None}
            for name, values in exp.sections.items()}
    used["run"] = {"plenocl_version": __version__,
                   "grid_shape": list(grid.shape), "grid_rotation_deg": grid.rotation_deg}
    write_toml(out / "experiment_used.toml", used)
    camera.to_toml(out / "camera_used.toml")


def _finish(summary: RunSummary, out: Path, log) -> None:
    done = len(summary.processed)
    summary.seconds_per_pair = (sum(summary.stage_seconds.values()) / done) if done else 0.0
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(asdict(summary), indent=2))
    log(f"{done} pair(s) processed, {len(summary.skipped)} already done, "
        f"{len(summary.failed)} failed" + (f": {summary.failed}" if summary.failed else ""))
