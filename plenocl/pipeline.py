"""One image pair through the whole chain: the default processing a user (or a batch
run) applies to each pair of raw images (docs/design.md §9).

:func:`process_pair` preprocesses and reconstructs both exposures with one projector
(its sensitivity and kernels are reused) and correlates the volumes. The steps stay
available on their own (:func:`plenocl.reconstruct`, :func:`plenocl.piv3d`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .piv import PIVResult, piv3d
from .reconstruction import (
    ProjectionOperator,
    ReconstructionInfo,
    ReconstructionSettings,
    run_reconstruction,
)


@dataclass
class PairResult:
    """What :func:`process_pair` made of one image pair.

    Attributes
    ----------
    vol_a, vol_b
        The reconstructed volumes ``(nz, ny, nx)`` (image intensity units).
    piv
        The displacement field between them (voxels; :class:`plenocl.PIVResult`).
    info_a, info_b
        What each reconstruction did (iterations, residuals, time).
    seconds
        Wall time per stage: ``reconstruct_a``, ``reconstruct_b``, ``piv``.
    """

    vol_a: np.ndarray
    vol_b: np.ndarray
    piv: PIVResult
    info_a: ReconstructionInfo
    info_b: ReconstructionInfo
    seconds: dict[str, float] = field(default_factory=dict)


def process_pair(raw_a, raw_b, projector: ProjectionOperator, *,
                 settings: ReconstructionSettings | None = None,
                 piv_options: dict | None = None) -> PairResult:
    """Reconstruct two raw images with one projector and correlate the volumes.

    Parameters
    ----------
    raw_a, raw_b
        The raw images of the two exposures (``(rows, cols)`` of the projector's camera).
    projector
        A :class:`plenocl.Projector` (or any
        :class:`plenocl.reconstruction.ProjectionOperator`), reused for both images.
    settings
        Reconstruction options (:class:`plenocl.reconstruction.ReconstructionSettings`);
        by default MLEM, 30 iterations, the median background removed and pixels within
        4 noise deviations of it dark, as :func:`plenocl.reconstruct`.
    piv_options
        Keyword arguments of :func:`plenocl.piv3d` (by default the windows are fitted to
        the volume's shape, and the volumes are deformed on the projector's device).

    Returns
    -------
    PairResult
        Both volumes, the displacement field, the reconstructions' info and stage times.
    """
    settings = ReconstructionSettings() if settings is None else settings
    seconds, out = {}, {}
    for tag, raw in (("a", raw_a), ("b", raw_b)):
        t0 = time.perf_counter()
        out[tag] = run_reconstruction(raw, projector, settings)
        seconds[f"reconstruct_{tag}"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    options = {"queue": projector.queue, **(piv_options or {})}
    res = piv3d(out["a"][0], out["b"][0], **options)
    seconds["piv"] = time.perf_counter() - t0
    return PairResult(out["a"][0], out["b"][0], res, out["a"][1], out["b"][1], seconds)
