"""``plenocl run experiment.toml``: every pair of an experiment, resumable, on this
machine or a Dask cluster (docs/batch.md).

The run checks the experiment file and that its output folder can be written in,
calibrates the camera if a white image is given, and decides what to do with the pairs a
previous run left (:mod:`.record`: each field carries the record of everything that made
it; a rerun skips the pairs made with the run's record, rescales those whose ``dt_s``
alone changed, correlates kept volumes again for a changed ``[piv]``, redoes the pairs
of a changed reconstruction, and refuses, before anything is changed, pairs of other
images, another camera or grid or without a record, unless ``redo``). Then it writes the
configuration used (``experiment_used.toml``, a record with every pair setting resolved;
``camera_used.toml``, ``grid_used.toml``), which now describes every field in the
folder. The pairs' settings go to the workers as an object
(:class:`~.worker.RunSettings`). Each pair's vector field goes atomically to
``OUT/pairs/pair_NNNNN.npz`` (and ``.vti``, ``.h5``, ``.dat``, ``.csv`` on request,
``[output] formats``); a pair that fails (unreadable, wrong size, NaN) is logged with
its reason and the run goes on. At the end, and after Ctrl-C, the finished pairs are
gathered into ``OUT/timeseries.zarr`` with the ensemble mean and RMS fluctuation
(:mod:`plenocl.io.timeseries`; the store records each pair's digest), its summary
figures go to ``OUT/figures/`` (:func:`plenocl.plot.batch_figures`), and
``summary.json`` reports pairs processed, skipped, rescaled, redone and failed, seconds
per pair and the stage split.

Pairs are made from frame numbers (:mod:`.pairing`): a missing frame is a gap, reported
by name, never a shift of the later pairs. Files a killed run left half-written are
removed first.
"""

from __future__ import annotations

import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..io.atomic import write_json
from ..io.fieldformat import field_metadata
from ..io.outputs import check_output_folder, disk_full
from ..io.progress import pair_bar
from ..io.timeseries import write_timeseries
from ..opencl.threads import thread_count
from ..options import NONE
from ..pipeline.resume import name_changes, remove_outputs
from .config import Experiment, image_folders, image_pairs, load_experiment, output_formats
from .ensemble_field import ENSEMBLE, update_ensemble
from .layout import (
    field_copies,
    finished_pairs,
    pair_file,
    remove_partial_files,
    volume_file,
)
from .pairing import ImagePair, PairPlan
from .prepare import (
    check_cluster_device,
    check_corrections,
    check_windows,
    frame_corrections,
    run_cameras,
    run_grid,
    write_used_config,
)
from .record import (
    CORRELATE,
    DT,
    FIELD_SECTIONS,
    REDO,
    RESCALE,
    SKIP,
    Decision,
    decide,
    refuse,
    run_record,
    store_record,
)
from .tracking import TrackingSummary, run_tracking
from .worker import (
    PairOutcome,
    PairProcessor,
    PairTask,
    RunSettings,
    add_copies,
    rescale_field,
)


@dataclass
class RunSummary:
    """What :func:`run` did (also written to ``summary.json``); ``stopped``: why the run
    stopped before its last pair or its time series (the output disk full), else
    ``None``; ``devices``: the pairs each device made, by
    :func:`plenocl.opencl.device.device_label` (workers spread over several devices:
    :mod:`plenocl.batch.cluster`)."""

    pairs: int = 0
    processed: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    rescaled: list[int] = field(default_factory=list)
    redone: list[int] = field(default_factory=list)
    failed: dict[int, str] = field(default_factory=dict)
    dropped_particles: dict[int, int] = field(default_factory=dict)
    gaps: dict[int, str] = field(default_factory=dict)
    unpaired: list[str] = field(default_factory=list)
    sources: dict[int, dict] = field(default_factory=dict)
    seconds_per_pair: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    wall_seconds: float = 0.0
    workers: int = 1
    devices: dict[str, int] = field(default_factory=dict)
    interrupted: bool = False
    stopped: str | None = None
    store: str | None = None
    ensemble: str | None = None
    figures: list[str] = field(default_factory=list)

    def exit_status(self) -> int:
        """The command's exit status: 130 when interrupted, 1 when a pair failed or the
        run stopped (:attr:`stopped`), else 0."""
        if self.interrupted:
            return 130
        return 1 if self.failed or self.stopped else 0


