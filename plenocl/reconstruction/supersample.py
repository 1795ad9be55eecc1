"""Lateral supersampling of a reconstruction (docs/design.md §6.4): the volume is
reconstructed on a grid with ``f x f`` lateral sub-voxels per voxel and summed back.

The paper's voxel (0.18 mm) images onto about one microlens, so on that grid a particle
between two voxel centres can only be drawn as a mixture of two voxels whose light
fields differ by a whole lens; the solver then explains the particle's image with light
at the wrong depth. Sub-voxels place it within a third of a lens, and the depth follows
(``benchmarks/accuracy.py``).
"""

from __future__ import annotations

import numpy as np

#: Largest accepted factor (memory and time grow as its square).
MAX_SUPERSAMPLE = 4


def bin_lateral(vol: np.ndarray, factor: int) -> np.ndarray:
    """Sum each ``factor x factor`` lateral block: ``(nz, ny f, nx f)`` to ``(nz, ny, nx)``
    (intensity conserved)."""
    nz, nyf, nxf = vol.shape
    if nyf % factor or nxf % factor:
        raise ValueError(f"a {vol.shape} volume does not bin by {factor} laterally")
    out = vol.reshape(nz, nyf // factor, factor, nxf // factor, factor).sum(axis=(2, 4))
    return out.astype(np.float32)


def spread_lateral(vol: np.ndarray, factor: int) -> np.ndarray:
    """Each voxel's intensity shared equally by its ``factor x factor`` sub-voxels: the
    inverse of :func:`bin_lateral` for a volume that is flat within each voxel."""
    v = np.asarray(vol, np.float32) / np.float32(factor * factor)
    return np.repeat(np.repeat(v, factor, axis=1), factor, axis=2)
