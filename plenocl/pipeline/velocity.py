"""Two volumes to their velocity field: the one composition that :func:`process_pair`,
the ``plenocl piv`` command and the boundary-layer demo share (issue 48).

:func:`refined_field` correlates the volumes (:func:`plenocl.piv3d`) and, with the
particle switch, refines the field by the volumes' matched particles
(:func:`refine_particles`): with a camera, by its focal zone and lines of sight
(docs/design.md §7.1, §7.4), and with the raw images, each particle first fitted to its
image (§7.2).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

from ..camera import Camera
from ..grid import Grid
from ..opencl.device import DeviceLike, get_queue
from ..piv import PIVResult, piv3d
from ..piv.devicemeans import DeviceWindowMeans
from ..piv.devicepeaks import DeviceMaxima
from ..piv.imagefit import ImageFit
from ..piv.jointfit import JointImageFit
from ..piv.refinement import (
    DEPTH_SUPPORT,
    SPREAD,
    FocalZone,
    SightLines,
    refine_with_particles,
)
from .settings import PairSettings

__all__ = ["StageClock", "refine_particles", "refined_field"]


class StageClock:
    """The wall time of each stage of a pair: ``seconds`` per stage name, and its
    ``spans`` (start and end on :func:`time.perf_counter`'s clock)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.spans: dict[str, tuple[float, float]] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as stage ``name``."""
        start = time.perf_counter()
        yield
        end = time.perf_counter()
        self.seconds[name], self.spans[name] = end - start, (start, end)


def refined_field(vol_a, vol_b, grid: Grid, settings: PairSettings, queue: DeviceLike = None,
                  *, camera: Camera | None = None, raws=None, backgrounds=None,
                  clock: StageClock | None = None, on_device: tuple | None = None,
                  background_free=None) -> PIVResult:
    """The velocity field of two volumes: ``settings.piv``'s correlation, refined by the
    particles (:func:`refine_particles`) where ``settings.particles`` asks.

    Parameters
    ----------
    vol_a, vol_b
        The two volumes ``(nz, ny, nx)`` on ``grid``.
    grid
        Their grid.
    settings
        The pair's settings (:class:`plenocl.pipeline.PairSettings`: ``piv``,
        ``particles``, ``image_fit``).
    queue
        Where PIV's deformation, predictor and sums, the image fit and the refinement's
        local maxima and tube sums run (``None``: the default device; ``False``: the
        host).
    camera, raws, backgrounds
        As :func:`refine_particles`.
    clock
        The :class:`StageClock` timing the stages ``piv`` and ``particles``.
    on_device
        The volumes' float32 device copies on ``queue``'s context (the reconstructions'
        ``info.volume_on_device``), read by both stages instead of uploading the volumes
        (:func:`plenocl.piv3d`, :func:`refine_particles`); ``None``: none.
    background_free
        As :func:`refine_particles`.
    """
    clock = clock or StageClock()
    with clock.stage("piv"):
        res = piv3d(vol_a, vol_b, settings.piv, queue=queue, on_device=on_device)
    return refine_particles(res, vol_a, vol_b, grid, settings, queue, camera=camera,
                            raws=raws, backgrounds=backgrounds, clock=clock,
                            on_device=on_device, background_free=background_free)


def refine_particles(res: PIVResult, vol_a, vol_b, grid: Grid, settings: PairSettings,
                     queue: DeviceLike = None, *, camera: Camera | list | None = None,
                     raws=None, backgrounds=None, clock: StageClock | None = None,
                     spread: float | None = SPREAD, weighted: bool = True,
                     depth_support: float = DEPTH_SUPPORT, on_device: tuple | None = None,
                     background_free=None) -> PIVResult:
    """``res`` refined by the volumes' matched particles
    (:func:`plenocl.piv.refinement.refine_with_particles`) where ``settings.particles``
    asks, timed as the stage ``particles``; ``res`` itself otherwise.

    Parameters
    ----------
    camera
        The (calibrated) camera: its focal zone (the depth uncertainty's systematic
        term) and lines of sight (a particle's peaks merged and centred along its line).
        ``None``: neither. A list: several cameras (docs/design.md §6.7), whose joint
        fit (:class:`plenocl.piv.jointfit.JointImageFit`) refines the particles; no
        focal zone or line of sight then (depth is seen).
    raws
        The two raw images the volumes were reconstructed from: with ``camera`` and
        ``settings.image_fit``, each particle is first fitted to its image
        (:class:`plenocl.piv.imagefit.ImageFit`). ``None``: the volumes' peaks as they
        are. Several cameras: per camera, its two raw images.
    backgrounds
        The ``(median, noise)`` each reconstruction removed (``None``: the fit estimates
        them); several cameras: per camera, its two or ``None``.
    spread, weighted, depth_support
        The pairs each window keeps (:func:`plenocl.piv.refinement.near_median`;
        ``None``: all within the search range), whether the window means weigh them
        by their fits' uncertainties (:func:`plenocl.piv.refinement.pair_weights`), and
        the depth's support in windows (one camera's;
        :data:`plenocl.piv.refinement.DEPTH_SUPPORT`);
        :func:`plenocl.piv.refinement.refine_with_particles`.
    on_device
        The volumes' float32 device copies (:func:`refined_field`), which the local
        maxima and tube sums on that device read.
    background_free
        One camera: the two raw images with their ``backgrounds`` removed as the
        reconstructions' solvers read them (their ``info.background_free``,
        :class:`plenocl.optics.rawimage.ScaledImage`; a ``None`` entry: removed here),
        for the image fit, which reads their device copies where on ``queue``'s context
        (:class:`plenocl.piv.imagefit.ImageFit`); ``None``: removed here.
    """
    if not settings.particles:
        return res
    clock = clock or StageClock()
    with clock.stage("particles"):
        fit = focus = sight = None
        device = None if queue is False else get_queue(queue)  # None: the host
        maxima = None if device is None else DeviceMaxima(device)
        device_means = (DeviceWindowMeans(device) if device is not None
                        and DeviceWindowMeans.supports(device) else None)
        if isinstance(camera, (list, tuple)):  # several cameras: their joint fit
            if raws is not None and settings.image_fit is not None:
                fit = JointImageFit(camera, grid, raws, settings.image_fit, queue=device,
                                    backgrounds=backgrounds)
        elif camera is not None:
            if raws is not None and settings.image_fit is not None:
                fit = ImageFit(camera, grid, raws, settings.image_fit, queue=device,
                               backgrounds=backgrounds, background_free=background_free)
            # the focal zone lies along the grid's z: a posed camera's is tilted in the
            # world grid, so its pairs are not told apart by it (docs/design.md §5.5)
            focus = FocalZone.along_grid(camera, grid)
            sight = SightLines.of(camera, grid, device)
        res = refine_with_particles(res, vol_a, vol_b, focus=focus, fit=fit, sight=sight,
                                    maxima=maxima, spread=spread, weighted=weighted,
                                    depth_support=depth_support, device_means=device_means,
                                    on_device=on_device)
    return res
