"""Every option of a reconstruction as one validated object, and what a run reports."""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field, replace

import numpy as np

from ..optics.rawimage import ScaledImage
from ..options import is_integer, whole_counts
from .supersample import MAX_SUPERSAMPLE

METHODS = ("mlem", "smart", "mart")
#: The reconstruction's method, recorded with every batch field (and so in the
#: ``volumes`` digest its kept volumes carry: :func:`plenocl.batch.record.run_record`),
#: every tracking run (:mod:`plenocl.batch.tracking`) and the demos' stages: a rerun
#: redoes the volumes an earlier method made from the same settings. Change it whenever
#: a reconstruction makes other volumes from the same settings (rounding included: a
#: kept volume then differs from a fresh one), the projector's defaults included (a batch
#: builds its projector with them: ``DEFAULT_OVERSAMPLE``, ``DEFAULT_SHEAR_TOL``,
#: ``general``, which no record names).
METHOD = ("coarse-to-fine: the coarse support's peak, floor and level found on the "
          "device, the level from float32 row sums added in float64 (2026-12-01, issue 46), "
          "in 256 parts of rows added in order (2026-12-03 night); "
          "a hexagonal array's axial view leaning one way whatever its numbering "
          "(2026-12-01 evening); the coarse run MLEM's whatever the method (2026-12-03: "
          "SMART's and MART's volumes from the same settings differ); a cropped early "
          "sub-voxel run's volume handed to the rest on the device, not through the "
          "host's image units (2026-12-04, issue 46: rounding)")
#: n per axis of MART's view blocks (n² blocks; 32 covers one block per view of 32 px lenses)
MAX_MART_BLOCKS = 32
#: Defaults per method on one grid: (iterations, relaxation). MART's are the paper's
#: synthetic case. They hold on the voxels (``supersample=1``), for SMART and MART also
#: on sub-voxels, and for MLEM on sub-voxels without coarse iterations.
DEFAULTS = {"mlem": (30, 1.0), "smart": (30, 1.0), "mart": (15, 0.7)}
#: Lateral sub-voxels per voxel and axis by default (docs/design.md §6.4).
SUPERSAMPLE = 3
#: Coarse-to-fine by default on sub-voxels (docs/design.md §6.5): iterations on the
#: voxels first, and the support threshold (a fraction of their brightest voxel). The
#: coarse iterations are MLEM's whatever the method (:meth:`ReconstructionSettings.
#: coarse_run`): the geometric-mean methods' on whole voxels lose particles (the
#: footprint a voxel a lens wide spreads, docs/design.md §6.2), and their support then
#: drops them (the paper's MART on noisy images: 44-54 % recovered after 4 MART coarse
#: iterations, 96 % after 4 MLEM ones; ``benchmarks/paper_mart.py``).
COARSE_ITERATIONS = 4
SUPPORT = 0.01
#: MLEM's defaults on sub-voxels after coarse iterations: (iterations, relaxation), both
#: phases over-relaxed (docs/design.md §6.5).
FINE_DEFAULTS = (7, 1.5)
#: MLEM's relaxation lies below this bound: MLEM may be over-relaxed,
#: ``E ← E (Wᵀ r / s)^μ`` with ``1 < μ < 2`` (docs/design.md §6.5: μ = 1.5 reaches in 7
#: iterations the volume of 10 at μ = 1; μ = 2 oscillates); SMART and MART take the
#: paper's ``0 < μ <= 1``.
MLEM_MAX_RELAX = 2.0
#: The lens weights a reconstruction may name (``lens_weights``; the projector's
#: ``plenocl.projection.projector.LENS_WEIGHTS``, which a test keeps equal).
LENS_WEIGHTS = ("paper", "extent")
#: Largest image smoothing accepted (``smooth_px``, pixels): a particle image's size; wider
#: smoothing would carry light across a microlens image (17 px at the paper's camera).
MAX_SMOOTH_PX = 4.0
#: The image smoothing of each method by default (``smooth_px=None``; pixels, 0: none).
#: The geometric-mean methods smooth by 1 px: their log ratio of a pixel left below the
#: dark threshold (-13.8) removes a noisy image's dim particle pixels, and so its
#: particles, where the smoothed image keeps them (the paper's MART on noisy ray-traced
#: images: 17-21 % recovered unsmoothed, 96-99 % smoothed; docs/design.md §6.2). MLEM
#: averages the ratios and is left as it is (``None``, no smoothing, is its record).
SMOOTH_DEFAULTS = {"mlem": None, "smart": 1.0, "mart": 1.0}


