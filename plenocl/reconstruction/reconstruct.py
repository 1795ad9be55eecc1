"""Reconstruction of a particle volume from one plenoptic image (docs/design.md §6).

Methods (all multiplicative, non-negative, on the device):

``"mlem"`` (default)
    Multiplicative EM, ``E ← E (Wᵀ r / s)^μ``: each voxel moves by the arithmetic mean of
    the ratios ``r = I / P`` of the pixels it reaches. It keeps in-focus particles,
    which light a single microlens, where geometric-mean updates lose them.
``"smart"``
    Simultaneous MART, ``E ← E exp(μ Wᵀ log r / s)``: the geometric mean.
``"mart"``
    The paper's MART, ``E_j ← E_j Π_i r_i^(μ w_ij)``, in block-sequential order: pixels
    are grouped by sub-aperture view (``mart_blocks`` interleaved groups of the pixel's
    offset behind its microlens), and each block updates the volume with a fresh
    projection. One block per pixel is the sequential original.

``s_j = Σ_i w_ij`` is the fraction of a voxel's light that reaches the sensor. The
image is scaled to a maximum of 1 inside the solver (dynamic range) and the volume
scaled back. Options (:class:`ReconstructionSettings`, validated once): lateral
sub-voxels and coarse-to-fine on them (the default; ``supersample=1``: the voxels
themselves), MLOS first guess, pixel threshold, zero-pixel masking, active slices,
cropping, dark-microlens skipping, early stop; a progress callback.

The solver needs of a projector only the operator contract
(:class:`plenocl.reconstruction.operator.ProjectionOperator`).
"""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings
import weakref
from collections.abc import Callable

import numpy as np
import pyopencl.array as cla

from ..opencl.volume import DeviceVolume, host_volume
from ..optics.rawimage import check_pixel_mask
from ..options import with_keywords
from .blocks import device_view_blocks
from .images import PreparedImage, prepare_image
from .joint import run_joint
from .operator import FramedOperator, PlannedOperator, ProjectionOperator
from .schedule import SupportStart, sampled_operator, support_on_device
from .settings import ReconstructionInfo, ReconstructionSettings
from .solver import OUTSIDE_WARN, UPDATES, Solver, check_start_volume
from .supersample import bin_lateral

#: A sub-voxel run's first guess from a coarser grid: the coarse start (a host volume or a
#: coarse run's support) and the lateral factor.
Spread = tuple[np.ndarray | SupportStart, int]


def _iterate(solver: Solver, vol, img, settings: ReconstructionSettings,
             info: ReconstructionInfo, step: Callable, callback, norm: float
             ) -> tuple[Solver, list]:
    """The iterations of :func:`reconstruct`; returns the solver they ended with (cropped
    or not) and its device volume."""
    for it in range(settings.iterations):
        cropping = settings.crop and it >= 1
        extent = solver.slice_extent(vol) if settings.skip_empty or cropping else None
        if cropping:
            solver, vol, extent = solver.crop(vol, extent)
            info.cropped_shape = solver.proj.grid.shape if solver.box else None
        active = extent[:, 1] >= 0 if settings.skip_empty else None
        if active is not None:
            info.active_slices.append(int(active.sum()))
        resid = step(solver, vol, img, active) / norm
        info.residuals.append(resid)
        info.iterations = it + 1
        if callback is not None and callback(it + 1, resid) is False:
            info.stopped = True
            break
        tol = settings.tol
        if tol is not None and it and abs(info.residuals[-2] - resid) < tol * resid:
            info.converged = True
            break
    solver.release_kept()
    return solver, vol


#: Per camera, the grid extents already checked (:func:`_warn_if_outside`).
_CHECKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _warn_if_outside(projector, solver: Callable[[], Solver], min_sensitivity: float
                     ) -> None:
    """Once per camera and grid extent: warn when much of the grid lies outside the field
    of view (``solver()``: a solver of ``projector``, made only when the extent is still
    to be checked). A voxel's sensitivity is the fraction of its light reaching the
    sensor, whatever its size, so the check of a coarse-to-fine reconstruction's coarse
    run stands for its sub-voxels too (the same extent on a finer grid; their
    sensitivities need not cross to the host)."""
    checked = _CHECKED.setdefault(projector.camera, set())
    key = _extent_key(projector.grid, min_sensitivity)
    if key in checked:
        return
    checked.add(key)
    fraction = solver().unseen_fraction()
    if fraction > OUTSIDE_WARN:
        warnings.warn(f"{fraction:.0%} of the grid's voxels send no more than "
                      f"{min_sensitivity:g} of their light to the sensor and are not "
                      "reconstructed: the grid reaches laterally beyond the camera's field "
                      "of view at its depths (the depths themselves are within those the "
                      "camera resolves: they were checked); narrow its x and y extents to that "
                      "field (plenocl.optics.depthrange.field_of_view_mm; Grid.for_camera and "
                      "plenocl grid fit it)", stacklevel=6)