def run(config: str | Path, out: str | Path | None = None, queue=None, log=print, *,
        workers: int | None = None, scheduler: str | None = None,
        progress: bool = True, redo: bool = False) -> RunSummary | TrackingSummary:
    """Process every image pair of an experiment file (see the module notes); with an
    enabled ``[tracking]`` section, track its frames instead
    (:func:`plenocl.batch.tracking.run_tracking`).

    Parameters
    ----------
    config
        The experiment file (:mod:`plenocl.batch.config`).
    out
        Output folder (default: the file's ``[output] folder``).
    queue
        OpenCL device (:func:`plenocl.get_queue` rules); with a cluster, a device name
        each worker looks up (or None: each worker's ``PLENOCL_DEVICE``/``PYOPENCL_CTX``).
    log
        Where messages go.
    workers
        Process the pairs on a local Dask cluster of this many worker processes.
    scheduler
        Address of an existing Dask scheduler to process the pairs on instead.
    progress
        Show a progress bar (pairs done, pairs/s, time left; with ``[tracking]``, the
        frames' steps).
    redo
        Redo the finished pairs a rerun would otherwise refuse (another camera or grid,
        changed source files, fields without a record; :mod:`.record`) instead of
        refusing (``plenocl run --redo``).

    Returns
    -------
    RunSummary or TrackingSummary
        Pairs processed, skipped (already written with the same record), rescaled (only
        ``dt_s`` changed), redone (a setting changed), failed (with the reason) and left
        out for a missing frame (``gaps``), and each finished pair's source files; or
        the tracking run's frames, tracks and stages run or skipped.

    Raises
    ------
    ValueError
        A finished pair the run cannot keep or remake as it is (another camera or grid,
        changed source files, a field without a record) without ``redo``: named, with
        the way out, before anything is changed.
    """
    exp = load_experiment(config)
    out = check_output_folder(out if out is not None else exp.base / exp["output"]["folder"])
    if exp.tracking is not None:
        return run_tracking(exp, out, queue, log, workers=workers, scheduler=scheduler,
                            progress=progress)
    plan = image_pairs(exp)
    check_cluster_device(queue, workers, scheduler)
    for path in remove_partial_files(out) if out.is_dir() else []:
        log(f"removed {path.name}, left half-written by an interrupted run")
    cameras = run_cameras(exp, queue, log)
    camera = cameras if exp.cameras else cameras[0]  # several: joint (design.md §6.7)
    grid = run_grid(exp, camera)
    check_windows(exp.pair.piv, grid)
    check_corrections(exp, cameras)
    settings = _run_settings(exp, run_record(exp, camera, grid), len(cameras))
    decisions = _decide(plan, out, settings.record, redo, image_folders(exp))
    summary = RunSummary(pairs=len(plan.pairs) + len(plan.gaps),
                         workers=workers or (0 if scheduler else 1),
                         gaps=dict(plan.gaps), unpaired=list(plan.unpaired))
    _apply(decisions, plan, out, grid, settings, summary, log)
    write_used_config(exp, out, camera, grid, _pair_record(exp))
    _report_gaps(plan, log)
    tasks = _tasks(plan.pairs, decisions, out, summary, log)
    t0 = time.perf_counter()
    with pair_bar(len(tasks), progress) as advance:
        def done(outcome: PairOutcome) -> None:
            _record(outcome, summary, log)
            advance(outcome.error is not None)
            if outcome.disk_full:  # no later pair could be written: stop computing them
                raise _DiskFull(outcome.error)

        try:
            _process(tasks, out, settings, queue, workers, scheduler, done)
        except KeyboardInterrupt:
            summary.interrupted = True
            log("interrupted: the pairs finished so far are kept; run again to go on")
        except _DiskFull as exc:
            summary.stopped = str(exc)
            log(f"stopped, the output disk is full: the pairs finished so far are kept; "
                f"free space and run again to go on ({exc})")
    summary.wall_seconds = time.perf_counter() - t0
    _finish(summary, exp, out, queue, log)
    return summary


