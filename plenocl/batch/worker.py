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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import load_camera
from ..device import DeviceLike
from ..grid import Grid
from ..io.files import read_image, write_volumes
from ..pipeline import PairSettings, process_pair
from ..pipeline.frames import load_frame
from ..reconstruction import UnusableImageError
from ..vectorfile import save_field
from .layout import pair_index, volume_file
from .pairing import fingerprint

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
    vti
        Also write a ParaView ``.vti`` per pair.
    keep_volumes
        Keep each pair's volumes beside its field (for the ensemble correlation).
    channel, dark, flat
        The frames' colour channel, and the absolute paths of the dark frame and flat
        field (``None``: none).
    """

    pair: PairSettings
    dt_s: float
    vti: bool = False
    keep_volumes: bool = False
    channel: str | None = None
    dark: str | None = None
    flat: str | None = None


@dataclass(frozen=True)
class PairTask:
    """One pair to process: its index, its two images and the field file to write."""

    index: int
    image_a: str
    image_b: str
    target: str


@dataclass
class PairOutcome:
    """What became of a :class:`PairTask`: ``error`` is None when the field was written."""

    index: int
    seconds: dict
    error: str | None = None


class PairProcessor:
    """Processes pairs of one run; see the module notes.

    Parameters
    ----------
    run_folder
        The run's output folder, holding ``camera_used.toml`` and ``grid_used.toml``
        (written by :func:`plenocl.batch.run` before any pair).
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
        self.camera = load_camera(folder / "camera_used.toml")
        self.grid = Grid.from_toml(folder / "grid_used.toml")
        self.dark, self.flat = (read_image(path, settings.channel) if path else None
                                for path in (settings.dark, settings.flat))
        self.device = device
        self._projector = None

    @property
    def projector(self):
        """The projector of every pair, made on first use."""
        if self._projector is None:
            from ..projection import Projector

            self._projector = Projector(self.camera, self.grid, self.device)
        return self._projector

    def __call__(self, task: PairTask) -> PairOutcome:
        """Process one pair and write its field atomically; a bad pair's error is
        returned, not raised, so that the run goes on."""
        t0 = time.perf_counter()
        try:
            raw_a, raw_b = self.frame(task.image_a), self.frame(task.image_b)
            sources = {"a": fingerprint(Path(task.image_a)),
                       "b": fingerprint(Path(task.image_b))}
            seconds = {"read": time.perf_counter() - t0}
            seconds.update(self._process(raw_a, raw_b, Path(task.target), sources))
        except PAIR_ERRORS as exc:
            return PairOutcome(task.index, {}, f"{_culprit(task, exc)}: {exc}")
        return PairOutcome(task.index, seconds)

    def frame(self, path: str) -> np.ndarray:
        """One raw frame as the camera sees it: its colour channel, the dark frame and
        flat field of the experiment, the camera's region of interest."""
        return load_frame(path, self.camera, self.settings.channel, self.dark, self.flat)

    def _process(self, raw_a, raw_b, target: Path, sources: dict) -> dict:
        run = self.settings
        pair = process_pair(raw_a, raw_b, self.projector, run.pair)
        t0 = time.perf_counter()
        if run.keep_volumes:  # for the ensemble correlation at the end of the run
            write_volumes(volume_file(target), pair.vol_a, pair.vol_b)
        if run.vti:
            save_field(target.with_suffix(".vti"), pair.piv, dt=run.dt_s, grid=self.grid)
        # the .npz last: its presence marks the pair done; it names the two source files
        save_field(target, pair.piv, dt=run.dt_s, grid=self.grid,
                   metadata={"sources": sources, "pair": pair_index(target)})
        return {**pair.seconds, "write": time.perf_counter() - t0}


def _culprit(task: PairTask, exc: Exception) -> str:
    """The file a pair's error comes from: the image a reconstruction refused, else
    both of the pair's."""
    which = exc.which if isinstance(exc, UnusableImageError) else None
    names = {"a": Path(task.image_a).name, "b": Path(task.image_b).name}
    return names[which] if which in names else f"{names['a']} + {names['b']}"