def _extent_key(grid, min_sensitivity: float) -> tuple:
    """What :func:`_warn_if_outside` checks once per camera: a grid's extent."""
    return (tuple(grid.x), tuple(grid.y), tuple(grid.z), grid.rotation_deg,
            float(min_sensitivity))


def _check_frame_outside(projector, min_sensitivity: float) -> None:
    """:func:`_warn_if_outside` for a rotated array's projector, whose iterations run on
    its lens-row frame: the grid the user gave is checked (through the framed operator),
    not the frame's, whose padding beyond that grid's corners lies outside the field of
    view by construction (it warned of 36 % of a grid 0.6 % outside)."""
    _warn_if_outside(projector, lambda: Solver(projector, min_sensitivity), min_sensitivity)
    _CHECKED.setdefault(projector.camera, set()).add(
        _extent_key(projector.frame.grid, min_sensitivity))


def reconstruct(image, projector: ProjectionOperator, method: str | None = None,
                iterations: int | None = None, relax: float | None = None, *,
                settings: ReconstructionSettings | None = None,
                callback: Callable[[int, float], bool | None] | None = None,
                return_info: bool = False, pixel_mask=None, **keywords):
    """Reconstruct a particle volume from one raw plenoptic image.

    By default (no options) coarse-to-fine MLEM on sub-voxels (docs/design.md §6.5), the
    same reconstruction as :func:`plenocl.process_pair`, ``plenocl reconstruct`` and
    ``plenocl run`` (:class:`ReconstructionSettings`' defaults): 4 iterations on the
    voxels find the particles' support, then 7 over-relaxed iterations (μ = 1.5) on 3 x 3
    lateral sub-voxels per voxel within it, summed back onto the projector's grid. On
    the cubic 40³ case it recovers more particles than 30 iterations on the voxels
    themselves, in less time. ``supersample=1`` reconstructs on the voxels themselves
    (see ``supersample`` below).

    Parameters
    ----------
    image
        Raw image ``(rows, cols)`` matching the projector's camera; uint8, uint16 or float;
        finite and non-negative. Several cameras (docs/design.md §6.7): a list of images,
        one per camera, with a list of projectors in the same order; one volume from all
        of them (MLEM, SMART or block MART over every camera's pixels).
    projector
        A :class:`plenocl.Projector` for the camera and grid (its queue runs the solver),
        or any :class:`plenocl.reconstruction.operator.ProjectionOperator` (one that
        cannot refine its grid with ``supersample=1``); several cameras: their posed
        projectors, on one world grid and one queue.
    settings
        Every option from ``method`` to ``support`` below as one
        :class:`ReconstructionSettings` (``None``: the defaults). The options may instead
        be given as arguments and keywords, which build one; values that differ from a
        given ``settings`` are an error.
    method
        ``"mlem"`` (default), ``"smart"`` or ``"mart"`` (see the module documentation).
    iterations, relax
        Iterations (on the sub-voxels after the coarse ones) and relaxation
        ``0 < μ <= 1``; MLEM may be over-relaxed, ``0 < μ < 2``
        (``settings.MLEM_MAX_RELAX``; fewer iterations reach the same volume). Defaults:
        MLEM after coarse iterations 7 at μ = 1.5 (``settings.FINE_DEFAULTS``), else per
        method in :data:`DEFAULTS` (MLEM and SMART 30 at μ = 1; MART the paper's 15 at
        μ = 0.7), each option given taking the place of its default alone.
    start
        ``"uniform"`` (constant, scaled so its projection carries the image's intensity),
        ``"mlos"`` (weighted geometric mean of the pixels each voxel reaches), or a volume
        ``(nz, ny, nx)`` in image units: a previous frame's reconstruction, or an
        upsampled coarse one (its zero voxels stay zero); on sub-voxels it is given on the
        projector's grid, spread over the sub-voxels, and replaces the coarse iterations.
    background
        ``"median"`` (default): subtract the image's median (the camera's dark level) and
        clip at 0, as ``plenocl reconstruct`` does; ``None``: use the image as it is.
    threshold
        Pixels at or below ``threshold`` (same units as ``image``, after the background)
        count as dark (zero). ``None``: 4 times the noise (the median absolute deviation)
        with the median background, else 0.
    mask_fraction
        Zero-pixel masking: voxels sending more than this fraction of their light onto
        dark pixels start at zero and stay there (``0``: any dark pixel; ``None``: off).
    min_sensitivity
        Voxels that send no more than this fraction of their light to the sensor (at the
        edges of the field of view) are not reconstructed: the image barely constrains
        them, and light from particles outside the grid would pile up in them.
    skip_empty
        Active-slice compaction: before every iteration, depth slices with no non-zero
        voxel (after masking, or emptied by the updates) are left out of both
        projections. Exact: multiplicative updates never revive a zero voxel.
    crop
        Automatic cropping to the illuminated region: after every iteration, when
        the non-zero voxels fill a bounding box of at most 80 % of the current grid, the
        remaining iterations run on that box (active-voxel compaction between iterations;
        exact up to float32 rounding; ``info.cropped_shape``).
    skip_dark
        Dark-microlens skipping: the iterations project only onto the microlenses that
        see a pixel above ``threshold`` (``info.lit_lens_fraction``), and MLEM
        back-projects only from them. Exact: no ratio depends on the projection at a
        dark pixel, and MLEM's ratio is 0 there (the log ratios of SMART and MART are
        not, so they back-project from every lens). The residuals are then taken over
        the lit lenses' pixels.
    tol
        Stop early when the relative residual changes by less than ``tol``.
    mart_blocks
        MART only: ``n`` gives ``n²`` interleaved blocks of sub-aperture views.
    ratio_floor
        SMART and MART only: the ratios ``I / P`` whose logs update the volume are
        floored at this value in ``(0, 1)``; ``None`` (default): the literal methods (a
        floor of 1e-6, so a dark pixel multiplies each voxel it sees by
        ``exp(-13.8 μ w)``). A floor of 0.1-0.5 keeps in-focus particles whose voxel
        footprint reaches pixels the particle leaves dark (docs/design.md §6.2).
    supersample
        Reconstruct on ``supersample x supersample`` lateral sub-voxels per voxel
        (:meth:`plenocl.Projector.refined`) and sum them back onto the projector's grid
        (docs/design.md §6.4): particles are placed within a fraction of a microlens, which
        fixes their depth. Default 3; time and memory per iteration grow about as its
        square. ``supersample=1`` reconstructs on the voxels themselves, one grid, with
        the method's own iterations (MLEM 30 at μ = 1): a cheaper run with about 3x the
        depth error; the basis of the paper's MART and SMART, to compare with it; an
        operator that cannot refine its grid; a kernel or solver checked voxel by voxel
        against a reference; a ``start`` volume iterated on the voxels themselves.
    coarse_iterations, support
        Coarse-to-fine (``supersample > 1`` only; docs/design.md §6.5): first
        ``coarse_iterations`` (default 4) of MLEM, whatever the method (SMART's and
        MART's geometric mean on whole voxels loses particles the support needs:
        docs/design.md §6.2), on the voxels themselves; the voxels brighter
        than ``support`` (default 0.01) times the brightest, grown by one voxel, are the
        support, and the ``iterations`` on the sub-voxels start flat on it and never
        leave it (the back projection skips the zero voxels). ``0``: the sub-voxels start
        from ``start`` everywhere. ``info.support_fraction``: the grid's fraction it
        kept.
    coarse_oversample
        Aperture samples per pixel footprint of the coarse iterations (default
        ``COARSE_OVERSAMPLE``, 0.625: a quarter of the projector's samples, which finds
        the same support in a third of the time; :meth:`plenocl.Projector.sampled`, built
        once per projector); ``None`` or a value at or above the projector's own: the
        projector itself.
    early_iterations, early_oversample
        Coarse-to-fine: the first ``early_iterations`` (default 3, at most all but one)
        of the sub-voxel iterations run on the refined projector with the aperture
        sampled ``early_oversample`` times per pixel footprint (default 0.9: about half
        the samples), the rest on the refined projector itself from their volume;
        ``early_oversample=None`` or ``early_iterations=0``: all on the projector's own.
    lens_weights
        How an aperture sample's light is shared between lenses: ``"paper"`` (the
        paper's bilinear weights) or ``"extent"`` (the voxel's extent in each lens's
        cell; docs/design.md §6.4), on :meth:`plenocl.Projector.weighted`, built once per
        projector; ``None`` (default): the projector's own (``Projector(lens_weights=)``,
        the extent weights by default).
    smooth_px
        Smooth the raw image by a Gaussian of this standard deviation (pixels, up to
        ``settings.MAX_SMOOTH_PX``) after its median is removed and before it is
        thresholded (:func:`plenocl.reconstruction.images.smooth_image`); the default
        threshold follows the noise the smoothing leaves, and ``info.background`` and
        ``info.noise`` stay the raw image's; 0: no smoothing. ``None`` (default): the
        method's own (``settings.SMOOTH_DEFAULTS``): 1 px for SMART and MART, which
        keeps them from losing a noisy image's dim particle pixels to the dark threshold
        (docs/design.md §6.2), none for MLEM.
    callback
        Called as ``callback(iteration, residual)`` after each iteration; returning
        ``False`` stops the reconstruction. Coarse-to-fine: the coarse iterations come
        first and the fine ones go on counting (``settings.total_iterations`` in all);
        stopped during the coarse ones, the coarse volume is returned.
    return_info
        Also return a :class:`ReconstructionInfo`.
    pixel_mask
        Bool ``(rows, cols)``, ``False`` where the image holds no data (unrendered rows
        of a render, its alpha: :func:`plenocl.io.files.read_alpha`; a masked sensor
        defect): those pixels are left out (the reconstruction of the observed pixels
        alone), where a 0 in the image would say "dark"; voxels seen mostly by them are
        not constrained and stay 0. Not with ``start="mlos"``.

    Returns
    -------
    numpy.ndarray
        float32 volume ``(nz, ny, nx)`` in the image's intensity units; never NaN or Inf.
    """
    given = {"method": method, "iterations": iterations, "relax": relax}
    keywords.update({k: v for k, v in given.items() if v is not None})
    settings = with_keywords(ReconstructionSettings, settings, keywords, "reconstruct")
    vol, info = run_reconstruction(image, projector, settings, callback, pixel_mask)
    return (vol, info) if return_info else vol


