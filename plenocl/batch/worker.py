"""One pair of a batch, from file paths to a written vector field: the unit of work of
:func:`plenocl.batch.run`, the same in a serial run and on a Dask worker.

A :class:`PairProcessor` is made once per process (per Dask worker: by the worker plugin
of :mod:`plenocl.batch.cluster`) from the run folder (the camera and grid the run wrote
there) and the run's :class:`RunSettings`, an object (pickled to each Dask worker; no
file is read back for it). It builds its OpenCL context and projector on the
first pair and reuses them (sensitivity and compiled kernels included) for every other.
Tasks carry only a :class:`PairTask` (file paths), never contexts or volumes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import load_camera
from ..grid import Grid
from ..io.fieldformat import field_metadata
from ..io.files import read_volumes, volumes_metadata, write_volumes
from ..io.outputs import disk_full
from ..opencl.device import DeviceLike, device_label
from ..pipeline import PairSettings, process_pair
from ..pipeline.frames import load_corrections, load_frame
from ..pipeline.pair import correlate_volumes, known_backgrounds
from ..reconstruction import UnusableImageError
from ..vectorfield import PIVResult, read_npz, save_field
from .layout import field_copies, pair_index, volume_file
from .pairing import ImagePair, pair_sources
from .prepare import camera_files
from .record import CORRELATE, field_record

#: The exceptions a bad pair raises (unreadable, wrong size, NaN, ...): logged, skipped.
PAIR_ERRORS = (ValueError, OSError, TypeError)


@dataclass(frozen=True)
class RunSettings:
    """What every pair of a run shares (:func:`plenocl.batch.run` makes it from the
    experiment file).

    Attributes
    ----------
    pair
        The chain's settings (:class:`plenocl.pipeline.PairSettings`).
    dt_s
        Time between the two exposures of a pair (s).
    formats
        The suffixes each pair's field is also written in beside its ``.npz``
        (``".vti"``, ``".h5"``, ``".dat"``, ``".csv"``;
        :func:`plenocl.batch.config.output_formats`).
    keep_volumes
        Keep each pair's volumes beside its field (for the ensemble correlation).
    channel, dark, flat
        The frames' colour channel, and the absolute paths of the dark frame and flat
        field (``None``: none).
    record
        The run's record (:func:`plenocl.batch.record.run_record`), written with each
        pair's field (``{}``: none, outside a run).
    cameras
        The run's cameras (several: one joint reconstruction of every camera's images,
        docs/design.md §6.7; their files :func:`plenocl.batch.prepare.camera_files`).
    """

    pair: PairSettings
    dt_s: float
    formats: tuple[str, ...] = ()
    keep_volumes: bool = False
    channel: str | None = None
    dark: str | None = None
    flat: str | None = None
    record: dict = field(default_factory=dict)
    cameras: int = 1


@dataclass(frozen=True)
class PairTask:
    """One pair to process: its index, its two images and the field file to write;
    ``mode`` :data:`~plenocl.batch.record.CORRELATE` correlates its kept volumes again
    instead of reconstructing (``"pair"``: the whole chain); several cameras: the first
    camera's two images, and ``others`` the other cameras' ``(a, b)`` in their order."""

    index: int
    image_a: str
    image_b: str
    target: str
    mode: str = "pair"
    others: tuple[tuple[str, str], ...] = ()

    @property
    def pair(self) -> ImagePair:
        """The task's images as an :class:`~plenocl.batch.pairing.ImagePair`."""
        return ImagePair(self.index, Path(self.image_a), Path(self.image_b),
                         tuple((Path(a), Path(b)) for a, b in self.others))


@dataclass
class PairOutcome:
    """What became of a :class:`PairTask`: ``error`` is None when the field was written;
    ``dropped``: the particles the fit to the raw images dropped
    (:attr:`plenocl.pipeline.PairResult.dropped`); ``disk_full``: the error was the
    output disk out of space (the run stops: no later pair could be written);
    ``device``: the device that made it (:func:`plenocl.opencl.device.device_label`)."""

    index: int
    seconds: dict
    error: str | None = None
    dropped: int = 0
    disk_full: bool = False
    device: str = ""


@dataclass
class ReadFrames:
    """A pair's raw frames read from their files (``frames``: the two frames, or for
    several cameras the two lists), the seconds it took, or the error reading raised."""

    frames: tuple | None
    seconds: float
    error: Exception | None = None