@dataclass
class ReconstructionInfo:
    """What a reconstruction did: iterations, residual history, time, masking;
    ``stopped``: the callback ended it; ``background`` and ``noise``: the median and
    noise (image units) the median background removed (``None`` without it); ``cameras``:
    several cameras' reconstruction, each camera's own (its background and noise), in
    the images' order (empty for one camera); ``volume_on_device`` and
    ``background_free``: the volume's float32 device copy on the projector's queue (the
    same values as the host volume) and the image the solver read where it is the image
    fit's (:class:`plenocl.optics.rawimage.ScaledImage`, with its device copy), kept where
    :func:`plenocl.reconstruction.reconstruct.run_reconstruction` was asked to
    (``keep_for_next_stage``: the stages after it read them instead of making them
    again), else ``None``."""

    method: str
    iterations: int = 0
    residuals: list[float] = field(default_factory=list)
    converged: bool = False
    stopped: bool = False
    seconds: float = 0.0
    active_fraction: float = 1.0
    active_slices: list[int] = field(default_factory=list)
    cropped_shape: tuple[int, int, int] | None = None
    lit_lens_fraction: float = 1.0
    supersample: int = 1
    coarse_iterations: int = 0
    support_fraction: float = 1.0
    background: float | None = None
    noise: float | None = None
    cameras: list[ReconstructionInfo] = field(default_factory=list)
    volume_on_device: object = field(default=None, repr=False, compare=False)
    background_free: ScaledImage | None = field(default=None, repr=False, compare=False)

    def release_kept(self) -> None:
        """Let go of what was kept for the stages after the reconstruction (the device
        volume, the image): an info kept for long holds no device memory."""
        self.volume_on_device = self.background_free = None


#: Aperture samples per pixel footprint of a coarse-to-fine reconstruction's coarse
#: iterations (docs/design.md §6.5): they only find the support, and a quarter of the
#: projector's samples (1.25) finds the same one.
COARSE_OVERSAMPLE = 0.625
#: The first sub-voxel iterations of a coarse-to-fine reconstruction, and their aperture
#: sampling (docs/design.md §6.5): the rest run on the projector's own (1.25).
EARLY_ITERATIONS = 3
EARLY_OVERSAMPLE = 0.9