def _refined(projector, factor: int):
    """The projector's operator on ``factor x factor`` lateral sub-voxels, refused with a
    clear error for an operator that cannot refine or a refined grid that does not fit."""
    if not hasattr(projector, "refined"):  # a RefinableOperator (see .operator)
        raise ValueError(f"supersample={factor} needs a projector that can refine its grid "
                         "(plenocl.Projector.refined); use supersample=1 with this operator")
    try:
        return projector.refined(factor)
    except MemoryError as err:
        raise MemoryError(f"{err}; supersample={factor} reconstructs on {factor * factor}x "
                          "the grid's voxels: a smaller factor (supersample=1, --supersample "
                          "1, is the grid itself) needs less") from err


def _weighted(projector, lens_weights: str | None):
    """The projector with ``lens_weights`` (:meth:`plenocl.Projector.weighted`; ``None``:
    itself), refused with a clear error for an operator that cannot change them."""
    if lens_weights is None:
        return projector
    if not hasattr(projector, "weighted"):  # a WeightedOperator (see .operator)
        raise ValueError(f"lens_weights={lens_weights!r} needs a projector that can change "
                         "its lens weights (plenocl.Projector.weighted); leave lens_weights "
                         "None with this operator")
    return projector.weighted(lens_weights)


def _coarse_start(start, grid) -> np.ndarray | None:
    """A start volume given on the grid (the fine run spreads it over the sub-voxels on
    the device), checked for its shape, its kind and that it can grow (every method
    multiplies its voxels: one at zero stays there); ``None`` for a named start."""
    if not isinstance(start, np.ndarray):
        return None
    check_start_volume(start, grid.shape)
    if not start.any():
        raise ValueError("start volume has no positive voxel (a start given, or the "
                         "combined volume of motion-tracking enhancement): the "
                         "multiplicative updates (MLEM, SMART, MART) cannot grow a voxel "
                         "from zero, so the result would be zero; give start='uniform' (the "
                         "default) or 'mlos'")
    return start


