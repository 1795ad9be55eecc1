"""One volume from several plenoptic cameras' images (docs/design.md §6.7, issue 49).

Each camera has its own projector (its pose carries the shared world grid into its
frame, :mod:`plenocl.projection.posed`); the system is every camera's pixels at once,
``Σ_j w^c_ij E_j = I^c_i``. MLEM over all of them updates a voxel by the mean of its
ratios over every camera's pixels, ``E ← E (Σ_c A_cᵀ r_c / Σ_c s_c)^μ`` with
``s_c = A_cᵀ 1``; SMART likewise with the log ratios. The paper's block MART visits the
cameras in turn, each camera's view blocks in its own order, each block a fresh
projection: ``E_j ← E_j Π_i r_i^(μ w_ij)`` over that block's pixels, so every camera's
pixels update the volume once per iteration. **Choice**: the images share one
scale (the brightest of them is 1), so the cameras' counts keep their ratio: a particle
is as bright in every camera's units, as it is for identical cameras; each image keeps
its own background, noise and dark-pixel threshold. A voxel is reconstructed when the
light it sends to all the sensors together is above ``min_sensitivity``.

The schedule is the single camera's (§6.5): coarse iterations on the voxels, their
support, the sub-voxel iterations within it, summed back onto the grid. Each camera's
:class:`plenocl.reconstruction.solver.Solver` holds its image's kernels and lit lenses;
:class:`JointSolver` adds their back projections.
"""

from __future__ import annotations

import time
import warnings
import weakref
from collections.abc import Callable, Sequence

import numpy as np

from ..camera.pose import check_distinct_views
from ..opencl.arrays import fill
from .blocks import device_view_blocks
from .images import PreparedImage, prepare_image
from .operator import FramedOperator
from .schedule import coarse_support, sampled_operator
from .settings import ReconstructionInfo, ReconstructionSettings
from .solver import OUTSIDE_WARN, RATIO_MIN, Solver, update_mart


class JointSolver:
    """The solvers of several cameras on one grid, with their summed sensitivity.

    Parameters
    ----------
    projectors
        One operator per camera, all on the same grid and device slabs.
    prepared
        Each camera's prepared image (its lit lenses select what its projections touch).
    factors
        Each image's factor into the shared scale (its own scale over the shared one).
    min_sensitivity
        Voxels whose summed sensitivity is at or below it stay 0.
    """

    def __init__(self, projectors: Sequence, prepared: Sequence[PreparedImage],
                 factors: Sequence[float], min_sensitivity: float) -> None:
        self.solvers = [Solver(p, min_sensitivity, im.lit) for p, im in
                        zip(projectors, prepared, strict=True)]
        first = self.solvers[0]
        self.proj, self.queue = first.proj, first.queue
        # the brightest image is the shared scale itself: its device copy serves as it is
        self.images = [im.on_device(self.queue) * np.float32(f) if f != 1.0
                       else im.on_device(self.queue)
                       for im, f in zip(prepared, factors, strict=True)]
        self.thresholds = [im.threshold * f for im, f in zip(prepared, factors, strict=True)]
        self.sens = self._added([[s.copy() for s in first.sens]]
                                + [solver.sens for solver in self.solvers[1:]])
        self.smin = first.smin

    def _added(self, volumes: Sequence[list]) -> list:
        """The slab-wise sum of several device volumes, into the first."""
        for vol in volumes[1:]:
            self.solvers[0].add_into(volumes[0], vol)
        return volumes[0]

    def uniform_start(self) -> list:
        """A constant volume whose projections carry the images' light."""
        light = sum(s.total(img) for s, img in zip(self.solvers, self.images, strict=True))
        total = sum(self.solvers[0].total(s) for s in self.sens)
        vol = self.proj.empty_volume()
        for v in vol:
            fill(v, light / max(total, 1e-30))
        return vol

    def update(self, vol: list, relax: float, log_ratio: bool, floor: float = RATIO_MIN
               ) -> float:
        """One simultaneous update over every camera's pixels (SMART's ratios floored at
        ``floor``); returns ``‖P - I‖`` over all of them before it."""
        backs, resid = [], 0.0
        for solver, img, thr in zip(self.solvers, self.images, self.thresholds, strict=True):
            fwd, back = solver.projections(log_ratio)
            proj = fwd(vol)
            resid += solver.total(proj, img)
            # the support is the volume just projected: a resampled grid reuses its frame
            # volume (Projector.back_device's reuse_forward)
            framed = isinstance(solver.proj, FramedOperator) and solver.proj.frame is not None
            reuse = {"reuse_forward": True} if framed else {}
            backs.append(back(solver.ratio(img, proj, thr, log_ratio, floor=floor),
                              support=vol, **reuse))
        b = self._added(backs)
        if log_ratio:
            self.solvers[0].update_voxels("update_exp", vol, b, np.float32(relax), self.smin,
                                          np.int32(1), sens=self.sens)
        else:
            self.solvers[0].update_voxels("update_mlem", vol, b, np.float32(relax),
                                          self.smin, sens=self.sens)
        return resid ** 0.5

    def update_mart(self, vol: list, relax: float, floor: float, blocks: Sequence,
                    n_blocks: int) -> float:
        """One block-MART iteration (module documentation): camera by camera, the single
        camera's block sweep (:func:`.solver.update_mart`; ``blocks``: each camera's
        block map, ``None`` for one block), a voxel staying 0 where the cameras' summed
        sensitivity is at or below ``min_sensitivity`` (a voxel one camera does not see
        is the other's to update). Returns ``‖P - I‖`` over every camera's pixels, each
        camera's taken before its first block."""
        resid = 0.0
        for solver, img, thr, blk in zip(self.solvers, self.images, self.thresholds, blocks,
                                         strict=True):
            resid += update_mart(solver, vol, img, None, relax, thr, blk, n_blocks, floor,
                                 sens=self.sens) ** 2
            solver.release_kept()  # one camera's buffers at a time, not every camera's
        return resid ** 0.5