@dataclass(frozen=True)
class ReconstructionSettings:
    """Every option of a reconstruction, validated once (see :func:`reconstruct` for
    their meaning); the one default of :func:`reconstruct`, :func:`plenocl.process_pair`,
    ``plenocl reconstruct`` and ``plenocl run``.

    By default coarse-to-fine on sub-voxels (docs/design.md §6.5): :data:`SUPERSAMPLE`
    x :data:`SUPERSAMPLE` lateral sub-voxels per voxel, :data:`COARSE_ITERATIONS` on the
    voxels first, :data:`SUPPORT`; for MLEM then :data:`FINE_DEFAULTS` (7 iterations on
    the sub-voxels at μ = 1.5). Options left at ``None`` resolve from those given:
    ``coarse_iterations`` is 0 on the voxels (``supersample=1``), and the coarse
    iterations are MLEM's whatever the method (:meth:`coarse_run`); ``iterations`` and
    ``relax`` are :data:`FINE_DEFAULTS` for MLEM on sub-voxels after coarse iterations,
    else the method's own (:data:`DEFAULTS`: ``supersample=1`` is MLEM's 30 at μ = 1);
    ``smooth_px`` the method's (:data:`SMOOTH_DEFAULTS`). Values given always win, each
    on its own. The stored object holds the resolved values (so
    ``dataclasses.replace(settings, supersample=1)`` keeps the sub-voxels' iterations;
    ``ReconstructionSettings(supersample=1)`` takes the voxels' own)."""

    method: str = "mlem"
    iterations: int | None = None
    relax: float | None = None
    start: str | np.ndarray = field(default="uniform", compare=False)
    threshold: float | None = None
    background: str | None = "median"
    mask_fraction: float | None = None
    min_sensitivity: float = 0.5
    skip_empty: bool = True
    crop: bool = True
    skip_dark: bool = True
    tol: float | None = None
    mart_blocks: int = 2
    ratio_floor: float | None = None
    supersample: int = SUPERSAMPLE
    coarse_iterations: int | None = None
    support: float = SUPPORT
    coarse_oversample: float | None = COARSE_OVERSAMPLE
    early_iterations: int = EARLY_ITERATIONS
    early_oversample: float | None = EARLY_OVERSAMPLE
    lens_weights: str | None = None
    smooth_px: float | None = None

    def __post_init__(self) -> None:
        whole_counts(self, (*COUNTS, "supersample"))  # 3.0, as a file may write it: 3
        fine = is_integer(self.supersample) and self.supersample > 1
        if self.coarse_iterations is None:
            object.__setattr__(self, "coarse_iterations", COARSE_ITERATIONS if fine else 0)
        if fine and self.coarse_iterations and self.method == "mlem":
            it_default, mu_default = FINE_DEFAULTS
        else:
            it_default, mu_default = DEFAULTS.get(self.method, (0, 1.0))
        if self.iterations is None:
            object.__setattr__(self, "iterations", it_default)
        if self.relax is None:
            object.__setattr__(self, "relax", mu_default)
        if self.smooth_px is None:
            object.__setattr__(self, "smooth_px", SMOOTH_DEFAULTS.get(self.method))
        _check_types(self)
        _check_options(self)

    @property
    def total_iterations(self) -> int:
        """The iterations a reconstruction runs at most, as its callback counts them: the
        coarse ones of a coarse-to-fine reconstruction (``supersample > 1`` from a named
        start) and then the others (a progress bar's total)."""
        coarse = self.supersample > 1 and isinstance(self.start, str)
        return self.iterations + (self.coarse_iterations if coarse else 0)

    def coarse_run(self) -> ReconstructionSettings:
        """The coarse run's settings (docs/design.md §6.5): ``coarse_iterations`` of MLEM
        on the voxels whatever the method. They only find the support the sub-voxels keep
        to, and the geometric-mean methods on whole voxels lose particles it needs
        (docs/design.md §6.2). At these settings' relaxation for MLEM, else MLEM's
        over-relaxed one (:data:`FINE_DEFAULTS`)."""
        mlem = self.method == "mlem"
        return replace(self, method="mlem", supersample=1, coarse_iterations=0,
                       iterations=self.coarse_iterations, ratio_floor=None,
                       relax=self.relax if mlem else FINE_DEFAULTS[1])

    @property
    def n_blocks(self) -> int:
        """Update blocks per iteration: MART's ``mart_blocks²`` views, else 1."""
        return self.mart_blocks**2 if self.method == "mart" and self.mart_blocks > 1 else 1


#: The options that count (iterations, blocks): integers, a whole float taken as one.
COUNTS = ("iterations", "coarse_iterations", "early_iterations", "mart_blocks")
#: The options that are numbers or None.
NUMBERS = ("threshold", "relax", "mask_fraction", "tol", "ratio_floor", "support",
           "coarse_oversample", "early_oversample", "smooth_px", "min_sensitivity")
#: Of :data:`NUMBERS`, those that take no None (``relax``'s None is resolved first).
REQUIRED_NUMBERS = ("relax", "support", "min_sensitivity")


def _check_types(s: ReconstructionSettings) -> None:
    """Counts are integers (not booleans), number options numbers (not text or
    booleans): named, before a comparison fails inside with a type error."""
    for name in COUNTS:
        if not is_integer(getattr(s, name)):
            raise ValueError(f"{name} must be a non-negative integer, got "
                             f"{getattr(s, name)!r}")
    for name in NUMBERS:
        value, nullable = getattr(s, name), name not in REQUIRED_NUMBERS
        if (value is not None or not nullable) and (
                isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real)):
            raise ValueError(f"{name} must be a number{' or None' if nullable else ''}, "
                             f"got {value!r}")