def _numbered(callback, offset: int):
    """``callback`` with the iterations numbered from ``offset + 1``: the fine run's
    iterations continue the coarse run's count."""
    if callback is None or not offset:
        return callback
    return lambda iteration, residual: callback(iteration + offset, residual)


def _supersampled(prepared: PreparedImage, projector, refined,
                  settings: ReconstructionSettings, callback, binned: bool = True
                  ) -> tuple[np.ndarray, ReconstructionInfo]:
    """The reconstruction on the refined grid, summed back onto the projector's on the
    device (``binned``; else the refined grid's volume); with ``coarse_iterations``, the
    coarse run on the voxels first (its iterations are the callback's first ones:
    docs/design.md §6.5; an empty or stopped coarse run returns the coarse grid's)."""
    f = settings.supersample
    start, support, done = _coarse_start(settings.start, projector.grid), None, 0
    if settings.coarse_iterations and start is None:
        coarse_settings = settings.coarse_run()
        sampled = sampled_operator(projector, settings.coarse_oversample)
        solver, vol, coarse_info = _iterations(
            prepared, projector if sampled is None else sampled, coarse_settings, callback)
        coarse = solver.binned_to_device(vol, 1, projector.grid.shape, prepared.scale)
        start = support_on_device(coarse, settings, solver.binning)  # the volume stays
        del solver, vol  # the coarse run's buffers, freed before the fine run
        support = 0.0 if start is None else start.fraction
        if not support:  # nothing to refine: the image holds no light (warned)
            coarse_info.support_fraction = coarse_info.active_fraction = 0.0
            return np.zeros(projector.grid.shape, np.float32), coarse_info
        if coarse_info.stopped:  # the callback stopped the reconstruction
            coarse_info.volume_on_device = coarse
            return _counted(DeviceVolume(coarse), coarse_info), coarse_info
        done = coarse_info.iterations
    fine = dataclasses.replace(settings, supersample=1, coarse_iterations=0,
                               start=settings.start if start is None else "uniform")
    factor = f if binned else 1
    if start is None:  # sub-voxels not binned (a frame's) are resampled on the host
        vol, info = _solve(prepared, refined, fine, _numbered(callback, done), factor=factor,
                           keep=binned)
    else:
        vol, info = _from_support(prepared, refined, fine, settings, _numbered(callback, done),
                                  factor, (start, f), keep=binned)
    info.supersample = f
    if support is not None:
        info.coarse_iterations, info.support_fraction = settings.coarse_iterations, support
    return vol, info


