"""A time-resolved experiment tracked: ``plenocl run`` with an enabled ``[tracking]``
section (docs/batch.md).

The frames matched by ``[images]`` (every frame by number, no gap: one recording at
``[tracking] frame_interval_s``) are read through the pairs' frame reader (channel,
dark frame, flat field, region of interest) and tracked by :func:`plenocl.track` as one
job: in this process, or as one task on a Dask cluster (``--workers``/``--scheduler``;
tracking is sequential, so one worker runs it). The run writes ``OUT/tracks.npz``
(:meth:`plenocl.Tracks.save`), ``OUT/tracks.vtu`` (ParaView poly-lines) and
``OUT/tracks.zarr`` (the tracks and their binned field, :mod:`.trackstore`), each
atomically, ``OUT/figures/tracks.png`` (the tracks coloured by speed) and
``summary.json``.

Resume is :class:`plenocl.pipeline.resume.StageRunner`'s: two stages, ``tracks`` (the
tracking) and ``field`` (the binned field, the ParaView file and the store), keyed on
the frames' content (name, size, SHA-256), the camera and grid used, the frame
corrections, every setting (the lens weights named), the reconstruction's method
(:data:`plenocl.reconstruction.METHOD`), the image fit's
(:data:`plenocl.piv.imagefit.METHOD`), the correlation's that predicts the first step
(:data:`plenocl.piv.direct.METHOD`) and the tracker's
(:data:`plenocl.pipeline.track.METHOD`); a rerun with the same skips both, any change
runs both again, but a change of the binned field's options alone (the field stage's own
key, with the digest of the tracks it bins and the methods that bin them: the tracker's
and :data:`plenocl.piv.refinement.METHOD`, its window means) runs the field stage
only. The outputs of a stage to be done again are removed before it starts, and the
store records both digests (its ``record`` attribute: ``tracks``, the configuration's,
and ``field``, the field stage's key), so the results beside ``experiment_used.toml``
are always its.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..camera import load_camera
from ..grid import Grid
from ..io.atomic import write_json
from ..io.progress import step_bar
from ..pipeline.frames import load_corrections, load_frame
from ..pipeline.resume import StageRunner, config_digest, remove_outputs
from ..pipeline.track import METHOD as TRACK_METHOD
from ..pipeline.track import TrackSettings, bin_tracks, track
from ..piv.direct import METHOD as CORRELATION_METHOD
from ..piv.imagefit import METHOD as FIT_METHOD
from ..piv.refinement import METHOD as REFINEMENT_METHOD
from ..piv.refinement import FocalZone
from ..ptv import Tracks
from ..reconstruction import METHOD as RECONSTRUCTION_METHOD
from .config import Experiment
from .pairing import fingerprint, numbered_series
from .prepare import (
    check_cluster_device,
    check_corrections,
    check_windows,
    frame_corrections,
    run_camera,
    run_grid,
    write_used_config,
)
from .trackconfig import TrackingOptions
from .trackstore import write_track_store

#: The files a tracking run writes in its output folder.
TRACKS, LINES, STORE = "tracks.npz", "tracks.vtu", "tracks.zarr"
#: The field stage's outputs (the store's own file marks it complete).
FIELD_OUTPUTS = [LINES, f"{STORE}/zarr.json"]


@dataclass
class TrackingSummary:
    """What a tracking run did (also written to ``summary.json``)."""

    frames: int = 0
    frame_numbers: list[int] = field(default_factory=list)
    tracks: int = 0
    dropped_particles: int = 0
    processed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    stage_seconds: dict[str, float] = field(default_factory=dict)
    wall_seconds: float = 0.0
    workers: int = 1
    store: str | None = None
    figures: list[str] = field(default_factory=list)

    def exit_status(self) -> int:
        """The command's exit status: 0 (a tracking run that fails raises instead)."""
        return 0