class PairProcessor:
    """Processes pairs of one run; see the module notes.

    Parameters
    ----------
    run_folder
        The run's output folder, holding ``camera_used.toml`` (several cameras: each
        ``camera_K_used.toml``) and ``grid_used.toml`` (written by
        :func:`plenocl.batch.run` before any pair).
    settings
        What every pair of the run shares.
    device
        OpenCL device of this process (:func:`plenocl.get_queue` rules: by default
        ``PYOPENCL_CTX``, else a GPU, else a CPU).
    """

    def __init__(self, run_folder: str | Path, settings: RunSettings,
                 device: DeviceLike = None) -> None:
        folder = Path(run_folder)
        self.settings = settings
        self.cameras = [load_camera(folder / name) for name in camera_files(settings.cameras)]
        self.camera = self.cameras[0]
        self.grid = Grid.from_toml(folder / "grid_used.toml")
        self.dark, self.flat = load_corrections(settings.dark, settings.flat, self.cameras,
                                                settings.channel)
        self.device = device
        self._projector = None
        self._label: str | None = None

    @property
    def projector(self):
        """The projector of every pair, made on first use; several cameras: the list of
        theirs, on one queue."""
        if self._projector is None:
            from ..opencl.device import get_queue
            from ..projection import Projector

            if len(self.cameras) == 1:
                self._projector = Projector(self.camera, self.grid, self.device)
            else:
                queue = get_queue(self.device)
                self._projector = [Projector(c, self.grid, queue) for c in self.cameras]
        return self._projector

    def __call__(self, task: PairTask, read: ReadFrames | None = None) -> PairOutcome:
        """Process one pair and write its field atomically; a bad pair's error is
        returned, not raised, so that the run goes on. ``read``: the pair's frames read
        beforehand (:meth:`read`, a serial run reading the next pair while this one
        computes); ``None``: read here."""
        read = self.read(task) if read is None else read
        try:
            if read.error is not None:
                raise read.error
            sources = pair_sources(task.pair)
            seconds = {"read": read.seconds}
            done, dropped = self._process(*read.frames, Path(task.target), sources,
                                          task.mode)
            seconds.update(done)
        except PAIR_ERRORS as exc:
            return PairOutcome(task.index, {}, f"{_culprit(task, exc)}: {_said(exc, task)}",
                               disk_full=disk_full(exc))
        return PairOutcome(task.index, seconds, dropped=dropped, device=self.device_label())

    def device_label(self) -> str:
        """The label of this processor's device (:func:`plenocl.opencl.device.device_label`),
        found once."""
        if self._label is None:
            projector = self.projector
            queue = (projector if not isinstance(projector, list) else projector[0]).queue
            self._label = device_label(queue.device)
        return self._label

    def read(self, task: PairTask) -> ReadFrames:
        """The pair's raw frames as :meth:`__call__` takes them, or the error that
        reading them raised (a pair's error, named when the pair is processed)."""
        t0 = time.perf_counter()
        try:
            frames = self._frames(task)
        except PAIR_ERRORS as exc:
            return ReadFrames(None, time.perf_counter() - t0, exc)
        return ReadFrames(frames, time.perf_counter() - t0)

    def frame(self, path: str, camera: int = 0) -> np.ndarray:
        """One raw frame as camera ``camera`` (its index) sees it: its colour channel,
        the dark frame and flat field of the experiment, the camera's region of
        interest."""
        label = None if len(self.cameras) == 1 else _camera_file(camera, path)
        return load_frame(path, self.cameras[camera], self.settings.channel, self.dark,
                          self.flat, label=label)

    def _frames(self, task: PairTask):
        """The pair's two raw frames; several cameras: two lists, camera by camera."""
        if len(self.cameras) == 1:
            return self.frame(task.image_a), self.frame(task.image_b)
        files = [(task.image_a, task.image_b), *task.others]
        if len(files) != len(self.cameras):
            raise ValueError(f"pair {task.index} names {len(files)} camera(s)' images, the "
                             f"run has {len(self.cameras)} cameras")
        frames = [(self.frame(a, c), self.frame(b, c)) for c, (a, b) in enumerate(files)]
        return [f[0] for f in frames], [f[1] for f in frames]

    def _process(self, raw_a, raw_b, target: Path, sources: dict, mode: str
                 ) -> tuple[dict, int]:
        """The pair through the chain (or its kept volumes correlated again), its files
        written: seconds per stage and the particles the fit dropped."""
        run = self.settings
        meta = field_record(run.record, sources, pair_index(target))
        if mode == CORRELATE:  # the kept volumes, made with the run's volumes digest
            vol_a, vol_b = read_volumes(volume_file(target))
            known = volumes_metadata(volume_file(target)).get("backgrounds")
            res, seconds = correlate_volumes(raw_a, raw_b, vol_a, vol_b, self.projector,
                                             run.pair, known)
        else:
            pair = process_pair(raw_a, raw_b, self.projector, run.pair,
                                volumes=run.keep_volumes)
            res, seconds = pair.piv, pair.seconds
        t0 = time.perf_counter()
        if mode != CORRELATE and run.keep_volumes:  # for the ensemble correlation
            write_volumes(volume_file(target), pair.vol_a, pair.vol_b,
                          {"volumes": meta["digests"]["volumes"],
                           "backgrounds": pair_backgrounds(pair)})
        # the .npz names the two source files and carries the record of what made it
        save_with_copies(target, res, self.grid, run.dt_s, run.formats, meta)
        return ({**seconds, "write": time.perf_counter() - t0},
                int(res.refinement.get("dropped", 0)))