class _DiskFull(Exception):
    """A pair could not be written for want of space: the run stops (the pairs still
    running on a cluster are cancelled)."""


def _no_store(path: Path, summary: RunSummary, exc: OSError, log) -> None:
    """The disk filled while the time-series store was written: its half-written copy,
    the older store (which no longer gathers this run's pairs) and its figures are
    removed, so no store is left that the pairs would not make
    (:func:`_stopped_writing`)."""
    # the older store's figures too: they drew a store no longer there
    for stale in (path.with_name(path.name + ".partial"), path, path.parent / "figures"):
        shutil.rmtree(stale, ignore_errors=True)
    _stopped_writing(f"the time series {path.name}", summary, exc, log)


def _stopped_writing(what: str, summary: RunSummary, exc: OSError, log) -> None:
    """``what``, gathered from the finished pairs, could not be written for want of
    space (and is not left): the summary says so (:attr:`RunSummary.stopped`), and a
    rerun with space writes it from the pairs kept."""
    why = (f"{what} could not be written, the output disk is full ({exc.strerror or exc}): "
           "the pairs are kept; free space and run again to write it")
    summary.stopped = why if summary.stopped is None else f"{summary.stopped}; {why}"
    log(f"stopped: {why}")


def _report_gaps(plan: PairPlan, log) -> None:
    """Say which pairs a missing frame leaves out, and which files belong to no pair."""
    for k, why in sorted(plan.gaps.items()):
        log(f"pair {k}: not made, {why}")
    for why in plan.unpaired:
        log(f"not in any pair: {why}")


def _decide(plan: PairPlan, out: Path, record: dict, redo: bool,
            folders: list[Path]) -> list[Decision]:
    """What to do with each finished pair (:func:`.record.decide`; ``folders``: the
    run's image folders); refuses, before anything is changed, when a pair can be
    neither kept nor remade (unless ``redo``)."""
    planned = {p.index: p for p in plan.pairs}
    decisions = [decide(planned.get(k), path, volume_file(path), record, redo, folders)
                 for k, path in finished_pairs(out)]
    refuse(decisions, out)
    return decisions


def _apply(decisions: list[Decision], plan: PairPlan, out: Path, grid,
           settings: RunSettings, summary: RunSummary, log) -> None:
    """Act on the decisions before any pair is processed: remove what a redone pair
    replaces (its field, its copies and volumes of another reconstruction), rescale the
    fields whose ``dt_s`` alone changed, and remove the run's products built from the
    old pairs (``timeseries.zarr``, ``experiment_used.toml``: written again)."""
    added = [d.index for d in decisions
             if d.action == SKIP and add_copies(pair_file(out, d.index), grid, settings.formats)]
    if added:
        log(f"{_count(added)}: {', '.join(settings.formats)} written from the kept field "
            "([output] formats)")
    changes = [d for d in decisions if d.action != SKIP]
    if not changes:
        return
    remove_outputs([out / "experiment_used.toml", out / "timeseries.zarr"])
    planned = {p.index for p in plan.pairs}
    for d in changes:
        target = pair_file(out, d.index)
        if d.action == RESCALE:
            rescale_field(target, grid, settings)
            summary.rescaled.append(d.index)
        else:  # made again: a pair that fails then leaves no field of other settings
            _remove_pair(target, keep_volumes=d.action == CORRELATE)
        if d.action in (REDO, CORRELATE) and d.index in planned:
            summary.redone.append(d.index)
    _report_decisions(changes, planned, settings, log)


def _remove_pair(target: Path, keep_volumes: bool = False) -> None:
    """A pair's field and its copies before it is made again, and its kept volumes unless
    ``keep_volumes`` (they are correlated again)."""
    volumes = () if keep_volumes else (volume_file(target),)
    remove_outputs([target, *field_copies(target), *volumes])