def check_cameras(images: Sequence, projectors: Sequence) -> None:
    """One image per projector, at least one, all projectors on one grid and queue, no
    two cameras with one view (:func:`plenocl.camera.pose.check_distinct_views`)."""
    if len(images) != len(projectors) or not projectors:
        raise ValueError(f"several cameras need one image per projector: got "
                         f"{len(images)} image(s) and {len(projectors)} projector(s)")
    grid, queue = projectors[0].grid, projectors[0].queue
    if len(projectors) > 1:
        check_distinct_views([p.camera for p in projectors])
    for k, proj in enumerate(projectors[1:], start=2):
        if proj.grid != grid:
            raise ValueError(f"projector {k}'s grid {proj.grid} is not projector 1's "
                             f"{grid}: every camera projects the same world grid")
        if proj.queue is not queue:
            raise ValueError(f"projector {k} runs on another OpenCL queue than projector 1: "
                             "build every camera's projector on one queue (q = "
                             "plenocl.get_queue(); plenocl.Projector(camera, grid, q))")


def run_joint(images: Sequence, projectors: Sequence, settings: ReconstructionSettings,
              callback: Callable[[int, float], bool | None] | None = None
              ) -> tuple[np.ndarray, ReconstructionInfo]:
    """:func:`plenocl.reconstruct` of several cameras' images (module documentation):
    MLEM, SMART or block MART, on the voxels or coarse-to-fine on sub-voxels with the
    single camera's schedule (coarse and early iterations on coarser aperture
    samplings)."""
    check_cameras(images, projectors)
    if settings.tol is not None or settings.mask_fraction is not None:
        raise ValueError("several cameras run every iteration over every pixel: tol and "
                         "mask_fraction are one camera's; leave them None")
    t0 = time.perf_counter()
    prepared = [prepare_image(img, p, settings) for img, p in zip(images, projectors,
                                                                  strict=True)]
    _warn_if_unequal(prepared)
    scale = max(im.scale for im in prepared)
    run = _Run(prepared, [im.scale / scale for im in prepared], settings, callback)
    f = settings.supersample
    if f == 1:
        solver, vol = run.iterate(projectors, settings.iterations)
        warn_partial_views(solver, projectors)
        out = solver.proj.volume_to_host(vol)
    else:
        coarse_run = settings.coarse_run()  # MLEM whatever the method
        solver, coarse = run.iterate(_sampled(projectors, settings.coarse_oversample),
                                     coarse_run.iterations, settings=coarse_run)
        warn_partial_views(solver, projectors)
        host = solver.proj.volume_to_host(coarse)
        start, support = coarse_support(host, settings)
        if start is None:  # no light in the coarse volume: nothing to refine
            start = np.zeros(host.shape, np.float32)
        refined = [p.refined(f) for p in projectors]
        early = min(settings.early_iterations, settings.iterations - 1)
        solver, vol = run.iterate(_sampled(refined, settings.early_oversample), early,
                                  spread=(start, f))
        solver, vol = run.iterate(refined, settings.iterations - early, device=vol)
        out = solver.solvers[0].binned_to_host(vol, f, projectors[0].grid.shape)
        run.info.supersample, run.info.coarse_iterations = f, settings.coarse_iterations
        run.info.support_fraction = support
    out *= np.float32(scale)
    run.info.cameras = [ReconstructionInfo(settings.method, background=im.background,
                                           noise=im.noise) for im in prepared]
    run.info.seconds = time.perf_counter() - t0
    run.info.active_fraction = float(np.count_nonzero(out)) / out.size
    return out, run.info