@dataclass(frozen=True)
class TrackJob:
    """The tracking of one run, from file paths to ``tracks.npz``: the unit of work in
    this process or on a Dask worker; ``config``: the run's configuration digest
    (``state.json``'s), recorded in ``tracks.npz`` (``Tracks.record_of``)."""

    frames: tuple[str, ...]
    run_folder: str
    settings: TrackSettings
    interval_s: float
    channel: str | None = None
    dark: str | None = None
    flat: str | None = None
    device: str | None = None
    config: str | None = None


def run_tracking(exp: Experiment, out: Path, queue=None, log=print, *,
                 workers: int | None = None, scheduler: str | None = None,
                 progress: bool = True) -> TrackingSummary:
    """Track the experiment's frames (see the module notes); :func:`plenocl.run` calls it
    for an experiment with an enabled ``[tracking]`` section. ``progress``: a bar over
    the frames (in this process, on a terminal).

    Raises
    ------
    ValueError
        A missing, unreadable or mis-sized frame, too few frames for ``min_length``, a
        binned-field window larger than the grid: named with the fix, before any frame
        is tracked.
    """
    opts = exp.tracking
    frames = frame_series(exp, opts)
    check_cluster_device(queue, workers, scheduler)
    camera = run_camera(exp, queue, log)
    grid = run_grid(exp, camera)
    check_windows(opts.settings.piv, grid)
    check_corrections(exp, [camera])
    layout = opts.layout(grid)
    write_used_config(exp, out, camera, grid, opts.record())
    runner = StageRunner(out, _config(exp, frames, out, opts), log)
    summary = TrackingSummary(len(frames), list(frames),
                              workers=workers or (0 if scheduler else 1))
    job = _job(exp, frames, out, opts, queue if isinstance(queue, str) else None,
               runner.key)
    _remove_stale(runner, out, opts, log)
    log(f"tracking {len(frames)} frames {opts.interval_s:g} s apart")
    t0 = time.perf_counter()
    _stage(runner, summary, "tracks", [TRACKS],
           lambda: _track(job, queue, workers, scheduler, progress))
    key = _field_key(out, opts)  # new tracks: again
    record = {"tracks": runner.key, "field": config_digest(key)}
    _stage(runner, summary, "field", FIELD_OUTPUTS,
           lambda: _write_outputs(out, frames, opts, camera, grid, layout, record), key)
    summary.wall_seconds = time.perf_counter() - t0
    tracks = Tracks.load(out / TRACKS)
    summary.tracks, summary.dropped_particles = len(tracks.positions), tracks.dropped
    summary.store = str(out / STORE)
    summary.figures = _figures(out, log)
    write_json(out / "summary.json", asdict(summary))
    log(f"{summary.tracks} tracks over {len(frames)} frames in {out / TRACKS}, "
        f"{out / LINES} and {out / STORE}"
        + (f"; {tracks.dropped} particle(s) dropped by the image fit (left the grid or "
           "not finite)" if tracks.dropped else ""))
    return summary


#: How the field stage bins the tracks beyond the refinement's window means; change it
#: whenever the binned field changes (a rerun bins the tracks again, not tracking them).
FIELD_METHOD = ("the focal zone's depth uncertainty only where it lies along the grid's z "
                "(a camera without pose; 2026-12-02)")


def _field_key(out: Path, opts: TrackingOptions) -> dict:
    """The field stage's own key: the binned field's options, the tracks' digest and
    the methods that bin them (the tracker's, the refinement's window means and
    :data:`FIELD_METHOD`)."""
    tracks = out / TRACKS
    return {**opts.field_record(), "tracks": _digest(tracks) if tracks.is_file() else None,
            "tracker": TRACK_METHOD, "refinement": REFINEMENT_METHOD, "field": FIELD_METHOD}


def _remove_stale(runner: StageRunner, out: Path, opts: TrackingOptions, log) -> None:
    """The outputs of the stages this run does again, removed before it starts: a run
    that fails leaves no tracks or field of another configuration beside its
    ``experiment_used.toml``."""
    stale = []
    if not runner.done("tracks", [TRACKS]):
        stale = [TRACKS, *FIELD_OUTPUTS]
    elif not runner.done("field", FIELD_OUTPUTS, _field_key(out, opts)):
        stale = FIELD_OUTPUTS
    gone = remove_outputs(out / name for name in dict.fromkeys(n.split("/")[0] for n in stale))
    if gone:
        log(f"removed {', '.join(p.name for p in gone)}: made with another configuration, "
            "made again")