def _report_decisions(changes: list[Decision], planned: set[int], settings: RunSettings,
                      log) -> None:
    """One line per kind of change: which pairs, what changed, what the run does."""
    groups: dict[tuple, list[int]] = {}
    for d in changes:
        action = d.action if d.action != REDO or d.index in planned else "remove"
        why = f"{name_changes(d.changed)} changed" if d.changed else ""
        if d.reason is not None:
            why = f"{d.reason} (--redo)"
        groups.setdefault((action, why, tuple(d.changed)), []).append(d.index)
    what = {RESCALE: "velocities rescaled from the stored displacements (nothing "
                     "reconstructed or correlated)",
            CORRELATE: "correlating the kept volumes again (no reconstruction)",
            REDO: "redoing them (reconstruction included)",
            "remove": "removed: this run makes no such pair (its frames are gone, or "
                      "its [images] selection leaves them out)"}
    for (action, why, changed), pairs in sorted(groups.items()):
        if action == REDO and changed and not settings.pair.mte.cycles and all(
                n == DT or n.split(".")[0] in FIELD_SECTIONS for n in changed):
            why += (" and no volumes of this reconstruction are kept"
                    + ("" if settings.keep_volumes else " ([piv] ensemble = false)"))
        log(f"{_count(pairs)}: {why}: {what[action]}")


def _count(pairs: list[int]) -> str:
    """``pair 3`` or ``4 pairs (0, 1, 2, ...)``."""
    if len(pairs) == 1:
        return f"pair {pairs[0]}"
    shown = ", ".join(map(str, pairs[:6])) + (", ..." if len(pairs) > 6 else "")
    return f"{len(pairs)} pairs ({shown})"


def _tasks(pairs: list[ImagePair], decisions: list[Decision], out: Path,
           summary: RunSummary, log) -> list[PairTask]:
    """The pairs still to do: those without a field, and those to correlate again; the
    others (made with the run's record, or rescaled) are skipped, and said so."""
    mode = {d.index: d.action for d in decisions}
    tasks = []
    for p in pairs:
        target = pair_file(out, p.index)
        others = tuple((str(a), str(b)) for a, b in p.others)
        if mode.get(p.index) == CORRELATE:
            tasks.append(PairTask(p.index, str(p.a), str(p.b), str(target), CORRELATE,
                                  others))
        elif not target.is_file():
            tasks.append(PairTask(p.index, str(p.a), str(p.b), str(target), others=others))
        elif mode.get(p.index) == SKIP:
            summary.skipped.append(p.index)
    if summary.skipped:
        log(f"{len(summary.skipped)} of {len(pairs)} pair(s) already done with these "
            f"settings in {out / 'pairs'}: skipped")
    (out / "pairs").mkdir(parents=True, exist_ok=True)
    return tasks


def _pair_record(exp: Experiment) -> dict:
    """The pair settings' sections as ``experiment_used.toml`` records them."""
    pair = exp.pair.to_dict(none=NONE)  # TOML has no null: "none"
    pair["piv"].update(exp["piv"])  # ensemble, the batch's
    return pair


def _run_settings(exp: Experiment, record: dict, cameras: int = 1) -> RunSettings:
    """What every pair of the run shares, from the checked experiment file, the run's
    record (:func:`.record.run_record`) and its number of cameras."""
    img = exp["images"]
    dark, flat = frame_corrections(exp)
    return RunSettings(exp.pair, float(img["dt_s"]), output_formats(exp["output"]),
                       bool(exp["piv"]["ensemble"]), img["channel"], dark, flat, record,
                       cameras)


def _process(tasks, out: Path, settings: RunSettings, queue, workers, scheduler,
             done) -> None:
    """Run the tasks serially in this process, or on a Dask cluster. Serially, a helper
    thread reads the next pair's frames (files, colour channel, dark frame and flat
    field, region of interest) while a pair computes, where the process may use two
    threads; the pairs are processed and recorded in the same order either way."""
    if not tasks:
        return
    if workers or scheduler:
        from .cluster import dask_client, run_on_dask

        with dask_client(workers, scheduler) as client:
            run_on_dask(client, tasks, out, settings, queue, done)
        return
    processor = PairProcessor(out, settings, queue)
    if thread_count() < 2:  # one thread allowed (PLENOCL_THREADS=1): in turn
        for task in tasks:
            done(processor(task))
        return
    with ThreadPoolExecutor(1, thread_name_prefix="plenocl-read") as reader:
        ahead = reader.submit(processor.read, tasks[0])
        for k, task in enumerate(tasks):
            read = ahead.result()
            if k + 1 < len(tasks):  # the next pair's files read while this one computes
                ahead = reader.submit(processor.read, tasks[k + 1])
            done(processor(task, read))


