"""The hexagonal cells of the image fit's ray bundle (docs/design.md §7.2): which lenses
share a ray that meets a hexagonal array at ``x``, and how much each gets.

A ray belongs to the lens whose centre is nearest (the hexagon around it, as the
simulator traces it, design.md §2). The lenses are numbered on the array's axial lattice
(:meth:`plenocl.Camera.on_lens_lattice`), an affine lattice fitted to the centres, so
the nearest centre lies at a corner of the lattice cell ``floor(q), floor(r)`` that
holds ``x`` (the two rows around the point). Near a cell edge the ray is shared, so the
image is smooth in ``x``: each neighbour ``j`` of the nearest lens ``a`` gets the weight::

    W_j = (R - δ_j) / (R + δ_j) for δ_j < R (else 0),   δ_j = (|x - j|² - |x - a|²) / (2p²)

relative to ``W_a = 1`` (``R``: the ramp in pitches, ``p``: the fitted pitch; ``δ_j`` is
the distance of ``x`` from the bisector of ``a`` and ``j``, in pitches, for a regular
array), and the shares are the weights normalised. With one neighbour in the ramp this is
the linear ramp ``w_j = 1/2 - δ_j/(2R)`` of the rectangular cells; near a vertex the three
lenses' shares follow their pairwise ratios. As ``δ`` takes the power distances over one
constant ``p²``, the ratio of two lenses' weights is the same whichever of them is
nearest, and the shares are continuous across every cell edge for ``R`` up to half a
pitch (:data:`HEX_RAMP_MAX`, a little less): there at most three neighbours share a ray
(those with ``(x - a) · (j - a) > 0``), so four lens choices hold every ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera.lattice import lattice_fit

#: Widest ramp (pitches) of the hexagonal cells: beyond half a pitch a fourth neighbour
#: or a lens beyond the neighbours would get a share, so wider ramps are cut to this.
HEX_RAMP_MAX = 0.45
#: Corners of the lattice cell that holds a point (axial steps ``(q, r)``).
CORNERS = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])


@dataclass(frozen=True)
class HexCells:
    """The hexagonal cells of a fitted axial lattice.

    ``model`` ``(3, 2)``: ``[q, r, 1] @ model`` is the position (mm) of the lens at axial
    indices ``(q, r)`` (of the axial view); ``steps`` ``(6, 2)`` int: the axial steps to
    the six nearest neighbours; ``pitch``: their mean length (mm).
    """

    model: np.ndarray
    steps: np.ndarray
    pitch: float

    @classmethod
    def fit(cls, lenses: np.ndarray) -> HexCells:
        """The cells of the lenses ``(rows, cols, 2)`` (mm, axial view, NaN: none)."""
        model = lattice_fit(lenses)
        cands = np.array([[1, 0], [0, 1], [1, -1], [1, 1]])
        length = np.hypot(*(cands @ model[:2]).T)
        near = cands[np.argsort(length, kind="stable")[:3]]
        pitch = float(np.sort(length)[:3].mean())
        return cls(model, np.vstack([near, -near]), pitch)

    @property
    def gram(self) -> np.ndarray:
        """``(2, 2)`` metric of the axial indices in pitches²: ``|v|² = v G vᵀ``."""
        m = self.model[:2] / self.pitch
        return m @ m.T

    def nearest(self, lattice: np.ndarray) -> np.ndarray:
        """Axial indices ``(..., 2)`` int of the fitted lens nearest each point given by
        its fractional axial indices ``lattice`` ``(..., 2)``: the nearest of the four
        corners of the lattice cell that holds it (the first on a tie)."""
        base = np.floor(lattice)
        off = (lattice - base)[..., None, :] - CORNERS  # (..., 4, 2)
        d2 = np.einsum("...ki,ij,...kj->...k", off, self.gram, off)
        return base.astype(np.int64) + CORNERS[np.argmin(d2, axis=-1)]

    def shares(self, lattice: np.ndarray, ramp: np.ndarray | float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The lenses sharing each ray and their shares.

        Parameters
        ----------
        lattice
            ``(..., 2)`` fractional axial indices of the rays' array-plane points.
        ramp
            Ramp half-width (pitches), broadcastable to ``lattice[..., 0]``; at most
            :data:`HEX_RAMP_MAX` (the caller cuts it).

        Returns
        -------
        index : ``(..., 7, 2)`` int
            Axial indices of the nearest lens and its six neighbours.
        share, dshare_dr : ``(..., 7)``
            Each lens's share of the ray (they sum to 1) and its derivative by the ramp.
        dshare_dx : ``(..., 7, 2)``
            The shares' derivatives by the array-plane point (per mm).
        """
        a = self.nearest(lattice)
        gram = self.gram
        v = lattice - a  # (..., 2) from the nearest lens, axial units
        g2 = np.einsum("ki,ij,kj->k", self.steps, gram, self.steps)  # (6,)
        delta = (g2 - 2 * v @ gram @ self.steps.T) / 2  # (..., 6) pitches
        r = np.asarray(ramp)[..., None]
        lit = delta < r
        den = np.where(lit, r + delta, 1.0)
        w = np.where(lit, (r - delta) / den, 0.0)
        dw_dd = np.where(lit, -2 * r / den**2, 0.0)
        dw_dr = np.where(lit, 2 * delta / den**2, 0.0)
        # d delta / dx = -(j - a) / p² with j - a = step @ model[:2] in mm
        ddelta_dx = -(self.steps @ self.model[:2]) / self.pitch**2  # (6, 2)
        return (np.concatenate([a[..., None, :], a[..., None, :] + self.steps], axis=-2),
                *_normalised(w, dw_dd[..., None] * ddelta_dx, dw_dr))


def _normalised(w: np.ndarray, dw_dx: np.ndarray, dw_dr: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The shares ``(1, w) / (1 + Σ w)`` of the nearest lens and its neighbours and their
    derivatives by the point ``(..., 7, 2)`` and by the ramp ``(..., 7)``, from the
    neighbours' weights ``w`` ``(..., 6)`` and theirs."""
    total = 1 + w.sum(axis=-1, keepdims=True)
    weight = np.concatenate([np.ones_like(total), w], axis=-1)
    share = weight / total
    dweight_dx = np.concatenate([np.zeros_like(dw_dx[..., :1, :]), dw_dx], axis=-2)
    dweight_dr = np.concatenate([np.zeros_like(total), dw_dr], axis=-1)
    dshare_dx = (dweight_dx - share[..., None] * dweight_dx.sum(axis=-2, keepdims=True)
                 ) / total[..., None]
    dshare_dr = (dweight_dr - share * dweight_dr.sum(axis=-1, keepdims=True)) / total
    return share, dshare_dx, dshare_dr
