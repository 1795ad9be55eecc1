"""The sums behind a particle's centroid along its line of sight (docs/design.md §7.4):
trilinear samples of a volume over a tube around each particle's line, their total and
their total weighted by the position along the line
(:meth:`plenocl.piv.refinement.SightLines.centres`).

:func:`host_tube_sums` computes them with SciPy's ``map_coordinates`` (the reference);
:class:`DeviceTubeSums` with ``kernels/sightline.cl`` on an OpenCL device, one work-group
per particle, the samples taken where they are needed instead of as a ``(particles,
samples, 3)`` array of coordinates on the host.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..opencl.program import KernelSet, group_size

__all__ = ["DeviceTubeSums", "host_tube_sums", "tube_points"]

def tube_points(centre: np.ndarray, frames: np.ndarray, local: np.ndarray) -> np.ndarray:
    """``(N, S, 3)`` voxel indices ``(x, y, z)`` of the samples: ``centre`` ``(N, 3)``
    plus each particle's frame ``(N, 3, 3)`` (local offset to index offset) times the
    local offsets ``(S, 3)``."""
    return centre[:, None, :] + np.einsum("nij,sj->nsi", frames, local)


def host_tube_sums(vol: np.ndarray, centre: np.ndarray, frames: np.ndarray,
                   local: np.ndarray) -> np.ndarray:
    """``(N, 2)``: per particle the sum of the samples (trilinear, 0 outside the volume,
    clipped at 0) and their sum weighted by ``local[:, 2]``, the position along the
    line; the samples at :func:`tube_points`."""
    n = len(centre)
    if not n:
        return np.zeros((0, 2))
    index = tube_points(centre, frames, local).reshape(-1, 3)
    values = ndimage.map_coordinates(np.asarray(vol, np.float32), index[:, ::-1].T,
                                     order=1, mode="constant").reshape(n, -1)
    values = np.maximum(values, 0.0)
    return np.column_stack([values.sum(axis=1), values @ local[:, 2]])


class DeviceTubeSums:
    """:func:`host_tube_sums` on ``queue``'s device (``kernels/sightline.cl``).

    Parameters
    ----------
    queue
        The device's queue.
    group
        Work-items per particle (a power of two); ``None``: 1 on a CPU,
        :data:`plenocl.opencl.program.GPU_GROUP` elsewhere.
    """

    def __init__(self, queue, group: int | None = None) -> None:
        self.group = group_size(queue, group)
        self._k = KernelSet(queue, "sightline.cl", ["tube_sums"], [f"-DPL_GROUP={self.group}"],
                            looping=["tube_sums"])

    @property
    def queue(self):
        """The device's queue."""
        return self._k.queue

    def __call__(self, vol: np.ndarray, centre: np.ndarray, frames: np.ndarray,
                 local: np.ndarray) -> np.ndarray:
        """As :func:`host_tube_sums` (float32 sums, as float64); ``vol`` a host array or
        a float32 device array on this queue (uploaded once for several calls)."""
        n = len(centre)
        if not n:
            return np.zeros((0, 2))
        vol = self._k.on_device(vol)
        nz, ny, nx = vol.shape
        out = self._k.array(2 * n)
        dev = [vol] + [self._k.to_device(np.asarray(a, np.float32))
                       for a in (centre, frames, local)]
        self._k.launch("tube_sums", (n * self.group,), dev[0], np.int32(nz), np.int32(ny),
                       np.int32(nx), *dev[1:], np.int32(len(local)), out,
                       local_size=(self.group,))
        return out.get().reshape(n, 2).astype(np.float64)
