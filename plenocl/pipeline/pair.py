"""One image pair through the whole chain: the default processing a user (or a batch
run) applies to each pair of raw images (docs/design.md §9).

:func:`process_pair` preprocesses and reconstructs both exposures with one projector
(its sensitivity and kernels are reused) and correlates the volumes. The steps stay
available on their own (:func:`plenocl.reconstruct`, :func:`plenocl.piv3d`).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..opencl.device import is_cpu
from ..opencl.pool import settle
from ..opencl.threads import thread_count
from ..opencl.volume import host_volume
from ..options import with_keywords
from ..piv import PIVResult, piv3d
from ..reconstruction import (
    ProjectionOperator,
    ReconstructionInfo,
    ReconstructionSettings,
    UnusableImageError,
    prepare_on_host,
    prepares_on_device,
    run_reconstruction,
)
from .mte import motion_tracking_enhancement
from .settings import PairSettings
from .velocity import StageClock, refine_particles, refined_field

if TYPE_CHECKING:
    import pyopencl as cl


@dataclass
class PairResult:
    """What :func:`process_pair` made of one image pair.

    Attributes
    ----------
    vol_a, vol_b
        The reconstructed volumes ``(nz, ny, nx)`` (image intensity units, host arrays);
        ``None`` where :func:`process_pair` was asked for the vectors alone
        (``volumes=False``: the volumes then never come back from the device).
    piv
        The displacement field between them (voxels; :class:`plenocl.PIVResult`).
    info_a, info_b
        What each reconstruction did (iterations, residuals, time).
    seconds
        Wall time per stage: ``reconstruct_a``, ``reconstruct_b``, ``piv`` (the
        single-frame correlation), ``mte`` (every cycle, its correlations included) and
        ``particles`` (the particle refinement, the fit to the raw images included).
    spans
        Each stage's ``(start, end)`` on :func:`time.perf_counter`'s clock (what a
        profile attributes to it: :class:`plenocl.bench.clprofile.OpenCLProfile`).
    """

    vol_a: np.ndarray | None
    vol_b: np.ndarray | None
    piv: PIVResult
    info_a: ReconstructionInfo
    info_b: ReconstructionInfo
    seconds: dict[str, float] = field(default_factory=dict)
    spans: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def dropped(self) -> int:
        """The particles the fit to the raw images dropped (their fit left the grid or
        was not finite; docs/design.md §7.2): ``piv.refinement["dropped"]``, 0 without
        the fit."""
        return int(self.piv.refinement.get("dropped", 0))


def process_pair(raw_a, raw_b, projector: ProjectionOperator,
                 settings: PairSettings | None = None, *, volumes: bool = True,
                 **parts) -> PairResult:
    """Reconstruct two raw images with one projector and correlate the volumes.

    Parameters
    ----------
    raw_a, raw_b
        The raw images of the two exposures (``(rows, cols)`` of the projector's camera).
    projector
        A :class:`plenocl.Projector` (or any
        :class:`plenocl.reconstruction.ProjectionOperator`), reused for both images.
    settings
        Every option of the chain (:class:`plenocl.pipeline.PairSettings`; ``None``: its
        defaults). Its parts may instead be given as keywords (``reconstruction=``,
        ``piv=``, ``mte=``, ``particles=``, ``image_fit=``), which build one; keywords
        that differ from a given ``settings`` are an error. The parts:

        - ``reconstruction``: by default :func:`plenocl.reconstruct`'s
          (:class:`~plenocl.reconstruction.ReconstructionSettings`' defaults): MLEM, the
          median background removed and pixels within 4 noise deviations of it dark,
          on 3 x 3 lateral sub-voxels per voxel (``supersample=3``, docs/design.md
          §6.4: the depth error falls two- to threefold), coarse-to-fine (§6.5): 4
          iterations on the voxels, then 7 over-relaxed ones (μ = 1.5) on the
          sub-voxels within the coarse volume's support.
        - ``piv``: :func:`plenocl.piv3d`'s options (by default the windows are fitted to
          the volume's shape); the volumes are deformed on the projector's device.
        - ``mte``: motion-tracking enhancement: after the single-frame volumes and their
          correlation, ``mte.cycles`` times warp each volume onto the other exposure's
          time, combine, reconstruct again from that guess and correlate (off by
          default).
        - ``particles``: refine the correlation's final field with the volumes'
          particles (:func:`plenocl.piv.refinement.refine_with_particles`,
          docs/design.md §7.1): each window's displacement becomes the mean of its
          matched particle pairs, and its uncertainty their standard error with the
          systematic depth term of the pairs near the camera's focal plane, whose depth
          is not measured. ``False``: the correlation's field.
        - ``image_fit``: before pairing, refine each volume's particles against its raw
          image (:class:`plenocl.piv.imagefit.ImageFit`, docs/design.md §7.2): at the
          paper's optics the vectors' depth error of uniform displacements falls by
          9-56 % and the lateral by 10-58 % (``benchmarks/accuracy.py``), for 2-32 s
          more per pair on 2 CPU cores. ``None`` (or ``False``): the volumes' peaks as
          they are.
    volumes
        Return the volumes (``True``, the default). ``False``: the vectors alone
        (``vol_a``, ``vol_b`` ``None``): the volumes stay on the device from the
        reconstructions to the particles, where only their summaries and the particles'
        neighbourhoods are read (docs/design.md §7.5), and are never copied to the host
        whole unless a stage measured faster on the host needs them (the first pass's
        FFT on a CPU device).

    Returns
    -------
    PairResult
        Both volumes (when asked), the displacement field, the reconstructions' info and
        stage times.
    """
    settings = with_keywords(PairSettings, settings, parts, "process_pair")
    if isinstance(projector, (list, tuple)):  # several cameras (docs/design.md §6.7)
        return _asked(_several_cameras(raw_a, raw_b, list(projector), settings), volumes,
                      projector[0].queue)
    rec = settings.reconstruction
    clock = StageClock()
    (vol_a, info_a), (vol_b, info_b) = _reconstructions(raw_a, raw_b, projector, rec,
                                                        not settings.mte.cycles, clock)
    if not settings.mte.cycles:
        try:
            known = known_backgrounds(info_a, info_b)
            res, _ = correlate_volumes(raw_a, raw_b, vol_a, vol_b, projector, settings,
                                       known, clock, on_device=kept_on_device(info_a, info_b),
                                       background_free=None if known is None else [
                                           info_a.background_free, info_b.background_free])
        finally:  # the result holds no device memory and no extra images
            for info in (info_a, info_b):
                info.release_kept()
        return _asked(PairResult(vol_a, vol_b, res, info_a, info_b, clock.seconds,
                                 clock.spans), volumes, projector.queue)

    def correlate(a, b) -> PIVResult:
        return piv3d(a, b, settings.piv, queue=projector.queue)

    with clock.stage("piv"):
        res = correlate(vol_a, vol_b)
    with clock.stage("mte"):
        vol_a, vol_b, res, infos, _ = motion_tracking_enhancement(
            raw_a, raw_b, projector, vol_a, vol_b, res, rec, settings.mte, correlate)
    info_a, info_b = infos
    res = refine_particles(res, vol_a, vol_b, projector.grid, settings, projector.queue,
                           camera=projector.camera, raws=(raw_a, raw_b),
                           backgrounds=known_backgrounds(info_a, info_b), clock=clock)
    return _asked(PairResult(vol_a, vol_b, res, info_a, info_b, clock.seconds, clock.spans),
                  volumes, projector.queue)


def _asked(result: PairResult, volumes: bool, queue: cl.CommandQueue) -> PairResult:
    """``result`` with its volumes on the host (``volumes``) or without them; either way
    it holds no device memory. ``queue``'s pool then settles (:func:`.pool.settle`)."""
    if volumes:
        result.vol_a, result.vol_b = host_volume(result.vol_a), host_volume(result.vol_b)
    else:
        result.vol_a = result.vol_b = None
    settle(queue)
    return result


def _reconstructions(raw_a, raw_b, projector, rec: ReconstructionSettings, keep: bool,
                     clock: StageClock) -> list[tuple[np.ndarray, ReconstructionInfo]]:
    """Both exposures' reconstructions, one after the other on the projector's queue.
    On a device that is not a CPU, the second image's host preparation (its checks,
    median, noise and scaling: NumPy, 0.3 s at paper size) runs on a helper thread while
    the first reconstructs, whose device leaves the host's cores idle (a camera's counts
    are prepared on the device instead, :mod:`plenocl.reconstruction.deviceimage`: the
    host only counts their levels); on a CPU device
    they are the device's, and a process allowed one thread (``PLENOCL_THREADS=1``, a
    batch's workers sharing the cores) has one, so there it runs in turn
    (docs/design.md §7.5)."""
    ahead = (None if is_cpu(projector.queue.device) or thread_count() < 2
             or prepares_on_device(raw_b, rec.background, rec.smooth_px, None) else
             ThreadPoolExecutor(1, thread_name_prefix="plenocl-prepare"))
    try:
        later = (None if ahead is None else
                 ahead.submit(prepare_on_host, raw_b, projector.camera, rec))
        return [_reconstruction(tag, raw, projector, rec, keep, clock, future)
                for tag, raw, future in (("a", raw_a, None), ("b", raw_b, later))]
    finally:
        if ahead is not None:
            ahead.shutdown(wait=True)


def _reconstruction(tag: str, raw, projector, rec: ReconstructionSettings, keep: bool,
                    clock: StageClock, later: Future | None
                    ) -> tuple[np.ndarray, ReconstructionInfo]:
    """One exposure's reconstruction (``later``: its host preparation, made ahead), its
    unusable image named by ``tag``."""
    with clock.stage(f"reconstruct_{tag}"):
        try:
            return run_reconstruction(raw, projector, rec, keep_for_next_stage=keep,
                                      ahead=None if later is None else later.result())
        except UnusableImageError as exc:
            raise UnusableImageError(f"raw_{tag}: {exc}", which=tag) from None


def _several_cameras(raws_a, raws_b, projectors: list, settings: PairSettings
                     ) -> PairResult:
    """:func:`process_pair` of several cameras (docs/design.md §6.7): each exposure
    reconstructed from every camera's image at once, the volumes correlated and refined
    by their particles, fitted to every camera's raw images at once
    (:class:`plenocl.piv.jointfit.JointImageFit`)."""
    for name, raws in (("raw_a", raws_a), ("raw_b", raws_b)):
        if not isinstance(raws, (list, tuple)) or len(raws) != len(projectors):
            raise ValueError(f"several cameras: {name} must be a list of one raw image per "
                             f"projector ({len(projectors)})")
    if settings.mte.cycles:
        raise ValueError("motion-tracking enhancement takes one camera; set mte cycles to "
                         "0 with several cameras")
    if len(projectors) == 1:
        return process_pair(raws_a[0], raws_b[0], projectors[0], settings)
    clock, out = StageClock(), {}
    for tag, raws in (("a", raws_a), ("b", raws_b)):
        with clock.stage(f"reconstruct_{tag}"):
            try:
                out[tag] = run_reconstruction(list(raws), projectors, settings.reconstruction)
            except UnusableImageError as exc:
                raise UnusableImageError(f"raw_{tag}: {exc}", which=tag) from None
    (vol_a, info_a), (vol_b, info_b) = out["a"], out["b"]
    known = [known_backgrounds(*pair) for pair in zip(info_a.cameras, info_b.cameras,
                                                        strict=True)]
    res, _ = correlate_volumes(raws_a, raws_b, vol_a, vol_b, projectors, settings, known,
                               clock)
    return PairResult(vol_a, vol_b, res, info_a, info_b, clock.seconds, clock.spans)


def correlate_volumes(raw_a, raw_b, vol_a, vol_b, projector: ProjectionOperator,
                      settings: PairSettings, backgrounds: list | None = None,
                      clock: StageClock | None = None, on_device: tuple | None = None,
                      background_free=None) -> tuple[PIVResult, dict[str, float]]:
    """The chain of :func:`process_pair` after its reconstruction, on two volumes made
    earlier (a batch rerun whose PIV settings changed reuses its kept volumes).

    Parameters
    ----------
    raw_a, raw_b
        The raw images the volumes were reconstructed from (the particles' fit to them);
        several cameras: each a list, camera by camera.
    vol_a, vol_b
        The two volumes, as :func:`process_pair` made them.
    projector, settings
        As :func:`process_pair`'s (several cameras: a list of projectors);
        motion-tracking enhancement (``settings.mte.cycles``) remakes the volumes, so it
        is refused here.
    backgrounds
        The ``(median, noise)`` each reconstruction removed (``None``: the fit estimates
        them), as :class:`plenocl.piv.imagefit.ImageFit` takes them; several cameras:
        per camera such a list or ``None``.
    clock
        The :class:`StageClock` to time the stages on (``None``: a new one).
    on_device
        The volumes' float32 device copies on the projector's queue (one camera;
        :func:`kept_on_device`), read instead of uploading the volumes again
        (:func:`plenocl.pipeline.velocity.refined_field`); ``None``: none.
    background_free
        One camera: the raw images with their ``backgrounds`` removed as the
        reconstructions' solvers read them (their ``info.background_free``,
        :class:`plenocl.optics.rawimage.ScaledImage`, with the device copies), for the
        image fit neither to remove them again nor to upload them; ``None``: removed
        there.

    Returns
    -------
    (PIVResult, dict)
        The field and the seconds of ``piv`` and ``particles`` (with any stages
        ``clock`` timed before).
    """
    if settings.mte.cycles:
        raise ValueError("correlate_volumes: motion-tracking enhancement remakes the "
                         "volumes; use process_pair")
    clock = clock or StageClock()
    if isinstance(projector, (list, tuple)):  # several cameras: their joint fit
        first = projector[0]
        res = refined_field(vol_a, vol_b, first.grid, settings, first.queue,
                            camera=[p.camera for p in projector],
                            raws=[[a, b] for a, b in zip(raw_a, raw_b, strict=True)],
                            backgrounds=backgrounds, clock=clock)
    else:
        res = refined_field(vol_a, vol_b, projector.grid, settings, projector.queue,
                            camera=projector.camera, raws=(raw_a, raw_b),
                            backgrounds=backgrounds, clock=clock, on_device=on_device,
                            background_free=background_free)
    return res, clock.seconds


def kept_on_device(*infos: ReconstructionInfo) -> tuple | None:
    """The reconstructions' device volumes (``info.volume_on_device``), ``None`` unless
    every one kept its volume there."""
    kept = tuple(info.volume_on_device for info in infos)
    return None if any(dev is None for dev in kept) else kept


def known_backgrounds(*infos: ReconstructionInfo) -> list | None:
    """The median and noise the reconstructions removed from the raw images, for the
    particle fit to reuse (``None`` when a reconstruction removed none)."""
    known = [(info.background, info.noise) for info in infos]
    return None if any(med is None for med, _ in known) else known
