"""A volume's local maxima on an OpenCL device (``kernels/peaks.cl``): the candidates of
:func:`plenocl.peaks.find_particles`, which the particle refinement takes from both
reconstructed volumes of every pair (docs/design.md §7.1).

:class:`DeviceMaxima` replaces the host's maximum filter over the whole volume
(:func:`plenocl.peaks.host_maxima`, the reference; SciPy on one core) by one work-item per
voxel; only the candidates' flat indices come back, sorted, so the peaks and their order
are the host's exactly.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cl_array

from ..opencl.program import KernelSet
from ..opencl.volume import DeviceVolume

__all__ = ["DeviceMaxima"]

#: Candidate slots of the first launch per voxel of the volume (grown when more are
#: found, and kept from one volume to the next).
START_SHARE = 1 / 256


class DeviceMaxima:
    """:func:`plenocl.peaks.host_maxima` on ``queue``'s device.

    Parameters
    ----------
    queue
        The device's queue (the kernel is built once per context).
    """

    def __init__(self, queue) -> None:
        self._k = KernelSet(queue, "peaks.cl", ["local_maxima"])
        self._found: cl_array.Array | None = None
        self._count = self._k.to_device(np.zeros(1, np.int32))

    @property
    def queue(self):
        """The device's queue."""
        return self._k.queue

    def __call__(self, vol, floor: float, reach: int = 1) -> np.ndarray:
        """The flat indices (C order, ascending) of ``vol``'s voxels above ``floor`` that
        no voxel within ``reach`` per axis exceeds (0 beyond the faces); ``vol`` a
        ``(nz, ny, nx)`` host array, a float32 device array or a
        :class:`~plenocl.opencl.volume.DeviceVolume` (read where it is, on this context)."""
        if isinstance(vol, DeviceVolume) and vol.array.context == self.queue.context:
            vol = vol.array
        if vol.size >= 2 ** 31:
            raise ValueError(f"a volume of {vol.size} voxels is too large for the device's "
                             "local maxima (at most 2^31 - 1); find its particles on the "
                             "host (queue=False)")
        dev = self._k.on_device(vol)
        nz, ny, nx = vol.shape
        capacity = max(1024, int(vol.size * START_SHARE))
        while True:
            found = self._slots(capacity)
            self._count.fill(0)
            self._k.launch("local_maxima", (nx, ny, nz), dev, *map(np.int32, (nz, ny, nx, reach)),
                           np.float32(floor), self._count, found, np.int32(capacity))
            count = int(self._count.get()[0])
            if count <= capacity:
                return np.sort(found[:count].get()) if count else np.zeros(0, np.int64)
            capacity = count

    def _slots(self, capacity: int) -> cl_array.Array:
        """At least ``capacity`` int32 slots (the kept buffer, grown as needed)."""
        if self._found is None or self._found.size < capacity:
            self._found = self._k.array(capacity, np.int32)
        return self._found
