"""Motion-tracking enhancement (MTE, Novara, Batenburg & Scarano 2010): a reconstruction
that uses both exposures (docs/design.md §6.3).

One cycle: the measured displacement field (smoothed, resampled onto every voxel) warps
each volume onto the other exposure's time; each exposure's volume is combined with the
other one warped onto it (a particle is lit in both, a ghost rarely in both at the same
place); each image is reconstructed again from that first guess, and the new volumes
are correlated. The combination is the geometric mean by default: it zeroes a voxel
that only one exposure lights.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..options import is_integer, whole_counts
from ..piv import PIVResult
from ..piv.deformation import make_deformer
from ..piv.interpolate import resample
from ..reconstruction import ProjectionOperator, ReconstructionSettings, run_reconstruction

COMBINATIONS = ("geometric", "mean", "min")


@dataclass(frozen=True)
class MTESettings:
    """Options of :func:`motion_tracking_enhancement`.

    Attributes
    ----------
    cycles
        Warp, combine, re-reconstruct and correlate cycles (0, the default: off; one
        cycle is measured in docs/design.md §6.3).
    iterations
        Reconstruction iterations of each exposure per cycle, from the combined guess.
    combine
        ``"geometric"`` (default: ``sqrt(E_a E_b')``, zero where either is zero),
        ``"mean"`` (Novara et al.'s arithmetic mean) or ``"min"``.
    smooth
        Gaussian smoothing of the displacement field before it warps the volumes, in
        vector spacings (0: none): a wrong vector must not drag particles away.
    """

    cycles: int = 0
    iterations: int = 10
    combine: str = "geometric"
    smooth: float = 1.0

    def __post_init__(self) -> None:
        whole_counts(self, ("cycles", "iterations"))
        if not is_integer(self.cycles) or self.cycles < 0:
            raise ValueError(f"MTE cycles must be a non-negative integer, got {self.cycles!r}")
        if not is_integer(self.iterations) or self.iterations < 1:
            raise ValueError(f"MTE iterations must be a positive integer, got "
                             f"{self.iterations!r}")
        if self.combine not in COMBINATIONS:
            raise ValueError(f"MTE combine must be one of {COMBINATIONS}, got "
                             f"{self.combine!r}")
        if not (np.isfinite(self.smooth) and self.smooth >= 0):
            raise ValueError(f"MTE smooth must be a non-negative number of vector spacings, "
                             f"got {self.smooth!r}")


def dense_displacement(piv: PIVResult, shape: tuple[int, int, int], smooth: float = 0.0
                       ) -> np.ndarray:
    """The displacement on every voxel, ``(3, nz, ny, nx)`` float32 as ``(dz, dy, dx)``.

    Masked (NaN) vectors count as 0; ``smooth`` is a Gaussian filter in vector spacings;
    the field is resampled by cubic splines (extrapolated linearly beyond the outermost
    window centres).
    """
    field = np.nan_to_num(np.stack([piv.w, piv.v, piv.u]).astype(np.float64))
    if smooth > 0:
        field = np.stack([ndimage.gaussian_filter(c, smooth, mode="nearest") for c in field])
    target = tuple(np.arange(n, dtype=float) for n in shape)
    return resample(field, (piv.z, piv.y, piv.x), target, dtype=np.float32)


def combine_volumes(own: np.ndarray, other: np.ndarray, how: str) -> np.ndarray:
    """An exposure's volume combined with the other one warped onto its time."""
    if how == "geometric":
        return np.sqrt(own * other)
    if how == "mean":
        return 0.5 * (own + other)
    if how == "min":
        return np.minimum(own, other)
    raise ValueError(f"MTE combine must be one of {COMBINATIONS}, got {how!r}")


def exchange(vol_a: np.ndarray, vol_b: np.ndarray, displacement: np.ndarray, queue=None
             ) -> tuple[np.ndarray, np.ndarray]:
    """``vol_b`` warped back onto the first exposure's time and ``vol_a`` forward onto the
    second's (cubic B-spline, on ``queue``'s device, the default one for ``None``, or with SciPy
    for ``False``), clipped
    at 0: ``b(p + d(p))`` and ``a(p - d(p))``."""
    deformer = make_deformer(3, queue)
    field = deformer.field(displacement)
    b_at_a = deformer(deformer.prepare(vol_b), field, 1.0)
    a_at_b = deformer(deformer.prepare(vol_a), field, -1.0)
    return np.clip(b_at_a, 0, None), np.clip(a_at_b, 0, None)


def motion_tracking_enhancement(raw_a, raw_b, projector: ProjectionOperator, vol_a, vol_b,
                                piv: PIVResult, settings: ReconstructionSettings,
                                mte: MTESettings, correlate: Callable[..., PIVResult]):
    """Refine two reconstructions and their displacement with both exposures.

    Parameters
    ----------
    raw_a, raw_b
        The raw images.
    projector
        The projector both volumes were reconstructed with.
    vol_a, vol_b, piv
        The single-frame volumes and their displacement field.
    settings
        The reconstruction settings of the single-frame volumes (method, background,
        threshold...); each cycle uses them with ``mte.iterations`` and the combined start.
    mte
        The cycles' options.
    correlate
        ``correlate(vol_a, vol_b) -> PIVResult``, the same correlation as the single frame.

    Returns
    -------
    tuple
        ``(vol_a, vol_b, piv, infos, seconds)``: the last cycle's volumes, field and
        reconstruction infos (``None`` with no cycle), and the cycles' wall time.
    """
    t0, infos = time.perf_counter(), (None, None)
    for _ in range(mte.cycles):
        d = dense_displacement(piv, projector.grid.shape, mte.smooth)
        b_at_a, a_at_b = exchange(vol_a, vol_b, d, projector.queue)
        out = []
        for raw, own, other in ((raw_a, vol_a, b_at_a), (raw_b, vol_b, a_at_b)):
            cycle = dataclasses.replace(settings, iterations=mte.iterations,
                                        start=combine_volumes(own, other, mte.combine))
            out.append(run_reconstruction(raw, projector, cycle))
        (vol_a, info_a), (vol_b, info_b) = out
        infos = (info_a, info_b)
        piv = correlate(vol_a, vol_b)
    return vol_a, vol_b, piv, infos, time.perf_counter() - t0