#: Warn when one camera's prepared image peaks more than this many times another's.
GAIN_WARN = 4.0
#: The cameras and grid extents already checked (:func:`warn_partial_views`), by the
#: first camera.
_VIEWS_CHECKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _warn_if_unequal(prepared: Sequence[PreparedImage]) -> None:
    """The images share one scale (module notes): a camera whose counts run far higher
    (a gain or bit depth) outweighs the others, and the second view's depth is lost
    (an audit: the depth error 0.19 -> 0.24 voxel at 16 x, 0.36 at 256 x); said."""
    peaks = [im.scale for im in prepared]
    low = min(p for p in peaks if p > 0) if any(p > 0 for p in peaks) else 0.0
    if low and max(peaks) > GAIN_WARN * low:
        hi, lo = peaks.index(max(peaks)) + 1, peaks.index(low) + 1
        warnings.warn(f"camera {hi}'s image peaks {max(peaks) / low:.1f} times camera {lo}'s "
                      "above their backgrounds: several cameras' images share one scale, so "
                      "a camera of higher gain or bit depth outweighs the others and the "
                      "second view's depth is partly lost; bring the frames to one gain "
                      "(divide the brighter camera's frames by the ratio of the gains)",
                      stacklevel=7)


def warn_partial_views(solver: JointSolver, projectors: Sequence) -> None:
    """Once per set of cameras and grid extent: warn for each camera that does not see
    more than :data:`.solver.OUTSIDE_WARN` of the grid (there the other cameras measure
    alone: one camera's depth error, or none)."""
    g = projectors[0].grid
    key = (tuple((id(p.camera), p.camera.pose) for p in projectors[1:]), tuple(g.x),
           tuple(g.y), tuple(g.z), g.rotation_deg, float(solver.smin))
    checked = _VIEWS_CHECKED.setdefault(projectors[0].camera, set())
    if key in checked:
        return
    checked.add(key)
    for k, one in enumerate(solver.solvers, start=1):
        fraction = one.unseen_fraction()
        if fraction > OUTSIDE_WARN:
            warnings.warn(f"camera {k} does not see {fraction:.0%} of the grid's voxels: there "
                          "the other cameras measure alone (one camera's depth error, or no "
                          "data where none sees them); narrow the grid to where the cameras' "
                          "views overlap, or turn the camera towards it", stacklevel=7)


def _sampled(projectors: Sequence, oversample: float | None) -> list:
    """Each projector on ``oversample`` aperture samples per pixel footprint where
    :func:`.schedule.sampled_operator` gives one; itself otherwise."""
    return [sampled_operator(p, oversample) or p for p in projectors]


class _Run:
    """The iterations of one joint reconstruction: its images, settings, callback and
    info, counted across its phases."""

    def __init__(self, prepared, factors, settings: ReconstructionSettings, callback):
        self.prepared, self.factors, self.settings = prepared, factors, settings
        self.callback = callback
        self.info = ReconstructionInfo(settings.method)
        self.norm = max(float(np.sqrt(sum((f * im.norm()) ** 2 for im, f in
                                          zip(prepared, factors, strict=True)))), 1e-30)

    def iterate(self, projectors, iterations: int, spread=None, device=None,
                settings: ReconstructionSettings | None = None):
        """``iterations`` joint updates from a uniform start, ``spread`` (a coarser
        volume's support shared over the sub-voxels) or a ``device`` volume of the same
        slabs, by ``settings``' method (the run's by default); returns the solver and its
        volume."""
        solver = JointSolver(projectors, self.prepared, self.factors,
                             self.settings.min_sensitivity)
        if device is not None:
            vol = device
        elif spread is not None:
            vol = solver.solvers[0].spread_start(*spread)
        else:
            vol = solver.uniform_start()
        st = settings or self.settings
        blocks = [device_view_blocks(p, st.mart_blocks) if st.n_blocks > 1 else None
                  for p in projectors] if st.method == "mart" else None
        for _ in range(iterations if not self.info.stopped else 0):
            resid = self._step(solver, vol, blocks, st) / self.norm
            self.info.residuals.append(resid)
            self.info.iterations += 1
            if self.callback is not None and self.callback(self.info.iterations,
                                                           resid) is False:
                self.info.stopped = True
                break
        return solver, vol

    @staticmethod
    def _step(solver: JointSolver, vol: list, blocks: list | None,
              st: ReconstructionSettings) -> float:
        """One iteration of ``st``'s method (``blocks``: each camera's view blocks, block
        MART's; ``None`` for MLEM and SMART); returns ``‖P - I‖``."""
        floor = RATIO_MIN if st.ratio_floor is None else st.ratio_floor
        if blocks is not None:
            return solver.update_mart(vol, st.relax, floor, blocks, st.n_blocks)
        return solver.update(vol, st.relax, st.method == "smart", floor)
