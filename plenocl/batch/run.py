"""``plenocl run experiment.toml``: every pair of an experiment, resumable, on this
machine or a Dask cluster (docs/batch.md).

The run checks the experiment file, calibrates the camera if a white image is given, and
writes the configuration used (``experiment_used.toml``, a record with every pair setting
resolved; ``camera_used.toml``, ``grid_used.toml``) before any pair. The pairs' settings
go to the workers as an object (:class:`~.worker.RunSettings`). Each pair's vector field
goes atomically to ``OUT/pairs/pair_NNNNN.npz`` (and ``.vti`` on request): a rerun skips
the pairs already there and says so; a pair that fails (unreadable, wrong size, NaN) is
logged with its reason and the run goes on. At the end, and after Ctrl-C, the finished
pairs are gathered into ``OUT/timeseries.zarr`` with the ensemble mean and RMS
fluctuation (:mod:`plenocl.io.timeseries`), its summary figures go to ``OUT/figures/``
(:func:`plenocl.plot.batch_figures`), and ``summary.json`` reports pairs processed,
skipped and failed, seconds per pair and the stage split.

Pairs are made from frame numbers (:mod:`.pairing`): a missing frame is a gap, reported
by name, never a shift of the later pairs. Each field records its two source files (name,
size, SHA-256); a rerun whose files differ from those a finished pair was made from
refuses to mix them. Files a killed run left half-written are removed first.
"""

from __future__ import annotations

import time
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..io.atomic import write_json
from ..io.fields import field_metadata
from ..io.progress import pair_bar
from ..io.timeseries import write_timeseries
from ..options import NONE
from ..pipeline.resume import pending
from .config import Experiment, image_pairs, load_experiment
from .layout import finished_pairs, pair_file, remove_partial_files
from .pairing import ImagePair, PairPlan, changed_since
from .prepare import (
    check_cluster_device,
    frame_corrections,
    run_camera,
    run_grid,
    write_used_config,
)
from .tracking import TrackingSummary, run_tracking
from .worker import PairOutcome, PairProcessor, PairTask, RunSettings


@dataclass
class RunSummary:
    """What :func:`run` did (also written to ``summary.json``)."""

    pairs: int = 0
    processed: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    failed: dict[int, str] = field(default_factory=dict)
    gaps: dict[int, str] = field(default_factory=dict)
    unpaired: list[str] = field(default_factory=list)
    sources: dict[int, dict] = field(default_factory=dict)
    seconds_per_pair: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    wall_seconds: float = 0.0
    workers: int = 1
    interrupted: bool = False
    store: str | None = None
    ensemble: str | None = None
    figures: list[str] = field(default_factory=list)

    def exit_status(self) -> int:
        """The command's exit status: 130 when interrupted, 1 when a pair failed, else 0."""
        if self.interrupted:
            return 130
        return 1 if self.failed else 0


def run(config: str | Path, out: str | Path | None = None, queue=None, log=print, *,
        workers: int | None = None, scheduler: str | None = None,
        progress: bool = True) -> RunSummary | TrackingSummary:
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

    Returns
    -------
    RunSummary or TrackingSummary
        Pairs processed, skipped (already written), failed (with the reason) and left
        out for a missing frame (``gaps``), and each finished pair's source files; or
        the tracking run's frames, tracks and stages run or skipped.
    """
    exp = load_experiment(config)
    out = Path(out) if out is not None else exp.base / exp["output"]["folder"]
    if exp.tracking is not None:
        return run_tracking(exp, out, queue, log, workers=workers, scheduler=scheduler,
                            progress=progress)
    plan = image_pairs(exp)
    check_cluster_device(queue, workers, scheduler)
    for path in remove_partial_files(out) if out.is_dir() else []:
        log(f"removed {path.name}, left half-written by an interrupted run")
    camera = run_camera(exp, queue, log)
    grid = run_grid(exp, camera)
    _refuse_other_grid(out, grid)
    _refuse_changed_inputs(plan, out)
    write_used_config(exp, out, camera, grid, _pair_record(exp))
    summary = RunSummary(pairs=len(plan.pairs) + len(plan.gaps),
                         workers=workers or (0 if scheduler else 1),
                         gaps=dict(plan.gaps), unpaired=list(plan.unpaired))
    _report_gaps(plan, log)
    tasks = _tasks(plan.pairs, out, summary, log)
    t0 = time.perf_counter()
    with pair_bar(len(tasks), progress) as advance:
        def done(outcome: PairOutcome) -> None:
            _record(outcome, summary, log)
            advance(outcome.error is not None)

        try:
            _process(tasks, out, _run_settings(exp), queue, workers, scheduler, done)
        except KeyboardInterrupt:
            summary.interrupted = True
            log("interrupted: the pairs finished so far are kept; run again to go on")
    summary.wall_seconds = time.perf_counter() - t0
    _finish(summary, exp, out, queue, log)
    return summary


def _report_gaps(plan: PairPlan, log) -> None:
    """Say which pairs a missing frame leaves out, and which files belong to no pair."""
    for k, why in sorted(plan.gaps.items()):
        log(f"pair {k}: not made, {why}")
    for why in plan.unpaired:
        log(f"not in any pair: {why}")


def _refuse_changed_inputs(plan: PairPlan, out: Path) -> None:
    """A finished pair whose source files differ from the plan's refuses the run: its
    field and the new pairs would mix two sets of inputs."""
    planned = {p.index: p for p in plan.pairs}
    changed = []
    for k, path in finished_pairs(out):
        pair = planned.get(k)
        try:
            recorded = field_metadata(path).get("sources", {})
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            changed.append(f"pair {k}: {path.name} cannot be read ({exc})")
            continue
        if pair is None:
            if recorded:
                continue  # a frame removed after its pair was made: the field stays valid
            changed.append(f"pair {k}: {path.name} exists but the images give no pair {k}")
        elif (why := changed_since(recorded, pair)) is not None:
            changed.append(f"pair {k}: {why}")
    if changed:
        raise ValueError(
            f"{out} holds pairs made from other images than this run's: "
            + "; ".join(changed[:5]) + (f"; and {len(changed) - 5} more" if len(changed) > 5
                                        else "")
            + ". Write this run to another folder (--out), or remove the old results")


def _tasks(pairs: list[ImagePair], out: Path, summary: RunSummary, log) -> list[PairTask]:
    """The pairs still to do; those whose field exists are skipped, and said so."""
    todo, done = pending(pairs, lambda pair: [pair_file(out, pair.index)])
    summary.skipped.extend(pair.index for pair in done)
    tasks = [PairTask(p.index, str(p.a), str(p.b), str(pair_file(out, p.index))) for p in todo]
    if summary.skipped:
        log(f"{len(summary.skipped)} of {len(pairs)} pair(s) already done in "
            f"{out / 'pairs'}: skipped")
    (out / "pairs").mkdir(parents=True, exist_ok=True)
    return tasks


def _pair_record(exp: Experiment) -> dict:
    """The pair settings' sections as ``experiment_used.toml`` records them."""
    pair = exp.pair.to_dict(none=NONE)  # TOML has no null: "none"
    pair["piv"].update(exp["piv"])  # ensemble, the batch's
    return pair