def _record(outcome: PairOutcome, summary: RunSummary, log) -> None:
    if outcome.error is not None:
        summary.failed[outcome.index] = outcome.error
        log(f"pair {outcome.index}: failed, skipped: {outcome.error}")
        return
    summary.processed.append(outcome.index)
    if outcome.device:
        summary.devices[outcome.device] = summary.devices.get(outcome.device, 0) + 1
    if outcome.dropped:
        summary.dropped_particles[outcome.index] = outcome.dropped
    for key, value in outcome.seconds.items():
        summary.stage_seconds[key] = summary.stage_seconds.get(key, 0.0) + value


def _figures(store: Path, folder: Path, log) -> list[str]:
    """The store's summary figures (:func:`plenocl.plot.batch_figures`) in ``folder``; a
    figure that cannot be drawn is reported, and the run's results stand."""
    from ..plot import batch_figures

    try:
        written = batch_figures(store, folder)
    except (ValueError, OSError, RuntimeError) as exc:
        log(f"summary figures not written: {exc}")
        return []
    log(f"summary figures: {', '.join(p.name for p in written)} in {folder}")
    return [str(p) for p in written]


def _finish(summary: RunSummary, exp: Experiment, out: Path, queue, log) -> None:
    """The ensemble correlation if asked for (not after Ctrl-C); gather every finished
    pair into the store and draw its summary figures; write ``summary.json``."""
    done = len(summary.processed)
    summary.processed.sort()
    summary.seconds_per_pair = (summary.wall_seconds / done) if done else 0.0
    interval = exp["images"]["pair_interval_s"]
    fields = finished_pairs(out)
    metas = {k: (path, field_metadata(path)) for k, path in fields}
    summary.sources = {k: meta.get("sources", {}) for k, (_, meta) in metas.items()}
    try:
        ensemble = update_ensemble(out, metas, exp["images"]["dt_s"], queue,
                                   output_formats(exp["output"]), log,
                                   wanted=bool(fields and exp["piv"]["ensemble"]
                                               and not summary.interrupted
                                               and summary.stopped is None))
    except OSError as exc:
        if not disk_full(exc):
            raise
        for part in (out / ENSEMBLE, *field_copies(out / ENSEMBLE)):  # none half-written
            part.unlink(missing_ok=True)
        _stopped_writing(f"the ensemble field {ENSEMBLE}", summary, exc, log)
        ensemble = None
    if exp["piv"]["ensemble"]:
        summary.ensemble = None if ensemble is None else str(ensemble)
    else:
        ensemble = None
    if fields:
        try:
            store = write_timeseries(out / "timeseries.zarr",
                                     [(k, k * interval if interval else float(k), p)
                                      for k, p in fields], "s" if interval else "pair",
                                     ensemble=ensemble,
                                     record=store_record({k: m for k, (_, m) in metas.items()},
                                                         ensemble))
        except OSError as exc:
            if not disk_full(exc):
                raise
            _no_store(out / "timeseries.zarr", summary, exc, log)
        else:
            summary.store = str(store)
            summary.figures = _figures(store, out / "figures", log)
    write_json(out / "summary.json", asdict(summary))
    each = (f" ({summary.seconds_per_pair:.1f} s each, "
            f"{3600 / summary.seconds_per_pair:.0f} pairs per hour)"
            if done and summary.seconds_per_pair > 0 else "")
    log(f"{done} pair(s) processed{each}, "
        f"{len(summary.skipped)} already done"
        + (f", {len(summary.rescaled)} rescaled to dt_s" if summary.rescaled else "")
        + f", {len(summary.failed)} failed"
        + (f": {summary.failed}" if summary.failed else "")
        + (f", {len(summary.gaps)} not made for missing frames" if summary.gaps else "")
        + (f", {sum(summary.dropped_particles.values())} particle(s) dropped by the image "
           f"fit in {len(summary.dropped_particles)} pair(s)"
           if summary.dropped_particles else "")
        + (f"; {len(fields)} in {out / 'timeseries.zarr'}" if fields else ""))