def _check_options(s: ReconstructionSettings) -> None:
    if s.threshold is not None and not (np.isfinite(s.threshold) and s.threshold >= 0):
        raise ValueError(f"threshold must be a finite number >= 0 (image units) or None "
                         f"(from the noise), got {s.threshold!r}")
    if s.tol is not None and not (np.isfinite(s.tol) and s.tol >= 0):
        raise ValueError(f"tol must be a finite number >= 0 (the residual's relative change "
                         f"that stops the iterations) or None, got {s.tol!r}")
    if s.background not in ("median", None):
        raise ValueError(f"background must be 'median' or None, got {s.background!r}")
    if int(s.mart_blocks) != s.mart_blocks or not 1 <= s.mart_blocks <= MAX_MART_BLOCKS:
        raise ValueError(f"mart_blocks must be an integer from 1 to {MAX_MART_BLOCKS} "
                         f"(n x n blocks of views), got {s.mart_blocks!r}")
    if s.method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {s.method!r}")
    if int(s.iterations) != s.iterations or s.iterations < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {s.iterations!r}")
    _check_relax(s.method, s.relax)
    if s.mask_fraction is not None and not 0 <= s.mask_fraction <= 1:
        raise ValueError(f"mask_fraction must be in [0, 1] or None, got {s.mask_fraction!r}")
    if not is_integer(s.supersample) or not 1 <= s.supersample <= MAX_SUPERSAMPLE:
        raise ValueError(f"supersample must be an integer from 1 to {MAX_SUPERSAMPLE} (lateral "
                         f"sub-voxels per voxel and axis), got {s.supersample!r}")
    if (int(s.coarse_iterations) != s.coarse_iterations or s.coarse_iterations < 0
            or isinstance(s.coarse_iterations, bool)):
        raise ValueError(f"coarse_iterations must be a non-negative integer, got "
                         f"{s.coarse_iterations!r}")
    for name in ("coarse_oversample", "early_oversample"):
        value = getattr(s, name)
        if value is not None and (isinstance(value, bool) or not np.isfinite(value)
                                  or value <= 0):
            raise ValueError(f"{name} must be a positive number (aperture samples per "
                             f"pixel footprint) or None (the projector's own), got "
                             f"{value!r}")
    if (isinstance(s.early_iterations, bool) or int(s.early_iterations) != s.early_iterations
            or s.early_iterations < 0):
        raise ValueError(f"early_iterations must be a non-negative integer, got "
                         f"{s.early_iterations!r}")
    if not (np.isfinite(s.support) and 0 <= s.support < 1):
        raise ValueError(f"support must be in [0, 1) (a fraction of the coarse volume's "
                         f"brightest voxel), got {s.support!r}")
    if s.ratio_floor is not None:
        if s.method == "mlem":
            raise ValueError("ratio_floor applies to the geometric-mean methods ('smart', "
                             "'mart'); MLEM averages the ratios and needs none")
        if not (np.isfinite(s.ratio_floor) and 0 < s.ratio_floor < 1):
            raise ValueError(f"ratio_floor must be in (0, 1) or None (the literal form), got "
                             f"{s.ratio_floor!r}")
    if s.lens_weights is not None and s.lens_weights not in LENS_WEIGHTS:
        raise ValueError(f"lens_weights must be one of {LENS_WEIGHTS} or None (the "
                         f"projector's own), got {s.lens_weights!r}")
    if s.smooth_px is not None and not (
            isinstance(s.smooth_px, numbers.Real) and not isinstance(s.smooth_px, bool)
            and np.isfinite(s.smooth_px) and 0 <= s.smooth_px <= MAX_SMOOTH_PX):
        raise ValueError(f"smooth_px must be a Gaussian's standard deviation in pixels, "
                         f"0 <= smooth_px <= {MAX_SMOOTH_PX:g} (about the particle images' "
                         f"size; 0: no smoothing), or None (the method's default), got "
                         f"{s.smooth_px!r}")
    if not 0 <= s.min_sensitivity < 1:
        raise ValueError(f"min_sensitivity must be in [0, 1), got {s.min_sensitivity!r}")


def _check_relax(method: str, relax: float) -> None:
    """``0 < μ <= 1``, and for MLEM (over-relaxed EM) ``0 < μ < MLEM_MAX_RELAX``."""
    if method == "mlem":
        ok = 0 < relax < MLEM_MAX_RELAX
        bound = f"0 < μ < {MLEM_MAX_RELAX:g} for MLEM (1 < μ over-relaxes: fewer iterations)"
    else:
        ok, bound = 0 < relax <= 1, f"0 < μ <= 1 for {method.upper()}"
    if not (np.isfinite(relax) and ok):
        raise ValueError(f"relax (μ) must satisfy {bound}, got {relax!r} (where relax was "
                         "not given, it was resolved for the method the settings were "
                         "made with, and dataclasses.replace keeps it: give relax with the "
                         "new method, or make new settings)")