def _from_support(prepared: PreparedImage, refined, fine: ReconstructionSettings,
                  settings: ReconstructionSettings, callback, factor: int,
                  spread: Spread, keep: bool = True) -> tuple[np.ndarray, ReconstructionInfo]:
    """The sub-voxel iterations from the coarse support (docs/design.md §6.5): the first
    ``early_iterations`` (leaving at least one) on the aperture sampled
    ``early_oversample`` times per pixel footprint when
    :func:`.schedule.sampled_operator` gives that projector, the rest on the refined
    projector from their volume, handed over on the device (as it is when both keep it
    in the same slabs and the early run did not crop it, else placed on the refined
    grid's slabs there: :meth:`Solver.placed_on`); ``keep``: :func:`_to_host`'s."""
    early = min(settings.early_iterations, fine.iterations - 1)
    sampled = sampled_operator(refined, settings.early_oversample) if early > 0 else None
    if sampled is None:
        return _solve(prepared, refined, fine, callback, factor=factor, spread=spread,
                      keep=keep)
    first = dataclasses.replace(fine, iterations=early)
    solver, vol, info = _iterations(prepared, sampled, first, callback, spread=spread)
    if info.stopped:  # the callback ended the reconstruction
        return _to_host(solver, vol, prepared, info, factor, refined.grid.shape, keep), info
    rest = dataclasses.replace(fine, iterations=fine.iterations - early)
    handed = {}
    if solver.box is None and _same_slabs(sampled, refined):
        handed["device"] = vol
    elif isinstance(sampled, PlannedOperator) and isinstance(refined, PlannedOperator):
        handed["device"] = solver.placed_on(vol, refined)  # a cropped box, placed there
    else:
        rest = dataclasses.replace(rest, start=_to_host(
            solver, vol, prepared, info, 1, refined.grid.shape, keep=False))
    out, late = _solve(prepared, refined, rest, _numbered(callback, early), factor=factor,
                       keep=keep, **handed)
    late.iterations += info.iterations
    late.residuals[:0] = info.residuals
    return out, late


def _same_slabs(a, b) -> bool:
    """Whether two projectors on one grid keep a volume in the same device slabs (their
    plans' depth ranges: a volume of one is then a volume of the other); ``False`` for
    operators without a plan."""
    if not (isinstance(a, PlannedOperator) and isinstance(b, PlannedOperator)):
        return False
    return list(a.plan.slabs) == list(b.plan.slabs)