def frame_series(exp: Experiment, opts: TrackingOptions) -> dict[int, Path]:
    """``{frame number: file}`` of the recording; none, a gap, or fewer frames than
    ``min_length`` is an error naming the folder and the fix."""
    img = exp["images"]
    folder = exp.base / img["folder"]
    files = sorted(f for f in folder.glob(img["pattern"]) if f.is_file())
    if not files:
        raise ValueError(f"no frames in {folder} matching {img['pattern']!r}: check "
                         "[images] folder and pattern")
    frames = numbered_series(files, img["first_frame"], folder)
    least = opts.settings.min_length
    if len(frames) < least:
        raise ValueError(f"{len(frames)} frame(s) in {folder} matching {img['pattern']!r}, "
                         f"but a track is kept when seen in [tracking] min_length = {least} "
                         f"frames: give at least {least} frames, or a smaller min_length "
                         "(>= 2)")
    return frames


def _stage(runner: StageRunner, summary: TrackingSummary, name: str, outputs: list[str],
           work: Callable[[], None], key: dict | None = None) -> None:
    """One stage through the runner (``key``: the stage's own resume key), recorded as
    skipped or processed."""
    (summary.skipped if runner.done(name, outputs, key) else summary.processed).append(name)
    summary.stage_seconds[name] = runner.run(name, outputs, work, key)


def _config(exp: Experiment, frames: dict[int, Path], out: Path,
            opts: TrackingOptions) -> dict:
    """What the tracks are made from: the resume key (the field's own options are the
    field stage's key, so changing only them does not track again)."""
    dark, flat = frame_corrections(exp)
    record = opts.record()
    record["tracking"] = {k: v for k, v in record["tracking"].items()
                          if not k.startswith("field_")}
    return {"frames": {n: _content(path) for n, path in frames.items()},
            "settings": record, "channel": exp["images"]["channel"],
            "dark": dark and _content(Path(dark)), "flat": flat and _content(Path(flat)),
            "camera": _digest(out / "camera_used.toml"), "grid": _digest(out / "grid_used.toml"),
            "reconstruction_method": RECONSTRUCTION_METHOD, "fit": FIT_METHOD,
            "correlation": CORRELATION_METHOD, "tracker": TRACK_METHOD}


def _content(path: Path) -> dict:
    """A file's name, size and SHA-256 (not its time: a copy is the same input)."""
    return {k: v for k, v in fingerprint(path).items() if k != "mtime_ns"}


def _digest(path: Path) -> str:
    """A file's SHA-256 (its content only)."""
    return fingerprint(path)["sha256"]


def _job(exp: Experiment, frames: dict[int, Path], out: Path, opts: TrackingOptions,
         device: str | None, config: str | None = None) -> TrackJob:
    dark, flat = frame_corrections(exp)
    return TrackJob(tuple(str(p.resolve()) for p in frames.values()), str(out.resolve()),
                    opts.settings, opts.interval_s, exp["images"]["channel"], dark, flat,
                    device, config)


def _track(job: TrackJob, queue, workers: int | None, scheduler: str | None,
           progress: bool) -> None:
    """The job in this process (with a progress bar when ``progress``), or as one task
    on a Dask cluster."""
    if not (workers or scheduler):
        track_job(job, queue, bar=progress)
        return
    from .cluster import dask_client

    with dask_client(workers, scheduler) as client:
        client.submit(track_on_worker, job, pure=False).result()


def track_on_worker(job: TrackJob) -> dict[str, float]:
    """The Dask task: the job on this worker's device (the run's device name, else the
    worker's ``PLENOCL_DEVICE``, else its default), without a progress bar."""
    return track_job(job, job.device or os.environ.get("PLENOCL_DEVICE") or None,
                     bar=False)