def rescale_field(target: Path, grid: Grid, settings: RunSettings) -> None:
    """A finished pair's field written again for the run's ``dt_s`` with the run's record
    (:func:`rewrite_field`)."""
    meta = field_record(settings.record, field_metadata(target)["sources"],
                        pair_index(target))
    rewrite_field(target, grid, settings.dt_s, settings.formats, meta)


def rewrite_field(target: Path, grid: Grid, dt: float, formats: tuple[str, ...],
                  metadata: dict) -> None:
    """A stored field written again for ``dt`` (its displacements, in voxels, are kept;
    the velocities follow) with ``metadata``; its copies too: those of ``formats`` and
    those already there (``.vti``, ``.dat``, ...)."""
    save_with_copies(target, read_npz(target)[0], grid, dt, formats, metadata)


def save_with_copies(target: Path, res: PIVResult, grid: Grid, dt: float,
                     formats: tuple[str, ...], metadata: dict) -> None:
    """A field's ``.npz`` ``target`` with ``metadata``, and its copies: those of
    ``formats`` and those already there. The ``.npz`` goes last: its presence marks the
    product done."""
    for copy in field_copies(target, formats):
        save_field(copy, res, dt=dt, grid=grid)
    save_field(target, res, dt=dt, grid=grid, metadata=metadata)


def add_copies(target: Path, grid: Grid, formats: tuple[str, ...]) -> list[str]:
    """The copies (``formats``, e.g. ``[output] formats``) a kept field lacks, written
    from its ``.npz``; the suffixes written."""
    missing = [s for s in formats if not target.with_suffix(s).is_file()]
    if missing:
        res, arrays = read_npz(target)
        for suffix in missing:
            save_field(target.with_suffix(suffix), res, dt=float(arrays["dt"]), grid=grid)
    return missing


def pair_backgrounds(pair) -> list | None:
    """The median and noise each reconstruction of a :class:`plenocl.pipeline.PairResult`
    removed, as kept volumes record them: ``[[median, noise], ...]`` per exposure, or
    per camera such a list (several cameras); ``None`` where one removed none."""
    infos = ([(pair.info_a, pair.info_b)] if not pair.info_a.cameras
             else list(zip(pair.info_a.cameras, pair.info_b.cameras, strict=True)))
    known = [known_backgrounds(*two) for two in infos]
    if any(k is None for k in known):
        return None
    lists = [[[float(v) for v in bg] for bg in k] for k in known]
    return lists if pair.info_a.cameras else lists[0]


def _said(exc: Exception, task: PairTask) -> str:
    """A pair's error as the run reports it: a full disk named with its folder and the
    fix (the pair was not written: a rerun makes it)."""
    if disk_full(exc):
        return (f"no space left on the disk of {Path(task.target).parent} ({exc}); free "
                "space there or give another output folder (--out): a rerun makes the "
                "pairs not written")
    return str(exc)


def _culprit(task: PairTask, exc: Exception) -> str:
    """The file a pair's error comes from: the image a reconstruction refused, else
    the pair's (several cameras: every camera's)."""
    which = exc.which if isinstance(exc, UnusableImageError) else None
    files = [(task.image_a, task.image_b), *task.others]
    named = (lambda c, f: Path(f).name) if len(files) == 1 else _camera_file
    names = {tag: " + ".join(named(c, f[i]) for c, f in enumerate(files))
             for i, tag in enumerate("ab")}
    return names[which] if which in names else f"{names['a']} + {names['b']}"


def _camera_file(camera: int, path) -> str:
    """A frame named with its camera (index ``camera`` from 0): several cameras' folders
    may hold the same file names."""
    return f"camera {camera + 1}'s {Path(path).name}"