def _run_settings(exp: Experiment) -> RunSettings:
    """What every pair of the run shares, from the checked experiment file."""
    img = exp["images"]
    dark, flat = frame_corrections(exp)
    return RunSettings(exp.pair, float(img["dt_s"]), bool(exp["output"]["vti"]),
                       bool(exp["piv"]["ensemble"]), img["channel"], dark, flat)


def _process(tasks, out: Path, settings: RunSettings, queue, workers, scheduler,
             done) -> None:
    """Run the tasks serially in this process, or on a Dask cluster."""
    if not tasks:
        return
    if workers or scheduler:
        from .cluster import dask_client, run_on_dask

        with dask_client(workers, scheduler) as client:
            run_on_dask(client, tasks, out, settings, queue, done)
        return
    processor = PairProcessor(out, settings, queue)
    for task in tasks:
        done(processor(task))


def _record(outcome: PairOutcome, summary: RunSummary, log) -> None:
    if outcome.error is not None:
        summary.failed[outcome.index] = outcome.error
        log(f"pair {outcome.index}: failed, skipped: {outcome.error}")
        return
    summary.processed.append(outcome.index)
    for key, value in outcome.seconds.items():
        summary.stage_seconds[key] = summary.stage_seconds.get(key, 0.0) + value


def _refuse_other_grid(out: Path, grid) -> None:
    """A rerun refuses to mix pairs of another grid into the folder."""
    grid_file = out / "grid_used.toml"
    if grid_file.is_file() and finished_pairs(out):
        from ..grid import Grid

        if Grid.from_toml(grid_file) != grid:
            raise ValueError(f"{out} holds pairs of another grid ({grid_file}); write this "
                             f"run to another folder (--out) or remove the old results")


def _ensemble(summary: RunSummary, exp: Experiment, out: Path, queue, log) -> Path | None:
    """The run's ensemble correlation; kept as it is when no pair was added since it was
    made (a rerun that only skips finished pairs redoes nothing)."""
    made = out / "ensemble.npz"
    if not summary.processed and made.is_file():
        log(f"ensemble correlation: no new pair, {made} kept")
        return made
    from .ensemble_field import ensemble_field

    return ensemble_field(out, exp["images"]["dt_s"], queue, exp["output"]["vti"], log)


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
    summary.sources = {k: field_metadata(path).get("sources", {}) for k, path in fields}
    ensemble = None
    if fields and exp["piv"]["ensemble"] and not summary.interrupted:
        ensemble = _ensemble(summary, exp, out, queue, log)
        summary.ensemble = None if ensemble is None else str(ensemble)
    if fields:
        store = write_timeseries(out / "timeseries.zarr",
                                 [(k, k * interval if interval else float(k), p)
                                  for k, p in fields], "s" if interval else "pair",
                                 ensemble=ensemble)
        summary.store = str(store)
        summary.figures = _figures(store, out / "figures", log)
    write_json(out / "summary.json", asdict(summary))
    log(f"{done} pair(s) processed ({summary.seconds_per_pair:.1f} s each), "
        f"{len(summary.skipped)} already done, {len(summary.failed)} failed"
        + (f": {summary.failed}" if summary.failed else "")
        + (f", {len(summary.gaps)} not made for missing frames" if summary.gaps else "")
        + (f"; {len(fields)} in {out / 'timeseries.zarr'}" if fields else ""))