def track_job(job: TrackJob, device=None, bar: bool = True) -> dict[str, float]:
    """Read every frame (all before any is tracked), track them (a progress bar over the
    frames' steps on a terminal, ``bar``), write ``tracks.npz`` atomically; returns
    seconds per step."""
    folder = Path(job.run_folder)
    camera = load_camera(folder / "camera_used.toml")
    grid = Grid.from_toml(folder / "grid_used.toml")
    t0 = time.perf_counter()
    frames = read_frames(job, camera)
    t1 = time.perf_counter()
    from ..projection import Projector

    with step_bar("frames (particles, then refits)", "step", bar) as progress:
        tracks = track(frames, Projector(camera, grid, device), job.interval_s, job.settings,
                       progress=progress)
    t2 = time.perf_counter()
    tracks.save(folder / TRACKS, None if job.config is None else {"tracks": job.config})
    return {"read": t1 - t0, "track": t2 - t1, "write": time.perf_counter() - t2}


def read_frames(job: TrackJob, camera) -> list[np.ndarray]:
    """Every frame as the camera sees it (:func:`plenocl.pipeline.frames.load_frame`);
    an unreadable or mis-sized frame is an error naming it and the fix."""
    dark, flat = load_corrections(job.dark, job.flat, [camera], job.channel)
    frames = []
    for path in job.frames:
        try:
            frames.append(load_frame(path, camera, job.channel, dark, flat))
        except (ValueError, OSError) as exc:
            raise ValueError(f"{exc}. A recording is tracked as one series at a constant "
                             f"interval: replace {Path(path).name}, or track the frames "
                             "before or after it ([images] first_frame, pattern)") from exc
    return frames


def _figures(out: Path, log) -> list[str]:
    """The tracks in 3-D, coloured by speed (``OUT/figures/tracks.png``); a figure that
    cannot be drawn is reported, and the run's results stand."""
    from ..plot.tracks import plot_tracks

    try:
        path = plot_tracks(out / "figures" / "tracks.png", Tracks.load(out / TRACKS))
    except (ValueError, OSError, RuntimeError) as exc:
        log(f"tracks figure not written: {exc}")
        return []
    log(f"tracks figure: {path}")
    return [str(path)]


def _write_outputs(out: Path, frames: dict[int, Path], opts: TrackingOptions, camera,
                   grid: Grid, layout, record: dict) -> None:
    """The tracks' ParaView lines, their binned field and the store (with ``record``:
    the digests of the tracks' configuration and of the field stage's key)."""
    tracks = Tracks.load(out / TRACKS)
    if not np.any(tracks.lengths >= 2):
        raise ValueError(f"no particle was tracked through {opts.settings.min_length} frames "
                         f"({out / TRACKS} holds no track): check that the frames are "
                         "consecutive and in focus, or lower [tracking] threshold or "
                         "min_length, or widen search (docs/errors.md)")
    tracks.save(out / LINES, seconds=True, frames=list(frames))  # m/s and frame numbers,
    # as the store and the figure
    fields = binned_fields(tracks, grid, opts, layout, FocalZone.along_grid(camera, grid))
    write_track_store(out / STORE, tracks, list(frames), fields, grid, record)


def binned_fields(tracks: Tracks, grid: Grid, opts: TrackingOptions, layout,
                  focus: FocalZone | None = None) -> list:
    """``(first frame, last frame, field)`` of every ``opts.field_steps`` steps (all
    steps at once for 0): :func:`plenocl.bin_tracks` on ``layout``'s windows."""
    steps = tracks.positions.shape[1] - 1
    size = opts.field_steps or steps
    window, step = layout
    out = []
    for start in range(0, steps, size):
        chosen = list(range(start, min(start + size, steps)))
        res = bin_tracks(tracks, grid, window, step, frames=chosen,
                         min_samples=opts.field_min_samples, focus=focus)
        out.append((start, chosen[-1] + 1, res))
    return out
