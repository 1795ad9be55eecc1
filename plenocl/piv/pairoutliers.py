"""Matched particle pairs that disagree with their neighbours (docs/design.md §7.4 item 8).

The particle refinement (:mod:`plenocl.piv.refinement`) averages the pairs of each interrogation
window, each weighed by its fit's uncertainty. A wrongly matched pair (a ghost, or two
different particles) whose fit is confident then carries a window alone: in a window of
three to five pairs it takes 90-97 % of the weight, and no test inside the window can
tell it from its few, poorly known neighbours. Across the volume it can: its
displacement lies many of its own standard deviations from what the pairs around it say
there.

This is the normalised median test of Westerweel & Scarano (2005), in the form Duncan et
al. (2010) gave it for scattered particle data, with the displacement gradient of the
flow taken out: each pair's :data:`NEIGHBOURS` nearest pairs are moved to its midpoint
along the local gradient of a field (the window means), and the pair is an outlier where
a lateral component lies more than :data:`THRESHOLD` times the combined scale from their
median; that scale adds in quadrature the neighbours' robust spread (1.4826 times their
median absolute deviation), the pair's own standard uncertainty and
:data:`plenocl.piv.refinement.WEIGHT_FLOOR`'s lateral part. A poorly known pair (a particle in the
focal zone, whose fit knows its lateral position to 0.15-0.2 voxel) is judged by that
uncertainty, and in a sheared flow the neighbours' spread grows with what the gradient
leaves.

Only the lateral components are tested: one camera's depth is 10-20 times less certain,
and the refinement takes it from the pairs that see it (docs/design.md §7.1).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial import cKDTree

from ..vectorfield import PIVResult

#: The nearest pairs each pair is compared with (Duncan et al. use the 8-16 neighbours
#: of a Delaunay triangulation in 3-D; 16 keeps the median robust to a few of them being
#: focal-zone pairs of 0.2-voxel scatter).
NEIGHBOURS = 16
#: A pair is an outlier beyond this many combined scales from its neighbours' median.
#: At the paper's optics under the error budget's rotation (three whole-sensor scenes,
#: docs/design.md §7.4 item 8, with its other two changes): 3.0 left out 0.9 % of the
#: pairs, 2.5 left out 1.8 %; the vectors erred 0.0137 and 0.0132 voxel laterally (0.0149
#: without the test). The small demo's boundary layer: 6.9, 7.0 and 6.8 % of U∞.
THRESHOLD = 2.5
#: Lateral floor (voxels) added in quadrature to every pair's scale: the scatter of the
#: best-fitted pairs' displacements at the paper's optics, the window means' weights'
#: lateral floor too (:data:`plenocl.piv.refinement.WEIGHT_FLOOR` takes it from here).
FLOOR = 0.02
#: A normal distribution's standard deviation over its median absolute deviation.
MAD_SIGMA = 1.4826


def field_gradient(field: PIVResult, points: np.ndarray) -> np.ndarray:
    """The displacement gradient ``(N, 3, 3)`` (component u, v, w; derivative along x, y,
    z, voxel per voxel) of ``field`` at ``points`` ``(N, 3)`` ``(x, y, z)`` voxels: the
    central differences between its window centres (one-sided at its faces), trilinear
    between centres and extended linearly beyond them; NaN vectors count as 0. An axis
    with a single window has no gradient along it."""
    axes = (field.z, field.y, field.x)
    grad = np.zeros((len(points), 3, 3))
    along = [k for k, a in enumerate(axes) if len(a) > 1]  # 0: z, 1: y, 2: x
    if not along:
        return grad
    sub = [np.asarray(axes[k], float) for k in along]
    zyx = np.asarray(points, float)[:, ::-1][:, along]
    for c, comp in enumerate((field.u, field.v, field.w)):
        values = np.nan_to_num(np.asarray(comp, float)).reshape([len(a) for a in sub])
        parts = np.gradient(values, *sub)
        for k, part in zip(along, parts if len(sub) > 1 else [parts]):
            look = RegularGridInterpolator(sub, part, bounds_error=False, fill_value=None)
            grad[:, c, 2 - k] = look(zyx)
    return grad


def neighbour_outliers(midpoints: np.ndarray, displacements: np.ndarray,
                       sigma: np.ndarray | None, field: PIVResult,
                       neighbours: int = NEIGHBOURS, threshold: float = THRESHOLD
                       ) -> np.ndarray:
    """Which pairs ``(N,)`` disagree with their neighbours laterally (module docstring).

    Parameters
    ----------
    midpoints, displacements
        ``(N, 3)`` ``(x, y, z)`` voxels.
    sigma
        ``(N, 3)`` each displacement's standard uncertainty (voxels); ``None``: every
        pair alike (only the neighbours' spread and :data:`FLOOR`).
    field
        The displacement field whose gradient moves the neighbours to each pair.
    neighbours, threshold
        :data:`NEIGHBOURS` and :data:`THRESHOLD`.

    With fewer than ``neighbours + 1`` pairs nothing is left out: too few to judge.
    """
    if not threshold > 0 or neighbours < 2:
        raise ValueError(f"neighbour_outliers got threshold={threshold}, neighbours="
                         f"{neighbours}: give a positive threshold ({THRESHOLD:g}) and at "
                         f"least 2 neighbours ({NEIGHBOURS})")
    mid, disp = np.asarray(midpoints, float), np.asarray(displacements, float)
    if len(mid) <= neighbours:
        return np.zeros(len(mid), bool)
    _, near = cKDTree(mid).query(mid, neighbours + 1)
    near = near[:, 1:]  # the pair itself is its own nearest
    grad = field_gradient(field, mid)
    moved = disp[near] + np.einsum("nij,nkj->nki", grad, mid[:, None, :] - mid[near])
    median = np.median(moved, axis=1)
    spread = MAD_SIGMA * np.median(np.abs(moved - median[:, None]), axis=1)
    own = np.zeros_like(disp) if sigma is None else np.asarray(sigma, float)
    scale = np.sqrt(spread ** 2 + own ** 2 + FLOOR ** 2)
    off = np.abs(disp - median) / scale
    return np.any(off[:, :2] > threshold, axis=1)