def _start_solver(prepared: PreparedImage, projector, settings: ReconstructionSettings,
                  info: ReconstructionInfo, spread: Spread | None = None,
                  device: list | None = None) -> tuple[Solver, cla.Array, list]:
    """The solver of one run, the device image and the first guess (masked): with
    ``spread`` ``(volume, factor)``, that volume of the ``factor`` times coarser grid
    spread over the sub-voxels instead of ``settings.start``; with ``device``, a device
    volume in the solver's units and this projector's slabs (an earlier run's)."""
    if prepared.lit is not None:
        info.lit_lens_fraction = float(prepared.lit.mean())
    solver = Solver(projector, settings.min_sensitivity, prepared.lit,
                    observed=prepared.observed)
    if prepared.observed is not None and spread is None and device is None:
        _check_observed(solver, prepared.observed)  # the first run: the voxels' own
    _warn_if_outside(projector, lambda: solver, settings.min_sensitivity)
    img = prepared.on_device(solver.queue)
    if device is not None:
        vol = device
    elif spread is None:
        vol = solver.start(img, settings.start, prepared.threshold, prepared.scale)
    else:
        vol = solver.spread_start(*spread, prepared.scale)
    if settings.mask_fraction is not None:
        lit = _holds_light(solver, vol)
        solver.mask(vol, img, prepared.threshold, settings.mask_fraction)
        if lit and not _holds_light(solver, vol):
            raise ValueError(
                f"mask_fraction={settings.mask_fraction:g} zeroed every voxel of the first "
                "guess: each sends more than that fraction of its light to dark pixels "
                "(below the threshold); give a larger mask_fraction (e.g. 0.5) or none")
    return solver, img, vol


def _holds_light(solver: Solver, vol: list) -> bool:
    """Whether any voxel of the device volume ``vol`` (its slabs) is above zero."""
    return any(solver.total(slab) > 0 for slab in vol)


def _check_observed(solver: Solver, observed: np.ndarray) -> None:
    """A pixel mask under which every voxel sees too few observed pixels to be
    reconstructed: refused, naming the mask (a map of the bad pixels given as the mask,
    ``True`` where a pixel holds data, left every voxel dark and the volume zero); one
    that marks most pixels without data and leaves much of the grid unseen: warned."""
    fraction = solver.unseen_fraction()
    said = (f"the pixel mask leaves {fraction:.0%} of the grid's voxels with too few "
            f"observed pixels to reconstruct: it marks {observed.mean():.1%} of the pixels "
            "as holding data (True = the pixel holds data); if yours marks the bad pixels, "
            "pass its inverse (pixel_mask=~bad; plenocl reconstruct --mask takes a file "
            "nonzero where pixels hold data)")
    if fraction >= 1.0:
        raise ValueError(said)
    if fraction > OUTSIDE_WARN and observed.mean() < 0.5:
        warnings.warn(said, stacklevel=7)


def _iterations(prepared: PreparedImage, projector, settings: ReconstructionSettings,
                callback, spread: Spread | None = None,
                device: list | None = None) -> tuple[Solver, list, ReconstructionInfo]:
    """One run of the iterations on the projector's grid: the solver it ended with
    (cropped or not), its device volume in the solver's units and the run's info;
    ``spread``, ``device``: the first guess (:func:`_start_solver`)."""
    info = ReconstructionInfo(settings.method)
    solver, img, vol = _start_solver(prepared, projector, settings, info, spread, device)
    blocks = device_view_blocks(projector, settings.mart_blocks) if settings.n_blocks > 1 else None
    step = functools.partial(UPDATES[settings.method], relax=settings.relax,
                             threshold=prepared.threshold, blocks=blocks,
                             n_blocks=settings.n_blocks, ratio_floor=settings.ratio_floor)
    solver, vol = _iterate(solver, vol, img, settings, info, step, callback,
                           prepared.norm())
    return solver, vol, info


def _to_host(solver: Solver, vol, prepared: PreparedImage, info: ReconstructionInfo,
             factor: int, grid_shape: tuple[int, int, int], keep: bool = True):
    """A run's device volume as the host volume in image units on the full grid of
    ``grid_shape`` (a cropped solver's box placed in it), summed over ``factor x factor``
    lateral blocks on the device when ``factor > 1``; sets ``info.active_fraction``.
    With ``keep``, the volume stays on the device (not for sub-voxels the host resamples
    or hands on: no full fine grid copied there): a :class:`DeviceVolume`, its array
    also ``info.volume_on_device``, copied to the host only when asked
    (:func:`run_reconstruction`)."""
    nz, ny, nx = grid_shape
    shape = (nz, ny // factor, nx // factor)
    if keep:
        device = solver.binned_to_device(vol, factor, shape, prepared.scale)
        out, info.volume_on_device = DeviceVolume(device), device
    elif factor == 1:
        out = solver.volume_to_host(vol, shape) * np.float32(prepared.scale)
    else:
        out = solver.binned_to_host(vol, factor, shape, prepared.scale)
    return _counted(out, info)


def _counted(vol, info: ReconstructionInfo):
    """``vol`` (host or :class:`DeviceVolume`), with ``info.active_fraction`` set to its
    share of non-zero voxels (a device volume's counted there)."""
    lit = (vol.summary().nonzero if isinstance(vol, DeviceVolume)
           else np.count_nonzero(vol))
    info.active_fraction = float(lit) / vol.size
    return vol


def _solve(prepared: PreparedImage, projector, settings: ReconstructionSettings, callback,
           factor: int = 1, spread: Spread | None = None,
           device: list | None = None, keep: bool = True
           ) -> tuple[np.ndarray, ReconstructionInfo]:
    """One run of the iterations on the projector's grid; the host volume in image units,
    summed over ``factor x factor`` lateral blocks on the device when ``factor > 1``;
    ``spread``, ``device``: the first guess (:func:`_start_solver`); ``keep``:
    :func:`_to_host`'s."""
    solver, vol, info = _iterations(prepared, projector, settings, callback, spread, device)
    return _to_host(solver, vol, prepared, info, factor, projector.grid.shape, keep), info


def _in_frame(image, projector, settings: ReconstructionSettings, callback, observed,
              keep: bool = False, ahead: PreparedImage | None = None
              ) -> tuple[np.ndarray, ReconstructionInfo]:
    """Sub-voxels on a grid across a rotated array's lens rows (``projector.frame``,
    docs/design.md §5.1): the iterations run on the lens-row frame's grid and its refined
    grid, on the separable kernels at their full speed, and the sub-voxels are resampled
    onto the projector's refined grid once, at the end, before they are summed (the
    resampling blurs by a fraction of a voxel only); a start volume is resampled onto the
    frame. ``keep``, ``ahead``: :func:`_run`'s."""
    f = settings.supersample
    fine = _refined(projector, f)
    start = settings.start
    if isinstance(start, np.ndarray):
        start = projector.volume_to_frame(start)
    _check_frame_outside(projector, settings.min_sensitivity)
    t0 = time.perf_counter()
    vol, info = _run(image, projector.frame, dataclasses.replace(settings, start=start),
                     callback, observed, binned=False, keep=keep, ahead=ahead)
    vol = host_volume(vol)  # resampled on the host
    if vol.shape == fine.frame.grid.shape:
        vol = bin_lateral(fine.volume_from_frame(vol), f)
    else:  # an empty or stopped coarse run: the voxels'
        vol = projector.volume_from_frame(vol)
    info.active_fraction = float(np.count_nonzero(vol)) / vol.size
    info.seconds = time.perf_counter() - t0
    info.volume_on_device = None  # the frame's grid, resampled on the host
    return vol, info


def run_reconstruction(image, projector: ProjectionOperator, settings: ReconstructionSettings,
                       callback: Callable[[int, float], bool | None] | None = None,
                       pixel_mask=None, *, keep_for_next_stage: bool = False,
                       ahead: PreparedImage | None = None
                       ) -> tuple[np.ndarray, ReconstructionInfo]:
    """:func:`reconstruct` with its options as one :class:`ReconstructionSettings`;
    returns the volume and its :class:`ReconstructionInfo`.

    The image is prepared once (:func:`plenocl.reconstruction.images.prepare_image`: the
    background, threshold, scale and lit lenses), also for the two runs of a
    coarse-to-fine reconstruction; ``info.seconds`` is the whole reconstruction's time.
    A projector with a ``frame`` (a resampled grid) reconstructs sub-voxels on it
    (:func:`_in_frame`) and voxels with its own operator (resampled every iteration: at
    the voxels' scale a single resampling at the end would blur particles by up to a
    voxel).

    ``keep_for_next_stage``: keep for the stages after it (:func:`plenocl.process_pair`)
    the volume on the device, as ``info.volume_on_device`` (float32, the projector's
    queue), where the reconstruction ends with it there (one camera, not on a rotated
    array's frame; ``None`` otherwise), for them to read without uploading it again: the
    volume returned is then a :class:`plenocl.opencl.volume.DeviceVolume` of that array,
    copied to the host only when asked (``np.asarray``, its ``get``; issue 46); and the
    image the solver read, ``info.background_free`` (:class:`plenocl.optics.rawimage.ScaledImage`:
    ``max(image - background, 0)`` divided by its brightest pixel, float32, with its
    device copy on the projector's queue), where it is the image fit's (the
    reconstruction removed a background and neither smoothed the image nor masked
    pixels; ``None`` otherwise), for the fit neither to remove the background again nor
    to upload the image. By default both are released: an info kept for long holds no
    device memory and no image.

    ``ahead``: the image's host preparation made beforehand
    (:func:`plenocl.reconstruction.images.prepare_on_host` of ``image`` with these
    settings and no pixel mask), e.g. on another thread
    while the device reconstructed another image; one camera only. ``info.seconds`` then
    leaves it out.
    """
    if ahead is not None and (pixel_mask is not None or isinstance(image, (list, tuple))):
        raise ValueError("ahead is one camera's image prepared without a pixel mask")
    vol, info = _reconstructed(image, projector, settings, callback, pixel_mask,
                               keep_for_next_stage, ahead)
    if not keep_for_next_stage:
        vol = host_volume(vol)
        info.release_kept()
    return vol, info


def _reconstructed(image, projector: ProjectionOperator, settings: ReconstructionSettings,
                   callback, pixel_mask, keep: bool = False,
                   ahead: PreparedImage | None = None
                   ) -> tuple[np.ndarray, ReconstructionInfo]:
    """:func:`run_reconstruction`'s work (the device volume kept in the info; with
    ``keep``, the background-free image too; ``ahead``: its)."""
    if isinstance(settings.start, str) and settings.start not in ("uniform", "mlos"):
        raise ValueError("start must be 'uniform', 'mlos' or a volume array, got "
                         f"{settings.start!r}")  # an option: checked before the image
    if isinstance(image, (list, tuple)):  # several cameras (docs/design.md §6.7)
        return _several(image, projector, settings, callback, pixel_mask)
    if not hasattr(projector, "grid"):  # a camera, a grid file, None
        raise TypeError(f"reconstruct takes a projector (plenocl.Projector(camera, grid)) "
                        f"after the image, got {type(projector).__name__}")
    _coarse_start(settings.start, projector.grid)
    projector = _weighted(projector, settings.lens_weights)
    observed = None if pixel_mask is None else check_pixel_mask(pixel_mask, projector.camera)
    if observed is not None and isinstance(settings.start, str) and settings.start == "mlos":
        raise ValueError("start='mlos' cannot use a pixel_mask (its geometric mean needs "
                         "every pixel): use start='uniform' (the default)")
    if (isinstance(projector, FramedOperator) and projector.frame is not None
            and settings.supersample > 1):
        return _in_frame(image, projector, settings, callback, observed, keep, ahead)
    return _run(image, projector, settings, callback, observed, keep=keep, ahead=ahead)


def _several(images, projectors, settings: ReconstructionSettings, callback, pixel_mask
             ) -> tuple[np.ndarray, ReconstructionInfo]:
    """:func:`run_reconstruction` of one image per camera, on one projector per camera
    (one camera: the single camera's reconstruction itself)."""
    if not isinstance(projectors, (list, tuple)):
        raise TypeError("several images need a list of projectors, one per camera (in the "
                        f"images' order), got {type(projectors).__name__}")
    if len(images) == 1 and len(projectors) == 1:
        return run_reconstruction(images[0], projectors[0], settings, callback, pixel_mask)
    if pixel_mask is not None or not (isinstance(settings.start, str)
                                      and settings.start == "uniform"):
        raise ValueError("several cameras reconstruct from a uniform start over every "
                         "pixel: pixel_mask and start volumes are for one camera")
    projectors = [_weighted(p, settings.lens_weights) for p in projectors]
    return run_joint(images, projectors, settings, callback)


def _run(image, projector, settings: ReconstructionSettings, callback, observed,
         binned: bool = True, keep: bool = False, ahead: PreparedImage | None = None
         ) -> tuple[np.ndarray, ReconstructionInfo]:
    """The reconstruction on the projector's own grid (sub-voxels summed when
    ``binned``); ``keep``: the background-free image kept in the info
    (:func:`run_reconstruction`'s ``keep_for_next_stage``); ``ahead``: its."""
    refined = _refined(projector, settings.supersample) if settings.supersample > 1 else None
    t0 = time.perf_counter()
    prepared = prepare_image(image, projector, settings, observed, ahead=ahead)
    if refined is None:
        vol, info = _solve(prepared, projector, settings, callback)
    else:
        vol, info = _supersampled(prepared, projector, refined, settings, callback, binned)
    info.seconds = time.perf_counter() - t0
    info.background, info.noise = prepared.background, prepared.noise
    if keep:
        info.background_free = prepared.fit_image(getattr(projector, "queue", None))
    return vol, info
